"""Compiled (numba) loops of the stereo-points front end (:mod:`.stereo_points`).

Why by hand: each step works on millions of 3-vectors and 3x3 matrices (B runs x 2001
epochs x N features); in numpy every intermediate is a full-size temporary array, and
profiling showed the temporaries, not the arithmetic, to be the cost (docs/results/hu2024.md,
Speed). These loops compute the same quantities as the numpy functions they stand in for,
which stay the reference: ``tests/test_frontends.py`` checks that both agree.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def triangulate_parallel_rotated(uv, obs, focal, baseline, cu, cv, sigma, R_LC):
    """Parallel-rig triangulation (Hu 2024 eq. 1, corrected) with its first-order covariance
    (``triangulation.triangulation_jacobian``), and both rotated into L.

    uv (B,n,2,N,2) px, obs (B,n,2,N), R_LC (B,n,3,3). Returns p_C, cov_C, p_L, cov_L
    (NaN where not usable), usable (B,n,N) and the counts of one-camera-only and bad
    triangulations per run (as ``stereo_points._finish_triangulation``)."""
    B, n, N = uv.shape[0], uv.shape[1], uv.shape[3]
    p_C = np.full((B, n, N, 3), np.nan)
    cov_C = np.full((B, n, N, 3, 3), np.nan)
    p_L = np.full((B, n, N, 3), np.nan)
    cov_L = np.full((B, n, N, 3, 3), np.nan)
    usable = np.zeros((B, n, N), dtype=np.bool_)
    one_cam = np.zeros(B, dtype=np.int64)
    bad = np.zeros(B, dtype=np.int64)
    J = np.zeros((3, 4))
    C = np.empty((3, 3))
    s2 = sigma * sigma
    for b in range(B):
        for k in range(n):
            R = R_LC[b, k]
            for i in range(N):
                ol, orr = obs[b, k, 0, i], obs[b, k, 1, i]
                if ol != orr:
                    one_cam[b] += 1
                if not (ol and orr):
                    continue
                ul, vl, ur = uv[b, k, 0, i, 0], uv[b, k, 0, i, 1], uv[b, k, 1, i, 0]
                disp = ul - ur
                if not (np.isfinite(disp) and disp > 0.0 and np.isfinite(vl)):
                    bad[b] += 1
                    continue
                y = focal * baseline / disp  # depth on the optical axis y
                x = y * (ul - cu) / focal
                z = y * (vl - cv) / focal
                kk = y / (focal * baseline)
                J[0, 0], J[0, 2] = y / focal - x * kk, x * kk
                J[1, 0], J[1, 2] = -y * kk, y * kk
                J[2, 0], J[2, 1], J[2, 2] = -z * kk, y / focal, z * kk
                ok = np.isfinite(x) and np.isfinite(y) and np.isfinite(z)
                for a in range(3):
                    for c in range(3):
                        s = 0.0
                        for m in range(4):
                            s += J[a, m] * J[c, m]
                        C[a, c] = s2 * s
                        ok = ok and np.isfinite(C[a, c])
                if not ok:
                    bad[b] += 1
                    continue
                usable[b, k, i] = True
                p_C[b, k, i, 0], p_C[b, k, i, 1], p_C[b, k, i, 2] = x, y, z
                cov_C[b, k, i] = C
                for a in range(3):
                    p_L[b, k, i, a] = R[a, 0] * x + R[a, 1] * y + R[a, 2] * z
                for a in range(3):
                    for c in range(3):
                        s = 0.0
                        for m in range(3):
                            for q in range(3):
                                s += R[a, m] * C[m, q] * R[c, q]
                        cov_L[b, k, i, a, c] = s
    return p_C, cov_C, p_L, cov_L, usable, one_cam, bad


@njit(cache=True, error_model="numpy")
def kabsch_moments(p, g, w):
    """The weighted, centred cross-covariance ``H = sum w g p^T`` of a rigid alignment
    ``p ~ R g + o``, the weighted centroids and the lever-arm information
    ``sum w (|a|^2 I - a a^T)`` (``stereo_points.weighted_kabsch`` before and after its SVD).

    p, g (M,K,3) (NaN allowed where w = 0), w (M,K). Returns H (M,3,3), pc, gc (M,3),
    info (M,3,3), count (M,) of points with w > 0 and the weight sum (M,)."""
    M, K = w.shape
    H = np.zeros((M, 3, 3))
    info = np.zeros((M, 3, 3))
    pc = np.zeros((M, 3))
    gc = np.zeros((M, 3))
    cnt = np.zeros(M, dtype=np.int64)
    sw = np.zeros(M)
    for m in range(M):
        for i in range(K):
            wi = w[m, i]
            if wi > 0:
                cnt[m] += 1
            sw[m] += wi
            if wi != 0.0:
                for a in range(3):
                    pc[m, a] += wi * p[m, i, a]
                    gc[m, a] += wi * g[m, i, a]
        s = sw[m] if sw[m] > 0 else 1.0
        for a in range(3):
            pc[m, a] /= s
            gc[m, a] /= s
        for i in range(K):
            wi = w[m, i]
            if not wi > 0:
                continue
            a0 = p[m, i, 0] - pc[m, 0]
            a1 = p[m, i, 1] - pc[m, 1]
            a2 = p[m, i, 2] - pc[m, 2]
            aa = a0 * a0 + a1 * a1 + a2 * a2
            av = (a0, a1, a2)
            for r in range(3):
                gr = wi * (g[m, i, r] - gc[m, r])
                H[m, r, 0] += gr * a0
                H[m, r, 1] += gr * a1
                H[m, r, 2] += gr * a2
            for r in range(3):
                for c in range(3):
                    info[m, r, c] += wi * ((aa if r == c else 0.0) - av[r] * av[c])
    return H, pc, gc, info, cnt, sw


@njit(cache=True, inline="always", error_model="numpy")
def _qmul(a, b, out):
    """Hamilton product a (x) b of [x, y, z, w] quaternions (``rotations.quat_multiply``)."""
    ax, ay, az, aw = a[0], a[1], a[2], a[3]
    bx, by, bz, bw = b[0], b[1], b[2], b[3]
    out[0] = aw * bx + bw * ax + (ay * bz - az * by)
    out[1] = aw * by + bw * ay + (az * bx - ax * bz)
    out[2] = aw * bz + bw * az + (ax * by - ay * bx)
    out[3] = aw * bw - (ax * bx + ay * by + az * bz)


@njit(cache=True, error_model="numpy")
def rate_fit(q, valid, h, dt):
    """``stereo_points.rates_from_G`` after its quaternion conversion: the symmetric
    least-squares slope of ``log(q(k+j) (x) conj(q(k)))`` over ``j = -h..h``.

    q (B,n,4) unit quaternions of R_GI (identity where not valid), valid (B,n). Returns
    omega (B,n,3), NaN where any epoch of the window is missing."""
    B, n = valid.shape
    omega = np.full((B, n, 3), np.nan)
    sjj = 0.0
    for j in range(1, h + 1):
        sjj += 2.0 * j * j
    qc = np.empty(4)
    m = np.empty(4)
    for b in range(B):
        for k in range(n):
            good = valid[b, k]
            if not good:
                continue
            for j in range(1, h + 1):
                if k + j >= n or k - j < 0 or not valid[b, k + j] or not valid[b, k - j]:
                    good = False
                    break
            if not good:
                continue
            qc[0], qc[1], qc[2], qc[3] = -q[b, k, 0], -q[b, k, 1], -q[b, k, 2], q[b, k, 3]
            num0 = num1 = num2 = 0.0
            for j in range(1, h + 1):
                for s in (1, -1):
                    _qmul(q[b, k + s * j], qc, m)
                    # rotations.log_quat: normalise, non-negative scalar part
                    nrm = math.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3])
                    sg = -1.0 if m[3] / nrm < 0.0 else 1.0
                    vx, vy, vz, ww = (sg * m[0] / nrm, sg * m[1] / nrm, sg * m[2] / nrm,
                                      sg * m[3] / nrm)  # fmt: skip
                    sv = math.sqrt(vx * vx + vy * vy + vz * vz)
                    kk = 2.0 / ww if sv < 1e-8 else 2.0 * math.atan2(sv, ww) / sv
                    num0 += s * j * kk * vx
                    num1 += s * j * kk * vy
                    num2 += s * j * kk * vz
            omega[b, k, 0] = -num0 / (dt * sjj)
            omega[b, k, 1] = -num1 / (dt * sjj)
            omega[b, k, 2] = -num2 / (dt * sjj)
    return omega


@njit(cache=True, error_model="numpy")
def normal_equations_at(a, b, w, ok, delay, sel):
    """Running sums of the weighted least squares of Hu 2024 eq. 13, read at epochs ``sel``:
    ``N = sum w a^T a`` (8x8), ``r = sum w a^T b``, ``bb = sum w |b|^2`` and the count of
    used epochs, each summed over epochs ``0 .. k - delay`` for ``k`` in ``sel``
    (``stereo_points.identify_and_dpacf``; the numpy version built the cumulative sums at
    every epoch, a (B, n, 8, 8) array, to read every fifth).

    a (B,n,3,8), b (B,n,3), w (B,n) (0 where not ok), ok (B,n), sel (S,) increasing."""
    B, n = w.shape
    S = sel.shape[0]
    N = np.zeros((B, S, 8, 8))
    r = np.zeros((B, S, 8))
    bb = np.zeros((B, S))
    cnt = np.zeros((B, S), dtype=np.int64)
    Nc = np.zeros((8, 8))
    rc = np.zeros(8)
    for bi in range(B):
        Nc[:, :] = 0.0
        rc[:] = 0.0
        bbc = 0.0
        cc = 0
        j = 0  # next epoch to add
        for si in range(S):
            last = sel[si] - delay  # include epochs up to here
            while j <= last:
                wj = w[bi, j]
                if wj != 0.0:
                    for p in range(8):
                        for q in range(p, 8):
                            Nc[p, q] += wj * (
                                a[bi, j, 0, p] * a[bi, j, 0, q]
                                + a[bi, j, 1, p] * a[bi, j, 1, q]
                                + a[bi, j, 2, p] * a[bi, j, 2, q]
                            )
                        rc[p] += wj * (
                            a[bi, j, 0, p] * b[bi, j, 0]
                            + a[bi, j, 1, p] * b[bi, j, 1]
                            + a[bi, j, 2, p] * b[bi, j, 2]
                        )
                    bbc += wj * (b[bi, j, 0] ** 2 + b[bi, j, 1] ** 2 + b[bi, j, 2] ** 2)
                if ok[bi, j]:
                    cc += 1
                j += 1
            for p in range(8):
                for q in range(p, 8):
                    N[bi, si, p, q] = Nc[p, q]
                    N[bi, si, q, p] = Nc[p, q]
                r[bi, si, p] = rc[p]
            bb[bi, si] = bbc
            cnt[bi, si] = cc
    return N, r, bb, cnt


@njit(cache=True, error_model="numpy")
def matrix_to_quat(R):
    """``rotations.matrix_to_quat`` for stacks (M,3,3) of rotation matrices: Shepperd's method
    (the largest of trace and diagonal picks the stable formula), normalised, scalar part
    made non-negative. Unlike scipy it does not first project a non-orthogonal matrix onto
    SO(3): use it only on products of rotation matrices."""
    M = R.shape[0]
    q = np.empty((M, 4))
    for m in range(M):
        r = R[m]
        tr = r[0, 0] + r[1, 1] + r[2, 2]
        big = max(tr, r[0, 0], r[1, 1], r[2, 2])
        if big == tr:
            w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
            f = 0.25 / w
            x, y, z = (r[2, 1] - r[1, 2]) * f, (r[0, 2] - r[2, 0]) * f, (r[1, 0] - r[0, 1]) * f
        elif big == r[0, 0]:
            x = 0.5 * math.sqrt(max(1.0 + 2 * r[0, 0] - tr, 0.0))
            f = 0.25 / x
            w, y, z = (r[2, 1] - r[1, 2]) * f, (r[0, 1] + r[1, 0]) * f, (r[0, 2] + r[2, 0]) * f
        elif big == r[1, 1]:
            y = 0.5 * math.sqrt(max(1.0 + 2 * r[1, 1] - tr, 0.0))
            f = 0.25 / y
            w, x, z = (r[0, 2] - r[2, 0]) * f, (r[0, 1] + r[1, 0]) * f, (r[1, 2] + r[2, 1]) * f
        else:
            z = 0.5 * math.sqrt(max(1.0 + 2 * r[2, 2] - tr, 0.0))
            f = 0.25 / z
            w, x, y = (r[1, 0] - r[0, 1]) * f, (r[0, 2] + r[2, 0]) * f, (r[1, 2] + r[2, 1]) * f
        n = math.sqrt(x * x + y * y + z * z + w * w)
        if w < 0:
            n = -n
        q[m, 0], q[m, 1], q[m, 2], q[m, 3] = x / n, y / n, z / n, w / n
    return q


@njit(cache=True, error_model="numpy")
def _jacobi_eig(A, V):
    """Cyclic Jacobi eigen-decomposition of a small symmetric matrix, in place: on return the
    diagonal of ``A`` holds the eigenvalues and the columns of ``V`` the eigenvectors."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(30):
        off = 0.0
        scale = 0.0
        for i in range(n):
            scale += A[i, i] * A[i, i]
            for j in range(i + 1, n):
                off += A[i, j] * A[i, j]
        if off <= 1e-30 * scale or off == 0.0:
            return
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # A <- A J (columns p, q)
                    akp, akq = A[k, p], A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(n):  # A <- J^T A (rows p, q)
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq


@njit(cache=True, error_model="numpy")
def kabsch_rotation(H):
    """The proper rotation ``R`` minimising ``sum w |a - R b|^2`` for ``H = sum w b a^T``
    (M,3,3; ``kabsch_moments``' H with b = g, a = p), by Horn's quaternion method (the
    eigenvector of the largest eigenvalue of his 4x4 matrix; Horn 1987, JOSA A 4(4) 629),
    and the ratio of the second to the first singular value of H (collinear points: 0).
    Why by hand: numpy's batched SVD of tens of thousands of 3x3 matrices was a tenth of the
    whole campaign; this gives the same rotation as the SVD with the reflection guard (test)."""
    M = H.shape[0]
    R = np.empty((M, 3, 3))
    ratio = np.empty(M)
    N4 = np.empty((4, 4))
    V4 = np.empty((4, 4))
    for m in range(M):
        S = H[m]
        sxx, sxy, sxz = S[0, 0], S[0, 1], S[0, 2]
        syx, syy, syz = S[1, 0], S[1, 1], S[1, 2]
        szx, szy, szz = S[2, 0], S[2, 1], S[2, 2]
        N4[0, 0] = sxx + syy + szz
        N4[0, 1] = N4[1, 0] = syz - szy
        N4[0, 2] = N4[2, 0] = szx - sxz
        N4[0, 3] = N4[3, 0] = sxy - syx
        N4[1, 1] = sxx - syy - szz
        N4[1, 2] = N4[2, 1] = sxy + syx
        N4[1, 3] = N4[3, 1] = szx + sxz
        N4[2, 2] = -sxx + syy - szz
        N4[2, 3] = N4[3, 2] = syz + szy
        N4[3, 3] = -sxx - syy + szz
        _jacobi_eig(N4, V4)
        best = 0
        for i in range(1, 4):
            if N4[i, i] > N4[best, best]:
                best = i
        w, x, y, z = V4[0, best], V4[1, best], V4[2, best], V4[3, best]
        n = math.sqrt(w * w + x * x + y * y + z * z)
        if not n > 0:
            w, x, y, z, n = 1.0, 0.0, 0.0, 0.0, 1.0
        w, x, y, z = w / n, x / n, y / n, z / n
        R[m, 0, 0] = w * w + x * x - y * y - z * z
        R[m, 0, 1] = 2 * (x * y - w * z)
        R[m, 0, 2] = 2 * (x * z + w * y)
        R[m, 1, 0] = 2 * (x * y + w * z)
        R[m, 1, 1] = w * w - x * x + y * y - z * z
        R[m, 1, 2] = 2 * (y * z - w * x)
        R[m, 2, 0] = 2 * (x * z - w * y)
        R[m, 2, 1] = 2 * (y * z + w * x)
        R[m, 2, 2] = w * w - x * x - y * y + z * z
        # singular values of H from Horn's eigenvalues: with l_max the largest, the other
        # three give (l_max + l_i) / 2 = sigma_1, sigma_2 and +-sigma_3 in some order
        sv = np.empty(3)
        c = 0
        for i in range(4):
            if i != best:
                sv[c] = abs(0.5 * (N4[best, best] + N4[i, i]))
                c += 1
        hi = max(sv[0], sv[1], sv[2])
        lo = min(sv[0], sv[1], sv[2])
        mid = sv[0] + sv[1] + sv[2] - hi - lo
        ratio[m] = mid / hi if hi > 0 else 0.0
    return R, ratio
