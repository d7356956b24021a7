"""OpenCV's ECC alignment (``cv2.findTransformECC``, MOTION_AFFINE) of many templates in one
compiled (numba) loop, for :func:`~tumblenav.frontends.stereo_images.refine.refine_affine`.

Why by hand: the image front end refines every tracked and every matched feature (~245 a
stereo pair at 120 features) by an affine ECC warp of a 15 x 15 template, and
``cv2.findTransformECC`` takes one template per call. Per call, OpenCV's fixed costs (argument
conversion, its dozen intermediate images and matrices) and the Python loop around it (the
crop's float copy, the warp's set-up) outweighed the arithmetic on 225 pixels: ~0.09 ms in
OpenCV and ~0.04 ms in Python a feature, 33 of the front end's 44 ms a pair on one core
(benchmarks/image_frontend.py). Here one call refines all the features of a frame, ~13 us a
feature.

What it computes: for each feature ``i``, the iteration of OpenCV 5.0.0's
``findTransformECC(templates[i], image[y0:y1, x0:x1] as float32, warps[i], MOTION_AFFINE,
(COUNT | EPS, max_iter, eps), inputMask=None, gaussFiltSize=1)`` (modules/video/src/ecc.cpp,
``findTransformECCWithMask``; its warpAffine, modules/imgproc/src/warp_kernels.simd.hpp), step
by step. It is the forward-additive ECC maximisation of Evangelidis & Psarakis 2008 (IEEE TPAMI
30(10), "Parametric image alignment using enhanced correlation coefficient maximization",
Sec. 3); the paper's text was not at hand here, so its equation numbers are not cited: OpenCV's
ecc.cpp is the reference followed, line by line:

1. the crop's gradients by central differences (OpenCV: ``filter2D`` with [-0.5, 0, 0.5] and
   its default border BORDER_REFLECT_101, so they are 0 in the crop's first and last
   column / row); ``gaussFiltSize=1``: no smoothing;
2. per iteration, the crop and its gradients warped back onto the template's grid by the
   current warp ``W`` (``x' = W [x, y, 1]``, crop pixels): bilinear, 0 outside the crop
   (``warpAffine``, INTER_LINEAR | WARP_INVERSE_MAP, BORDER_CONSTANT), and the mask of the
   template pixels whose nearest crop pixel lies inside the crop (``warpAffine`` of a
   ones-image, INTER_NEAREST);
3. zero-mean template ``t`` and warped image ``v`` over the mask (their means and norms over
   the mask only; OpenCV leaves ``v`` unchanged off the mask and sets ``t`` to 0 there);
4. the Jacobian of the warped image with respect to the six parameters, per pixel
   ``G = [gx x, gy x, gx y, gy y, gx, gy]`` (warped gradients, template pixel x, y) over all
   the pixels, and the Hessian ``H = G^T G``;
5. the correlation coefficient ``rho = t.v / (|t| |v|)`` (the returned score is that of the
   last iteration, computed before its update), then the ECC update (the case of a positive
   denominator, the one OpenCV implements):
   ``lambda = (|v|^2 - v^T G H^-1 G^T v) / (t.v - t^T G H^-1 G^T v)`` and
   ``dp = H^-1 G^T (lambda t - v)``, added to ``W`` (float32, as OpenCV's warp matrix);
6. stop after ``max_iter`` iterations or when ``|rho - rho_previous| < eps``. A NaN ``rho``
   (no pixel of the mask, or a flat warped patch) or ``lambda``'s denominator <= 0 ends the
   feature as a failure, where OpenCV throws (``StsNoConv``).

Differences from OpenCV, all rounding: the mapped coordinates, the bilinear weights, the sums
and the 6 x 6 solve (LU with partial pivoting; a pivot below 10 FLT_EPSILON makes ``H^-1``
zero, as OpenCV's ``invert``) are float64 here, float32 (or mixed) there. Typically the
refined centres agree to 1e-6 px (``tests/test_image_frontend.py`` checks 2e-3 px). Rounding
matters only where ``H`` is ill-conditioned (a patch textured in about one direction): ECC
then creeps along the flat direction for many iterations, the stopping rule fires at another
iteration, and the two end apart. Over the 31,969 refinements of benchmarks/image_frontend.py
at 9 m (130 pairs): median 6e-7 px, 99th percentile 1.4e-5 px, 40 beyond 1e-3 px (at most
0.44 px; 38 of them took 8-20 iterations, in the other two the stopping rule fired one
iteration apart), and no accept or failure decision differed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["ECC_FLAT", "ECC_MINIMISED", "ECC_OK", "ecc_affine"]

# a feature's outcome (OpenCV: the returned score, or its StsNoConv exception)
ECC_OK = 0
ECC_FLAT = 1  # rho is NaN: no template pixel maps into the crop, or the warped patch is flat
ECC_MINIMISED = 2  # lambda's denominator <= 0: the step would minimise the correlation

_PIVOT_EPS = 10.0 * float(np.finfo(np.float32).eps)  # OpenCV hal::LU32f's singularity test


@njit(cache=True, error_model="numpy")
def _crop_gradients(image, x0, y0, ch, cw, buf):
    """Step 1: the crop ``image[y0:y0+ch, x0:x0+cw]`` into ``buf[:, :, 0]`` and its central
    differences along x and y into ``buf[:, :, 1]``, ``buf[:, :, 2]`` (BORDER_REFLECT_101:
    0 on the crop's edges)."""
    for r in range(ch):
        for c in range(cw):
            buf[r, c, 0] = float(image[y0 + r, x0 + c])
    for r in range(ch):
        for c in range(cw):
            if 0 < c < cw - 1:
                buf[r, c, 1] = 0.5 * (buf[r, c + 1, 0] - buf[r, c - 1, 0])
            else:
                buf[r, c, 1] = 0.0
            if 0 < r < ch - 1:
                buf[r, c, 2] = 0.5 * (buf[r + 1, c, 0] - buf[r - 1, c, 0])
            else:
                buf[r, c, 2] = 0.0


@njit(cache=True, error_model="numpy")
def _lerp(p00, p01, p10, p11, fx, fy):
    """Bilinear interpolation in OpenCV's order of operations (warp_common.scalar.hpp)."""
    v0 = p00 + fx * (p01 - p00)
    v1 = p10 + fx * (p11 - p10)
    return v0 + fy * (v1 - v0)


@njit(cache=True, error_model="numpy")
def _warp_back(buf, ch, cw, W, hs, ws, v, gx, gy, inside):
    """Step 2: the crop and its gradients (``buf``, ch x cw x 3) at the template's pixels
    (hs x ws) mapped by the warp ``W`` (2, 3) into ``v``, ``gx``, ``gy`` (row order), bilinear, 0 outside the crop (warpAffine, INTER_LINEAR, BORDER_CONSTANT 0: a point
    more than one pixel outside is 0, a nearer one blends the crop's edge with 0), and the mask
    ``inside`` of the pixels whose nearest crop pixel is in the crop (INTER_NEAREST)."""
    a00, a01, a02 = float(W[0, 0]), float(W[0, 1]), float(W[0, 2])
    a10, a11, a12 = float(W[1, 0]), float(W[1, 1]), float(W[1, 2])
    # when the template's four corners map into [0, cw - 1) x [0, ch - 1) (a hair inside: the
    # rounding of the pixels between them), so does every pixel (an affine map keeps the
    # hull): all four bilinear neighbours lie in the crop, and so does the nearest
    interior = True
    for cr in range(4):
        c = 0.0 if cr % 2 == 0 else ws - 1.0
        r = 0.0 if cr < 2 else hs - 1.0
        sx = a00 * c + a01 * r + a02
        sy = a10 * c + a11 * r + a12
        if not (1e-9 <= sx <= cw - 1 - 1e-9 and 1e-9 <= sy <= ch - 1 - 1e-9):
            interior = False
    for r in range(hs):
        for c in range(ws):
            k = r * ws + c
            sx = a00 * c + a01 * r + a02
            sy = a10 * c + a11 * r + a12
            if interior:
                ix = int(math.floor(sx))
                iy = int(math.floor(sy))
                fx = sx - ix
                fy = sy - iy
                for j in range(3):
                    p00, p01 = buf[iy, ix, j], buf[iy, ix + 1, j]
                    p10, p11 = buf[iy + 1, ix, j], buf[iy + 1, ix + 1, j]
                    val = _lerp(p00, p01, p10, p11, fx, fy)
                    if j == 0:
                        v[k] = val
                    elif j == 1:
                        gx[k] = val
                    else:
                        gy[k] = val
                inside[k] = True
                continue
            v[k] = gx[k] = gy[k] = 0.0
            inside[k] = False
            if not (abs(sx) < 1e9 and abs(sy) < 1e9):  # NaN or far: outside
                continue
            nx = np.rint(sx)  # INTER_NEAREST (cvRound: half to even)
            ny = np.rint(sy)
            inside[k] = 0 <= nx < cw and 0 <= ny < ch
            ix = int(math.floor(sx))
            iy = int(math.floor(sy))
            if ix < -1 or ix >= cw or iy < -1 or iy >= ch:
                continue
            fx = sx - ix
            fy = sy - iy
            in_x0, in_x1 = ix >= 0, ix + 1 < cw
            in_y0, in_y1 = iy >= 0, iy + 1 < ch
            for j in range(3):
                p00 = buf[iy, ix, j] if (in_x0 and in_y0) else 0.0
                p01 = buf[iy, ix + 1, j] if (in_x1 and in_y0) else 0.0
                p10 = buf[iy + 1, ix, j] if (in_x0 and in_y1) else 0.0
                p11 = buf[iy + 1, ix + 1, j] if (in_x1 and in_y1) else 0.0
                val = _lerp(p00, p01, p10, p11, fx, fy)
                if j == 0:
                    v[k] = val
                elif j == 1:
                    gx[k] = val
                else:
                    gy[k] = val


@njit(cache=True, error_model="numpy")
def _normal_equations(tmpl, v, gx, gy, inside, mv, mt, H, ip, tp):
    """Steps 3-4 of the module: with ``v`` the warped crop, ``t`` the template (``tmpl``),
    zero-mean over the mask as OpenCV makes them (``v - mv`` on the mask, ``v`` off it;
    ``t - mt`` on it, 0 off it), and the Jacobian rows ``G = [gx x, gy x, gx y, gy y, gx, gy]``
    of all the pixels: fills ``H = G^T G``, ``ip = G^T v``, ``tp = G^T t`` and returns
    ``|v|^2``, ``|t|^2``, ``t.v`` over the mask.

    G's entries are products of a gradient and a power of x, y, so ``H`` follows from the
    sums of gx^2, gx gy, gy^2 weighted by 1, x, y, x^2, xy, y^2 (row sums over x first):
    the same sums as OpenCV's blockwise dot products, in another order."""
    hs, ws = tmpl.shape
    vv = tt = tv = 0.0
    # totals: q1/qx/qy/qxx/qxy/qyy = sum of q weighted by 1, x, y, x^2, xy, y^2
    aa1 = aax = aay = aaxx = aaxy = aayy = 0.0  # gx^2
    ab1 = abx = aby = abxx = abxy = abyy = 0.0  # gx gy
    bb1 = bbx = bby = bbxx = bbxy = bbyy = 0.0  # gy^2
    av1 = avx = avy = bv1 = bvx = bvy = 0.0  # gx v, gy v
    at1 = atx = aty = bt1 = btx = bty = 0.0  # gx t, gy t
    for r in range(hs):
        ra1 = rax = raxx = rb1 = rbx = rbxx = rc1 = rcx = rcxx = 0.0
        rv1 = rvx = rw1 = rwx = rt1 = rtx = ru1 = rux = 0.0
        for c in range(ws):
            k = r * ws + c
            a = gx[k]
            b = gy[k]
            if inside[k]:
                vk = v[k] - mv
                tk = float(tmpl[r, c]) - mt
                vv += vk * vk
                tt += tk * tk
                tv += tk * vk
            else:
                vk = v[k]
                tk = 0.0
            x = float(c)
            q = a * a
            ra1 += q
            rax += q * x
            raxx += q * x * x
            q = a * b
            rb1 += q
            rbx += q * x
            rbxx += q * x * x
            q = b * b
            rc1 += q
            rcx += q * x
            rcxx += q * x * x
            rv1 += a * vk
            rvx += a * vk * x
            rw1 += b * vk
            rwx += b * vk * x
            rt1 += a * tk
            rtx += a * tk * x
            ru1 += b * tk
            rux += b * tk * x
        y = float(r)
        aa1 += ra1
        aax += rax
        aay += ra1 * y
        aaxx += raxx
        aaxy += rax * y
        aayy += ra1 * y * y
        ab1 += rb1
        abx += rbx
        aby += rb1 * y
        abxx += rbxx
        abxy += rbx * y
        abyy += rb1 * y * y
        bb1 += rc1
        bbx += rcx
        bby += rc1 * y
        bbxx += rcxx
        bbxy += rcx * y
        bbyy += rc1 * y * y
        av1 += rv1
        avx += rvx
        avy += rv1 * y
        bv1 += rw1
        bvx += rwx
        bvy += rw1 * y
        at1 += rt1
        atx += rtx
        aty += rt1 * y
        bt1 += ru1
        btx += rux
        bty += ru1 * y
    # G = [gx x, gy x, gx y, gy y, gx, gy] (OpenCV's image_jacobian_affine_ECC)
    H[0, 0], H[0, 1], H[0, 2], H[0, 3], H[0, 4], H[0, 5] = aaxx, abxx, aaxy, abxy, aax, abx
    H[1, 1], H[1, 2], H[1, 3], H[1, 4], H[1, 5] = bbxx, abxy, bbxy, abx, bbx
    H[2, 2], H[2, 3], H[2, 4], H[2, 5] = aayy, abyy, aay, aby
    H[3, 3], H[3, 4], H[3, 5] = bbyy, aby, bby
    H[4, 4], H[4, 5] = aa1, ab1
    H[5, 5] = bb1
    for i in range(6):
        for j in range(i):
            H[i, j] = H[j, i]
    ip[0], ip[1], ip[2], ip[3], ip[4], ip[5] = avx, bvx, avy, bvy, av1, bv1
    tp[0], tp[1], tp[2], tp[3], tp[4], tp[5] = atx, btx, aty, bty, at1, bt1
    return vv, tt, tv


@njit(cache=True, error_model="numpy")
def _solve2(H, b1, b2, x1, x2):
    """``x1 = H^-1 b1``, ``x2 = H^-1 b2`` (6 x 6, LU with partial pivoting on a copy); both 0
    when a pivot is below OpenCV's singularity threshold (its ``invert`` then returns 0)."""
    n = H.shape[0]
    A = H.copy()
    for j in range(n):
        x1[j] = b1[j]
        x2[j] = b2[j]
    for i in range(n):
        k = i
        for j in range(i + 1, n):
            if abs(A[j, i]) > abs(A[k, i]):
                k = j
        if abs(A[k, i]) < _PIVOT_EPS:
            for j in range(n):
                x1[j] = 0.0
                x2[j] = 0.0
            return
        if k != i:
            for j in range(n):
                A[i, j], A[k, j] = A[k, j], A[i, j]
            x1[i], x1[k] = x1[k], x1[i]
            x2[i], x2[k] = x2[k], x2[i]
        for j in range(i + 1, n):
            f = A[j, i] / A[i, i]
            for c in range(i, n):
                A[j, c] -= f * A[i, c]
            x1[j] -= f * x1[i]
            x2[j] -= f * x2[i]
    for i in range(n - 1, -1, -1):
        s1 = x1[i]
        s2 = x2[i]
        for c in range(i + 1, n):
            s1 -= A[i, c] * x1[c]
            s2 -= A[i, c] * x2[c]
        x1[i] = s1 / A[i, i]
        x2[i] = s2 / A[i, i]


@njit(cache=True, error_model="numpy")
def ecc_affine(templates, image, boxes, warps, max_iter, eps):
    """Affine ECC alignment of each template in its crop of ``image`` (see the module).

    Parameters
    ----------
    templates : (m, hs, ws) float32
        Grey levels of the templates.
    image : (h, w) uint8 or float32
        The image the templates are sought in.
    boxes : (m, 4) int64
        Each template's crop ``x0, y0, x1, y1`` (pixels, ``image[y0:y1, x0:x1]``), non-empty
        and inside ``image``.
    warps : (m, 2, 3) float32
        Initial warps from template pixels to crop pixels (OpenCV's ``warpMatrix``).
    max_iter : int
        Most iterations (TermCriteria COUNT).
    eps : float
        Smallest change of the correlation coefficient that continues (TermCriteria EPS).

    Returns
    -------
    warps : (m, 2, 3) float32
        Refined warps (the initial one where a feature failed).
    rho : (m,) float64
        The correlation coefficient (OpenCV's return value); NaN where a feature failed.
    status : (m,) int8
        ``ECC_OK``, or why the feature failed (``ECC_FLAT``, ``ECC_MINIMISED``).
    """
    m, hs, ws = templates.shape
    out = warps.copy()
    rho_out = np.full(m, np.nan)
    status = np.zeros(m, dtype=np.int8)
    ch_max = 1
    cw_max = 1
    for i in range(m):
        ch_max = max(ch_max, boxes[i, 3] - boxes[i, 1])
        cw_max = max(cw_max, boxes[i, 2] - boxes[i, 0])
    buf = np.empty((ch_max, cw_max, 3))
    npx = hs * ws
    v = np.empty(npx)
    gx = np.empty(npx)
    gy = np.empty(npx)
    inside = np.empty(npx, dtype=np.bool_)
    H = np.empty((6, 6))
    ip = np.empty(6)  # G^T v (v less its mask mean on the mask, as warped off it)
    tp = np.empty(6)  # G^T t (t less its mask mean on the mask, 0 off it)
    x_ip = np.empty(6)
    x_tp = np.empty(6)
    for f in range(m):
        x0, y0 = boxes[f, 0], boxes[f, 1]
        ch, cw = boxes[f, 3] - y0, boxes[f, 2] - x0
        if ch <= 0 or cw <= 0:
            status[f] = ECC_FLAT
            continue
        _crop_gradients(image, x0, y0, ch, cw, buf)
        W = out[f]
        rho = -1.0
        last_rho = -eps
        it = 1
        while it <= max_iter and abs(rho - last_rho) >= eps:
            it += 1
            _warp_back(buf, ch, cw, W, hs, ws, v, gx, gy, inside)
            n = 0
            sv = 0.0
            st = 0.0
            for r in range(hs):
                for c in range(ws):
                    if inside[r * ws + c]:
                        n += 1
                        sv += v[r * ws + c]
                        st += float(templates[f, r, c])
            # 3. zero-mean over the mask; 4. Jacobian and Hessian over all the pixels
            mv = sv / n if n else 0.0
            mt = st / n if n else 0.0
            vv, tt, tv = _normal_equations(templates[f], v, gx, gy, inside, mv, mt, H, ip, tp)
            # 5. the correlation coefficient and the ECC update
            last_rho = rho
            rho = tv / (math.sqrt(vv) * math.sqrt(tt))
            if math.isnan(rho):
                status[f] = ECC_FLAT
                break
            _solve2(H, ip, tp, x_ip, x_tp)
            lam_n = vv
            lam_d = tv
            for a in range(6):
                lam_n -= ip[a] * x_ip[a]
                lam_d -= tp[a] * x_ip[a]
            if lam_d <= 0.0:
                status[f] = ECC_MINIMISED
                break
            lam = lam_n / lam_d
            # dp = H^-1 G^T (lam t - v), in OpenCV's order of the parameters
            W[0, 0] += lam * x_tp[0] - x_ip[0]
            W[1, 0] += lam * x_tp[1] - x_ip[1]
            W[0, 1] += lam * x_tp[2] - x_ip[2]
            W[1, 1] += lam * x_tp[3] - x_ip[3]
            W[0, 2] += lam * x_tp[4] - x_ip[4]
            W[1, 2] += lam * x_tp[5] - x_ip[5]
        if status[f] == ECC_OK:
            rho_out[f] = rho
        else:
            out[f] = warps[f]
    return out, rho_out, status
