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

# the compiled quaternion algebra (matrix_to_quat is also this module's, for stereo_points)
from tumblenav.rotations_compiled import log_quat, matrix_to_quat, quat_multiply

__all__ = [
    "align_rigid",
    "joint_normal_equations",
    "kabsch_moments",
    "kabsch_rotation",
    "matrix_to_quat",
    "normal_equations_at",
    "rate_fit",
    "triangulate_parallel_rotated",
    "whiten_rows",
]


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
def _moments_one(p, g, w, H, pc, gc, info):
    """:func:`kabsch_moments` of one alignment: p, g (K,3), w (K,); fills H, info (3,3),
    pc, gc (3,) and returns the count of points with w > 0 and the weight sum."""
    K = w.shape[0]
    cnt = 0
    sw = 0.0
    for a in range(3):
        pc[a] = 0.0
        gc[a] = 0.0
        for c in range(3):
            H[a, c] = 0.0
            info[a, c] = 0.0
    for i in range(K):
        wi = w[i]
        if wi > 0:
            cnt += 1
        sw += wi
        if wi != 0.0:
            for a in range(3):
                pc[a] += wi * p[i, a]
                gc[a] += wi * g[i, a]
    s = sw if sw > 0 else 1.0
    for a in range(3):
        pc[a] /= s
        gc[a] /= s
    for i in range(K):
        wi = w[i]
        if not wi > 0:
            continue
        a0 = p[i, 0] - pc[0]
        a1 = p[i, 1] - pc[1]
        a2 = p[i, 2] - pc[2]
        aa = a0 * a0 + a1 * a1 + a2 * a2
        av = (a0, a1, a2)
        for r in range(3):
            gr = wi * (g[i, r] - gc[r])
            H[r, 0] += gr * a0
            H[r, 1] += gr * a1
            H[r, 2] += gr * a2
        for r in range(3):
            for c in range(3):
                info[r, c] += wi * ((aa if r == c else 0.0) - av[r] * av[c])
    return cnt, sw


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
        cnt[m], sw[m] = _moments_one(p[m], g[m], w[m], H[m], pc[m], gc[m], info[m])
    return H, pc, gc, info, cnt, sw


@njit(cache=True, error_model="numpy")
def rate_fit(q, valid, h, dt):
    """``stereo_points.rates_and_covariance`` after its quaternion conversion: the symmetric
    least-squares slopes of ``log(q(k+j) (x) conj(q(k)))`` over ``j = -h..h``, of a line
    and of a line plus a cubic term.

    q (B,n,4) unit quaternions of R_GI (identity where not valid), valid (B,n). Returns
    omega (B,n,3) of the linear fit and omega (B,n,3) of the cubic one, NaN where any epoch
    of the window is missing (the cubic one also for h = 1)."""
    B, n = valid.shape
    omega = np.full((B, n, 3), np.nan)
    omega3 = np.full((B, n, 3), np.nan)
    s2 = s4 = s6 = 0.0
    for j in range(1, h + 1):
        s2 += 2.0 * j**2
        s4 += 2.0 * j**4
        s6 += 2.0 * j**6
    det = s2 * s6 - s4 * s4
    qc = np.empty(4)
    m = np.empty(4)
    num = np.empty(3)
    num3 = np.empty(3)
    lg = np.empty(3)
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
            num[:] = 0.0
            num3[:] = 0.0
            for j in range(1, h + 1):
                for s in (1, -1):
                    quat_multiply(q[b, k + s * j], qc, m)
                    log_quat(m, lg)
                    sj = s * j
                    sj3 = sj * j * j
                    for a in range(3):
                        num[a] += sj * lg[a]
                        num3[a] += sj3 * lg[a]
            for a in range(3):
                omega[b, k, a] = -num[a] / (dt * s2)
                if det > 0.0:  # h >= 2
                    omega3[b, k, a] = -(s6 * num[a] - s4 * num3[a]) / (dt * det)
    return omega, omega3


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
def _horn_one(S, R, N4, V4, sv):
    """:func:`kabsch_rotation` of one ``H`` (3x3): fills ``R`` and returns the singular
    value ratio (``N4``, ``V4`` (4,4) and ``sv`` (3,) are scratch)."""
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
    R[0, 0] = w * w + x * x - y * y - z * z
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = w * w - x * x + y * y - z * z
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = w * w - x * x - y * y + z * z
    # singular values of H from Horn's eigenvalues: with l_max the largest, the other
    # three give (l_max + l_i) / 2 = sigma_1, sigma_2 and +-sigma_3 in some order
    c = 0
    for i in range(4):
        if i != best:
            sv[c] = abs(0.5 * (N4[best, best] + N4[i, i]))
            c += 1
    hi = max(sv[0], sv[1], sv[2])
    lo = min(sv[0], sv[1], sv[2])
    mid = sv[0] + sv[1] + sv[2] - hi - lo
    return mid / hi if hi > 0 else 0.0


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
    sv = np.empty(3)
    for m in range(M):
        ratio[m] = _horn_one(H[m], R[m], N4, V4, sv)
    return R, ratio


@njit(cache=True, inline="always", error_model="numpy")
def _inv3_sym(C, out):
    """Inverse of a symmetric 3x3 matrix by cofactors; False if not positive definite."""
    a, b, c = C[0, 0], C[0, 1], C[0, 2]
    d, e, f = C[1, 1], C[1, 2], C[2, 2]
    A00 = d * f - e * e
    A01 = c * e - b * f
    A02 = b * e - c * d
    det = a * A00 + b * A01 + c * A02
    if not (det > 0.0 and a > 0.0 and a * d - b * b > 0.0):
        return False
    out[0, 0] = A00 / det
    out[0, 1] = out[1, 0] = A01 / det
    out[0, 2] = out[2, 0] = A02 / det
    out[1, 1] = (a * f - c * c) / det
    out[1, 2] = out[2, 1] = (b * c - a * e) / det
    out[2, 2] = (a * d - b * b) / det
    return True


@njit(cache=True, error_model="numpy")
def _chol6(A, L):
    """Cholesky factor ``L`` of the symmetric 6x6 ``A``; False if not numerically positive
    definite."""
    for i in range(6):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 1e-300:
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@njit(cache=True, error_model="numpy")
def _chol_back6(L, g, x):
    """Solve ``L L^T x = g`` given the Cholesky factor ``L`` (6x6)."""
    for i in range(6):
        s = g[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(5, -1, -1):
        s = x[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


@njit(cache=True, error_model="numpy")
def _rigid_normal(p, g, Wi, use, gc, R, c, A, gv):
    """Cost ``sum (p_i - R (g_i - gc) - c)^T W_i (...)`` of a rigid fit and its Gauss-Newton
    normal equations ``A`` (6x6), ``gv`` (6,) in ``(dtheta, dc)`` with ``R <- exp(dtheta) R``:
    the Jacobian of point i is ``[-[u_i x], I]``, ``u_i = R (g_i - gc)``."""
    for i in range(6):
        gv[i] = 0.0
        for j in range(6):
            A[i, j] = 0.0
    cost = 0.0
    K = p.shape[0]
    u = np.empty(3)
    y = np.empty(3)
    WU = np.empty((3, 3))  # W [u x]
    UT = np.empty((3, 3))
    for i in range(K):
        if not use[i]:
            continue
        W = Wi[i]
        for a in range(3):
            u[a] = (
                R[a, 0] * (g[i, 0] - gc[0])
                + R[a, 1] * (g[i, 1] - gc[1])
                + R[a, 2] * (g[i, 2] - gc[2])
            )
        for a in range(3):
            y[a] = p[i, a] - u[a] - c[a]
        # [u x] = [[0, -u2, u1], [u2, 0, -u0], [-u1, u0, 0]]
        for a in range(3):
            WU[a, 0] = W[a, 1] * u[2] - W[a, 2] * u[1]
            WU[a, 1] = W[a, 2] * u[0] - W[a, 0] * u[2]
            WU[a, 2] = W[a, 0] * u[1] - W[a, 1] * u[0]
        # [u x]^T, row a
        UT[0, 0], UT[0, 1], UT[0, 2] = 0.0, u[2], -u[1]
        UT[1, 0], UT[1, 1], UT[1, 2] = -u[2], 0.0, u[0]
        UT[2, 0], UT[2, 1], UT[2, 2] = u[1], -u[0], 0.0
        for a in range(3):
            Wy = W[a, 0] * y[0] + W[a, 1] * y[1] + W[a, 2] * y[2]
            cost += y[a] * Wy
            gv[3 + a] += Wy
            # theta part of J^T W y = -[u x]^T W y = -(W [u x])^T y
            gv[a] -= WU[0, a] * y[0] + WU[1, a] * y[1] + WU[2, a] * y[2]
            for b in range(3):
                A[3 + a, 3 + b] += W[a, b]
                # A_tt = [u x]^T W [u x];  A_tc = -[u x]^T W = -(W [u x])^T
                A[a, b] += UT[a, 0] * WU[0, b] + UT[a, 1] * WU[1, b] + UT[a, 2] * WU[2, b]
                A[a, 3 + b] -= WU[b, a]
    for a in range(3):
        for b in range(3):
            A[3 + b, a] = A[a, 3 + b]
    return cost


@njit(cache=True, error_model="numpy")
def _gn_rigid(p, g, Wi, use, gc, R0, c0, iters, R, c, A, S):
    """Gauss-Newton of the rigid fit of :func:`_rigid_normal` from ``R0``, ``c0``; the
    result in ``R``, ``c`` and its normal matrix in ``A``; returns the cost (inf if the
    normal matrix is singular). ``S`` is scratch (6, 6) + vectors."""
    An = S[0]
    L = S[1]
    gv = S[2, 0]
    gn = S[2, 1]
    d = S[2, 2]
    cn = S[2, 3, :3]
    Rn = S[3, :3, :3]
    E = S[3, 3:, 3:]
    R[:, :] = R0
    c[:] = c0
    cost = _rigid_normal(p, g, Wi, use, gc, R, c, A, gv)
    if not np.isfinite(cost):
        return np.inf
    for _ in range(iters):
        if not _chol6(A, L):
            return np.inf
        _chol_back6(L, gv, d)
        th = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if th < 1e-12:
            break
        # R_new = exp(d_theta) R (Rodrigues)
        kx, ky, kz = d[0] / th, d[1] / th, d[2] / th
        s, ct = math.sin(th), math.cos(th)
        v = 1.0 - ct
        E[0, 0] = ct + kx * kx * v
        E[0, 1] = kx * ky * v - kz * s
        E[0, 2] = kx * kz * v + ky * s
        E[1, 0] = ky * kx * v + kz * s
        E[1, 1] = ct + ky * ky * v
        E[1, 2] = ky * kz * v - kx * s
        E[2, 0] = kz * kx * v - ky * s
        E[2, 1] = kz * ky * v + kx * s
        E[2, 2] = ct + kz * kz * v
        for a in range(3):
            for b in range(3):
                Rn[a, b] = E[a, 0] * R[0, b] + E[a, 1] * R[1, b] + E[a, 2] * R[2, b]
            cn[a] = c[a] + d[3 + a]
        if th < 1e-7:  # converged (far below any attitude noise): take it, keep A
            R[:, :] = Rn
            c[:] = cn
            break
        cost_n = _rigid_normal(p, g, Wi, use, gc, Rn, cn, An, gn)
        if not cost_n <= cost * (1.0 + 1e-12):
            break
        cost = cost_n
        R[:, :] = Rn
        c[:] = cn
        A[:, :] = An
        gv[:] = gn
    return cost


@njit(cache=True, error_model="numpy")
def _point_weights(cov_p, cov_g, R, use, Wi):
    """``W_i = (cov_p_i + R cov_g_i R^T)^-1`` for the used points; a point whose sum is not
    positive definite is dropped from ``use``. Returns the number of points left."""
    cnt = 0
    C = np.empty((3, 3))
    T = np.empty((3, 3))
    for i in range(use.shape[0]):
        if not use[i]:
            continue
        for a in range(3):
            for b in range(3):
                T[a, b] = (
                    R[a, 0] * cov_g[i, 0, b] + R[a, 1] * cov_g[i, 1, b] + R[a, 2] * cov_g[i, 2, b]
                )
        for a in range(3):
            for b in range(3):
                C[a, b] = cov_p[i, a, b] + T[a, 0] * R[b, 0] + T[a, 1] * R[b, 1] + T[a, 2] * R[b, 2]
        if _inv3_sym(C, Wi[i]):
            cnt += 1
        else:
            use[i] = False
    return cnt


@njit(cache=True, error_model="numpy")
def _noise_share(p, g, cov_p, cov_g, R, use, gc, Wi, A, Bn, L, out):
    """The covariance of the fit's attitude error from the points' own noise alone (the
    rotation block of ``A^-1 Bn A^-1``, ``Bn = sum J_i^T W_i cov_p_i W_i J_i``, ``J_i = [-[u_i
    x], I]``, the weights ``W_i`` at ``R``), into ``out`` (3x3); False if not determined.
    The template's share, ``cov_g``, is an error fixed in G (it turns with the view only), so
    it does not enter the rates (``stereo_points.rates_and_covariance``) as noise would."""
    if _point_weights(cov_p, cov_g, R, use, Wi) < 3:
        return False
    gv = np.empty(6)
    _rigid_normal(p, g, Wi, use, gc, R, np.zeros(3), A, gv)
    for a in range(6):
        for b in range(6):
            Bn[a, b] = 0.0
    u = np.empty(3)
    J = np.empty((3, 6))
    WJ = np.empty((3, 6))
    CWJ = np.empty((3, 6))
    for i in range(use.shape[0]):
        if not use[i]:
            continue
        for a in range(3):
            u[a] = (
                R[a, 0] * (g[i, 0] - gc[0])
                + R[a, 1] * (g[i, 1] - gc[1])
                + R[a, 2] * (g[i, 2] - gc[2])
            )
        # J = [-[u x], I]
        J[0, 0], J[0, 1], J[0, 2] = 0.0, u[2], -u[1]
        J[1, 0], J[1, 1], J[1, 2] = -u[2], 0.0, u[0]
        J[2, 0], J[2, 1], J[2, 2] = u[1], -u[0], 0.0
        for a in range(3):
            for b in range(3):
                J[a, 3 + b] = 1.0 if a == b else 0.0
        W = Wi[i]
        for a in range(3):
            for k in range(6):
                WJ[a, k] = W[a, 0] * J[0, k] + W[a, 1] * J[1, k] + W[a, 2] * J[2, k]
        C = cov_p[i]
        for a in range(3):
            for k in range(6):
                CWJ[a, k] = C[a, 0] * WJ[0, k] + C[a, 1] * WJ[1, k] + C[a, 2] * WJ[2, k]
        for k in range(6):
            for l2 in range(6):
                Bn[k, l2] += WJ[0, k] * CWJ[0, l2] + WJ[1, k] * CWJ[1, l2] + WJ[2, k] * CWJ[2, l2]
    if not _chol6(A, L):
        return False
    Ainv = np.empty((6, 6))
    e6 = np.zeros(6)
    col = np.empty(6)
    for j in range(6):
        for i in range(6):
            e6[i] = 1.0 if i == j else 0.0
        _chol_back6(L, e6, col)
        for i in range(6):
            Ainv[i, j] = col[i]
    for a in range(3):  # the rotation block of Ainv Bn Ainv (Ainv symmetric)
        for b in range(3):
            acc = 0.0
            for k in range(6):
                for l2 in range(6):
                    acc += Ainv[a, k] * Bn[k, l2] * Ainv[l2, b]
            out[a, b] = acc
    return True


@njit(cache=True, error_model="numpy")
def _angle_between(R1, R2):
    tr = 0.0
    for a in range(3):
        for b in range(3):
            tr += R1[a, b] * R2[a, b]
    return math.acos(min(1.0, max(-1.0, 0.5 * (tr - 1.0))))


@njit(cache=True, error_model="numpy")
def _fit_from(p, g, cov_p, cov_g, use0, gc, Rs, c0, iters, Wi, use, R, c, A, S):
    """Gauss-Newton from the start ``Rs``, ``c0`` (the position of the template point
    ``gc``) with the weights at the start's rotation; re-weighted at the result and refitted
    once if it moved by more than 2 deg. Returns the cost (inf if not determined)."""
    use[:] = use0
    if _point_weights(cov_p, cov_g, Rs, use, Wi) < 3:
        return np.inf
    cost = _gn_rigid(p, g, Wi, use, gc, Rs, c0, iters, R, c, A, S)
    if np.isfinite(cost) and _angle_between(R, Rs) > 0.035:
        use[:] = use0
        if _point_weights(cov_p, cov_g, R, use, Wi) < 3:
            return np.inf
        R1 = R.copy()
        c1 = c.copy()
        cost = _gn_rigid(p, g, Wi, use, gc, R1, c1, iters, R, c, A, S)
    return cost


@njit(cache=True, error_model="numpy")
def align_rigid(p, g, cov, cov_g, w, iters, run_len):
    """Rigid alignments ``p_i ~ R_CG g_i + o`` by Gauss-Newton in the metric of each
    residual's covariance ``cov_i + R_CG cov_g_i R_CG^T`` (the point's and its template
    coordinates'; ``stereo_points.weighted_kabsch`` with covariances).

    p, g (M,K,3), cov (M,K,3,3), cov_g (M // run_len, K, 3, 3) (per run), w (M,K) (points
    with w > 0 are used; the weights of the Kabsch start), ``iters`` Gauss-Newton steps at
    most (a step that raises the cost stops it). The alignments come in runs of ``run_len``
    consecutive epochs (1: independent): the fit starts from the previous epoch's attitude
    where there is one, else from the isotropically weighted Kabsch fit (Horn's method),
    which is also tried when the warm start's cost fails the chi-square gate (``3 K - 6``
    degrees of freedom, Wilson-Hilferty at z = 4.75, about 1e-6): with metre-level depth
    errors on a target of a few metres the Kabsch attitude can be tens of degrees off and a
    few fits from it end in another local minimum. Returns R_CG (M,3,3), o (M,3), the
    covariance of the attitude error ``dtheta`` in C (``R_CG <- exp(dtheta) R_CG``; the
    rotation block of the inverse normal matrix, so the translation is estimated with it),
    ``ok`` (M,) (at least three non-collinear points) and ``refined`` (M,): where no fit
    passed the gate the Kabsch fit is returned with its information-form covariance
    ``(sum w (|a|^2 I - a a^T))^-1``; last, the points' own noise's share of that covariance
    (:func:`_noise_share`; the whole covariance where no fit passed)."""
    M, K = w.shape
    Ro = np.full((M, 3, 3), np.nan)
    oo = np.full((M, 3), np.nan)
    covt = np.full((M, 3, 3), np.nan)
    covn = np.full((M, 3, 3), np.nan)
    ok_out = np.zeros(M, dtype=np.bool_)
    done = np.zeros(M, dtype=np.bool_)
    Wi = np.empty((K, 3, 3))
    Bn = np.empty((6, 6))
    use0 = np.empty(K, dtype=np.bool_)
    use = np.empty(K, dtype=np.bool_)
    S = np.zeros((4, 6, 6))
    A = np.empty((6, 6))
    A2 = np.empty((6, 6))
    L = np.empty((6, 6))
    gc = np.empty(3)
    c0 = np.empty(3)
    c = np.empty(3)
    c2 = np.empty(3)
    R = np.empty((3, 3))
    R2 = np.empty((3, 3))
    Rk = np.empty((3, 3))
    pm = np.empty(3)  # centroid of the points
    e6 = np.zeros(6)
    col = np.empty(6)
    H = np.empty((3, 3))
    info = np.empty((3, 3))
    pcw = np.empty(3)
    gcw = np.empty(3)
    N4 = np.empty((4, 4))
    V4 = np.empty((4, 4))
    sv = np.empty(3)
    for m in range(M):
        cnt = 0
        for a in range(3):
            gc[a] = 0.0
            pm[a] = 0.0
        for i in range(K):
            good = w[m, i] > 0
            for a in range(3):
                good = good and np.isfinite(p[m, i, a]) and np.isfinite(g[m, i, a])
            use0[i] = good
            if good:
                cnt += 1
                for a in range(3):
                    gc[a] += g[m, i, a]
                    pm[a] += p[m, i, a]
        if cnt < 3:
            continue
        for a in range(3):
            gc[a] /= cnt
            pm[a] /= cnt  # the warm start's translation
        dof = 3.0 * cnt - 6.0
        f = 2.0 / (9.0 * dof)
        gate = max(dof * (1.0 - f + 4.75 * math.sqrt(f)) ** 3, 20.0)
        r = m // run_len
        warm = run_len > 1 and m % run_len != 0 and done[m - 1]
        cost = np.inf
        if warm:
            for a in range(3):
                c0[a] = pm[a]
            cost = _fit_from(p[m], g[m], cov[m], cov_g[r], use0, gc, Ro[m - 1], c0, iters, Wi,
                             use, R, c, A, S)  # fmt: skip
        kabsch = False
        if not cost <= gate:  # the Kabsch start
            cnt_w, sw = _moments_one(p[m], g[m], w[m], H, pcw, gcw, info)
            if cnt_w < 3 or not sw > 0:
                continue
            if not _horn_one(H, Rk, N4, V4, sv) > 1e-9:  # collinear
                continue
            kabsch = True
            for a in range(3):
                c0[a] = pcw[a] + (Rk[a, 0] * (gc[0] - gcw[0]) + Rk[a, 1] * (gc[1] - gcw[1])
                                  + Rk[a, 2] * (gc[2] - gcw[2]))  # fmt: skip
            cost2 = _fit_from(p[m], g[m], cov[m], cov_g[r], use0, gc, Rk, c0, iters, Wi, use,
                              R2, c2, A2, S)  # fmt: skip
            if cost2 < cost:
                cost = cost2
                R[:, :] = R2
                c[:] = c2
                A[:, :] = A2
        ok_out[m] = True
        if cost <= gate and _chol6(A, L):
            for j in range(3):
                for i in range(6):
                    e6[i] = 1.0 if i == j else 0.0
                _chol_back6(L, e6, col)
                for i in range(3):
                    covt[m, i, j] = col[i]
            use[:] = use0
            if not _noise_share(p[m], g[m], cov[m], cov_g[r], R, use, gc, Wi, A2, Bn, L, covn[m]):
                covn[m] = covt[m]
            Ro[m] = R
            for a in range(3):
                oo[m, a] = c[a] - (R[a, 0] * gc[0] + R[a, 1] * gc[1] + R[a, 2] * gc[2])
            done[m] = True
        else:  # no fit passed: the Kabsch fit (computed above unless the warm start passed)
            if not kabsch:
                cnt_w, sw = _moments_one(p[m], g[m], w[m], H, pcw, gcw, info)
                ratio = _horn_one(H, Rk, N4, V4, sv) if cnt_w >= 3 and sw > 0 else 0.0
                if not ratio > 1e-9:
                    ok_out[m] = False
                    continue
            Ro[m] = Rk
            for a in range(3):
                oo[m, a] = pcw[a] - (Rk[a, 0] * gcw[0] + Rk[a, 1] * gcw[1] + Rk[a, 2] * gcw[2])
            for a in range(3):
                info[a, a] += 1e-12
            if not _inv3_sym(info, covt[m]):
                ok_out[m] = False
            covn[m] = covt[m]
    return Ro, oo, covt, ok_out, done, covn


@njit(cache=True, error_model="numpy")
def whiten_rows(a, b, C_all, ok):
    """Generalised least squares rows of Hu 2024 eq. 11-12 (``stereo_points.
    identify_and_dpacf``), in place: each epoch's three rows ``a`` (B,n,3,8) and ``b``
    (B,n,3) are multiplied by ``L^-1``, ``L L^T = C`` (B,n,3,3; plus 1e-12 of its trace on
    the diagonal). Epochs not ``ok`` (or whose C is not positive definite) are zeroed and
    set not ``ok``."""
    B, n = ok.shape
    C = np.empty((3, 3))
    L = np.zeros((3, 3))
    for bi in range(B):
        for k in range(n):
            if ok[bi, k]:
                for r in range(3):
                    for s in range(3):
                        C[r, s] = C_all[bi, k, r, s]
                tr = C[0, 0] + C[1, 1] + C[2, 2]
                for r in range(3):
                    C[r, r] += 1e-12 * tr
                # Cholesky C = L L^T
                good = C[0, 0] > 0.0
                d1 = d2 = 0.0
                if good:
                    L[0, 0] = math.sqrt(C[0, 0])
                    L[1, 0] = C[1, 0] / L[0, 0]
                    L[2, 0] = C[2, 0] / L[0, 0]
                    d1 = C[1, 1] - L[1, 0] ** 2
                    good = d1 > 0.0
                if good:
                    L[1, 1] = math.sqrt(d1)
                    L[2, 1] = (C[2, 1] - L[2, 0] * L[1, 0]) / L[1, 1]
                    d2 = C[2, 2] - L[2, 0] ** 2 - L[2, 1] ** 2
                    good = d2 > 0.0
                if good:
                    L[2, 2] = math.sqrt(d2)
                    for col in range(8):
                        y0 = a[bi, k, 0, col] / L[0, 0]
                        y1 = (a[bi, k, 1, col] - L[1, 0] * y0) / L[1, 1]
                        y2 = (a[bi, k, 2, col] - L[2, 0] * y0 - L[2, 1] * y1) / L[2, 2]
                        a[bi, k, 0, col], a[bi, k, 1, col], a[bi, k, 2, col] = y0, y1, y2
                    y0 = b[bi, k, 0] / L[0, 0]
                    y1 = (b[bi, k, 1] - L[1, 0] * y0) / L[1, 1]
                    y2 = (b[bi, k, 2] - L[2, 0] * y0 - L[2, 1] * y1) / L[2, 2]
                    b[bi, k, 0], b[bi, k, 1], b[bi, k, 2] = y0, y1, y2
                    continue
                ok[bi, k] = False
            for r in range(3):
                b[bi, k, r] = 0.0
                for col in range(8):
                    a[bi, k, r, col] = 0.0


@njit(cache=True, error_model="numpy")
def joint_normal_equations(Phi, R, p, cov, cov_G, col, f, nf):
    """Normal equations of ``stereo_points.joint_features`` (its numpy form, the reference
    in the tests, made a batch of (M,3,3) temporaries per run): rows ``p_i(j) = Phi[j] a +
    R[j] f_i`` for the points with ``col[j, i] >= 0`` (the feature's block), weighted by
    the inverse of ``cov[j, i] + R[j] [f_i x] cov_G[j] [f_i x]^T R[j]^T`` with the lever
    arms ``f`` (nf,3). Returns N (K+3nf, K+3nf), rhs, ``sum p^T W p`` (the weighted squared
    residual at the solution x is that less ``x . rhs``) and the number of points used."""
    m, N_ = col.shape
    K = Phi.shape[2]
    dim = K + 3 * nf
    Nm = np.zeros((dim, dim))
    rhs = np.zeros(dim)
    bb = 0.0
    cnt = 0
    L = np.empty((3, 3))
    C = np.empty((3, 3))
    W = np.empty((3, 3))
    Sk = np.zeros((3, 3))
    nu = K + 3
    A = np.empty((3, nu))  # the point's design rows on its used columns
    AW = np.empty((nu, 3))
    cols = np.empty(nu, dtype=np.int64)
    for k in range(K):
        cols[k] = k
    for j in range(m):
        for i in range(N_):
            c = col[j, i]
            if c < 0:
                continue
            fx, fy, fz = f[c, 0], f[c, 1], f[c, 2]
            Sk[0, 1], Sk[0, 2], Sk[1, 0], Sk[1, 2], Sk[2, 0], Sk[2, 1] = -fz, fy, fz, -fx, -fy, fx
            for a in range(3):  # lever = R [f x]
                for b in range(3):
                    L[a, b] = R[j, a, 0] * Sk[0, b] + R[j, a, 1] * Sk[1, b] + R[j, a, 2] * Sk[2, b]
            for a in range(3):
                for b in range(3):
                    s = cov[j, i, a, b]
                    for q in range(3):
                        for r in range(3):
                            s += L[a, q] * cov_G[j, q, r] * L[b, r]
                    C[a, b] = s
            det = (C[0, 0] * (C[1, 1] * C[2, 2] - C[1, 2] * C[2, 1])
                   - C[0, 1] * (C[1, 0] * C[2, 2] - C[1, 2] * C[2, 0])
                   + C[0, 2] * (C[1, 0] * C[2, 1] - C[1, 1] * C[2, 0]))  # fmt: skip
            if not det > 0.0:
                continue
            W[0, 0] = (C[1, 1] * C[2, 2] - C[1, 2] * C[2, 1]) / det
            W[0, 1] = (C[0, 2] * C[2, 1] - C[0, 1] * C[2, 2]) / det
            W[0, 2] = (C[0, 1] * C[1, 2] - C[0, 2] * C[1, 1]) / det
            W[1, 0] = (C[1, 2] * C[2, 0] - C[1, 0] * C[2, 2]) / det
            W[1, 1] = (C[0, 0] * C[2, 2] - C[0, 2] * C[2, 0]) / det
            W[1, 2] = (C[0, 2] * C[1, 0] - C[0, 0] * C[1, 2]) / det
            W[2, 0] = (C[1, 0] * C[2, 1] - C[1, 1] * C[2, 0]) / det
            W[2, 1] = (C[0, 1] * C[2, 0] - C[0, 0] * C[2, 1]) / det
            W[2, 2] = (C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]) / det
            o = K + 3 * c
            for b in range(3):
                cols[K + b] = o + b
            for a in range(3):
                for k in range(K):
                    A[a, k] = Phi[j, a, k]
                for b in range(3):
                    A[a, K + b] = R[j, a, b]
            for u in range(nu):
                for b in range(3):
                    AW[u, b] = A[0, u] * W[0, b] + A[1, u] * W[1, b] + A[2, u] * W[2, b]
            for a in range(3):
                for b in range(3):
                    bb += p[j, i, a] * W[a, b] * p[j, i, b]
            cnt += 1
            for u in range(nu):
                cu = cols[u]
                rhs[cu] += AW[u, 0] * p[j, i, 0] + AW[u, 1] * p[j, i, 1] + AW[u, 2] * p[j, i, 2]
                for v in range(nu):
                    Nm[cu, cols[v]] += AW[u, 0] * A[0, v] + AW[u, 1] * A[1, v] + AW[u, 2] * A[2, v]
    return Nm, rhs, bb, cnt
