"""Compiled (numba) per-run loop of the Hu 2024 EKF: the same filter as the numpy path of
:func:`tumblenav.estimators.ekf_dpacf.run_filter`, step for step.

Why by hand: the filter's cost is thousands of tiny (3x3, 3x33, 9x9) products per epoch.
Batched numpy over runs pays a temporary array and a Python dispatch for each of them, which
profiling showed to be most of the time (``docs/results/hu2024.md``, Speed); no library offers
an error-state EKF with this structure. The kernel writes the loops out once per run, exploits
the structure of H (attitude, position and one feature block per measurement) and of Phi
(block diagonal), and keeps everything in registers-sized loops.

Covered: ``dpacf_measurement: attitude`` without the innovation gate (the defaults), for
ekf-dpacf and ekf-baseline. The other options run on the numpy path. ``tests/test_ekf_dpacf.py``
checks that both paths give the same states, covariances, NIS and NEES.

State layout (:func:`tumblenav.estimators.ekf_dpacf.layout`): nominal
``[q(4), w(3), p(3), r(3), v(3), f(3N)]``, error ``[dtheta(3), dw(3), dp(3), dr(3), dv(3),
df(3N)]``; the offsets below are read from it. The quaternion algebra is
:mod:`tumblenav.rotations_compiled`'s, the attitude RK4 :mod:`tumblenav.dynamics.compiled`'s.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tumblenav.dynamics.compiled import rk4_attitude
from tumblenav.estimators.hu2024.frame import TURN_NODES, TURN_WEIGHTS
from tumblenav.estimators.hu2024.model import layout
from tumblenav.rotations_compiled import (
    boxminus,
    boxplus,
    exp_quat,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
)

# Floating-point licence for the compiler: reassociation and fused multiply-add let it
# vectorise the sums; NaN and inf semantics are kept (the divergence checks rely on them).
# The inlined primitives of rotations_compiled and dynamics.compiled run under it too.
_FM = {"reassoc", "contract", "arcp", "nsz"}

# Block offsets, read once from ekf_dpacf's StateLayout (numba cannot call it: plain ints,
# frozen into the compiled code). Error state:
_LAYOUT = layout(0)
_BLOCKS = ("attitude", "rate", "inertia", "position", "velocity", "features")
_SA, _SW, _SP, _SR, _SV, _SF = (_LAYOUT.err(b).start for b in _BLOCKS)
# nominal state:
_NQ, _NW, _NP, _NR, _NV, _NF = (_LAYOUT.nom(b).start for b in _BLOCKS)
# The loops below are written for this order (the rotation's 9 error states, then [r, v],
# then the features; a nominal index is its error index + 1 after the quaternion).
_SHIFT = _NW - _SW
if (_SA, _SW, _SP, _SR, _SV, _SF) != (0, 3, 6, 9, 12, 15) or _SHIFT != 1 or _NV != _NR + 3:
    raise ImportError("hu2024.kernels: model.layout changed; the kernel's loops need updating")


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _boxplus(x, dx):
    """``StateLayout.boxplus`` for this layout, in place: q <- exp(dtheta) (x) q."""
    boxplus(x[_NQ : _NQ + 4], dx[_SA : _SA + 3], x[_NQ : _NQ + 4])
    for i in range(_SW, dx.shape[0]):
        x[i + _SHIFT] += dx[i]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _mm_into(A, B, C):
    """C = A @ B for small dense matrices (explicit loops, zero entries of A skipped: a BLAS
    call per 3x3 or 9x9 product costs more than the product)."""
    n, m, r = A.shape[0], A.shape[1], B.shape[1]
    for i in range(n):
        for j in range(r):
            C[i, j] = 0.0
        for k in range(m):
            a = A[i, k]
            if a != 0.0:
                for j in range(r):
                    C[i, j] += a * B[k, j]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _mm(A, B):
    """A @ B (a new array) for small dense matrices, see :func:`_mm_into`."""
    C = np.empty((A.shape[0], B.shape[1]))
    _mm_into(A, B, C)
    return C


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _inv3(S, out):
    """Inverse of a 3x3 matrix by cofactors (as ``ekf_dpacf._inv3``)."""
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    d, e, f = S[1, 0], S[1, 1], S[1, 2]
    g, h, i = S[2, 0], S[2, 1], S[2, 2]
    A, B_, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B_ + c * C
    out[0, 0], out[0, 1], out[0, 2] = A / det, -(b * i - c * h) / det, (b * f - c * e) / det
    out[1, 0], out[1, 1], out[1, 2] = B_ / det, (a * i - c * g) / det, -(a * f - c * d) / det
    out[2, 0], out[2, 1], out[2, 2] = C / det, -(a * h - b * g) / det, (a * e - b * d) / det


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _rk4(x, dt):
    """``ekf_dpacf.propagate_rotation``: RK4 of q and omega (Hu 2024 eq. 2, 21), in place."""
    qn = np.empty(4)
    rk4_attitude(x[_NQ : _NQ + 4], x[_NW : _NW + 3], x[_NP : _NP + 3], dt, qn, x[_NW : _NW + 3])
    nrm = math.sqrt(qn[0] ** 2 + qn[1] ** 2 + qn[2] ** 2 + qn[3] ** 2)
    for i in range(4):
        x[_NQ + i] = qn[i] / nrm


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _frame_jac(w, p):
    """``model.frame_error_rate_jacobian`` of one run: ``G = M(omega, p) [omega x] -
    [K(omega) x]`` (3, 3)."""
    wx, wy, wz = w[0], w[1], w[2]
    K0, K1, K2 = p[0] * wy * wz, p[1] * wx * wz, p[2] * wx * wy
    M = np.zeros((3, 3))
    M[0, 1], M[0, 2] = p[0] * wz, p[0] * wy
    M[1, 0], M[1, 2] = p[1] * wz, p[1] * wx
    M[2, 0], M[2, 1] = p[2] * wy, p[2] * wx
    Sw = np.zeros((3, 3))
    Sw[0, 1], Sw[0, 2], Sw[1, 0], Sw[1, 2], Sw[2, 0], Sw[2, 1] = -wz, wy, wz, -wx, -wy, wx
    G = _mm(M, Sw)
    G[0, 1] += K2  # - [K x]
    G[0, 2] -= K1
    G[1, 0] -= K2
    G[1, 2] += K0
    G[2, 0] += K1
    G[2, 1] -= K0
    return G


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _frame_error_qc(w, p, C, tau_max, out):
    """``model.frame_error_Qc`` of one run into ``out`` (3, 3): ``G C G^T tau`` with
    ``G = M(omega, p) [omega x] - [K(omega) x]``, ``tau = min(|omega| / |K|, tau_max)``."""
    wx, wy, wz = w[0], w[1], w[2]
    K0, K1, K2 = p[0] * wy * wz, p[1] * wx * wz, p[2] * wx * wy
    G = _frame_jac(w, p)
    k = math.sqrt(K0 * K0 + K1 * K1 + K2 * K2)
    wn = math.sqrt(wx * wx + wy * wy + wz * wz)
    tau = wn / k if k * tau_max > wn else tau_max
    GC = _mm(G, C)
    for i in range(3):
        for j in range(3):
            s = 0.0
            for m in range(3):
                s += GC[i, m] * G[j, m]
            out[i, j] = s * tau
    for i in range(3):
        for j in range(i + 1, 3):
            v = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = v
            out[j, i] = v


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _rotation_discrete(w, p, s_r2, dt, ws, Qf):
    """``ekf_dpacf.discretise(core_F(.., rotation_only=True), core_Qc[:9, :9], dt)``, with
    ``Qf`` (3, 3) added to the rate block of Qc (the frame error's share, ``_frame_error_qc``):
    Phi (eq. 38, 4th-order series) and Q_k (eq. 39, Van Loan to dt^3) of the 9-state block,
    written into the workspace ``ws`` (9, 9, 9): F, F^2, F^3, F^4, F Qc, F^2 Qc, F Qc F^T, then
    returned as views ``Phi = ws[7]``, ``Q_k = ws[8]``."""
    F, A2, A3, A4, FQ, F2Q, T, Phi, Qk = (
        ws[0],
        ws[1],
        ws[2],
        ws[3],
        ws[4],
        ws[5],
        ws[6],
        ws[7],
        ws[8],
    )
    F[:, :] = 0.0
    wx, wy, wz = w[0], w[1], w[2]
    px, py, pz = p[0], p[1], p[2]
    F[0, 1], F[0, 2] = wz, -wy  # -[w x]
    F[1, 0], F[1, 2] = -wz, wx
    F[2, 0], F[2, 1] = wy, -wx
    F[0, 3] = F[1, 4] = F[2, 5] = -1.0
    F[3, 4], F[3, 5] = px * wz, px * wy  # M(omega, p), eq. 30
    F[4, 3], F[4, 5] = py * wz, py * wx
    F[5, 3], F[5, 4] = pz * wy, pz * wx
    F[3, 6] = wy * wz  # N(omega), eq. 30
    F[4, 7] = wx * wz
    F[5, 8] = wx * wy
    _mm_into(F, F, A2)  # powers of F; the series takes dt^k / k! below
    _mm_into(A2, F, A3)
    _mm_into(A2, A2, A4)
    dt2, dt3, dt4 = dt * dt, dt * dt * dt, dt * dt * dt * dt
    for i in range(9):
        for j in range(9):
            Phi[i, j] = (
                (1.0 if i == j else 0.0)
                + F[i, j] * dt
                + A2[i, j] * dt2 / 2
                + A3[i, j] * dt3 / 6
                + A4[i, j] * dt4 / 24
            )
    j1 = (1 - py) / (1 + px)  # J(p) of eq. 22 (noise_gain)
    j2 = (1 + pz) / (1 - px)
    Qc3 = Qf.copy()  # Qc's rate block: diag(q3, q4, q5) + Qf, zero elsewhere
    Qc3[0, 0] += s_r2
    Qc3[1, 1] += s_r2 * j1 * j1
    Qc3[2, 2] += s_r2 * j2 * j2
    for i in range(9):  # F Qc: columns 3..5 from F's columns 3..5 times Qc3
        for j in range(9):
            FQ[i, j] = 0.0
        for j in range(3):
            FQ[i, 3 + j] = F[i, 3] * Qc3[0, j] + F[i, 4] * Qc3[1, j] + F[i, 5] * Qc3[2, j]
    _mm_into(F, FQ, F2Q)
    for i in range(9):  # T = F Qc F^T
        for j in range(9):
            T[i, j] = FQ[i, 3] * F[j, 3] + FQ[i, 4] * F[j, 4] + FQ[i, 5] * F[j, 5]
    for i in range(9):
        for j in range(i, 9):
            qc = 0.0
            if 3 <= i <= 5 and 3 <= j <= 5:
                qc = Qc3[i - 3, j - 3]
            v = (
                qc * dt
                + (FQ[i, j] + FQ[j, i]) * dt2 / 2
                + (F2Q[i, j] + 2 * T[i, j] + F2Q[j, i]) * dt3 / 6
            )
            Qk[i, j] = v  # symmetric by construction
            Qk[j, i] = v
    return Phi, Qk


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _predict_cov(P, Phr, Qr, Pht, Qt):
    """P <- Phi P Phi^T + Q with Phi = blockdiag(Phr (9), Pht (6), I), for a symmetric P.

    Rows first, ``W = Phi[:15] P[:15]`` (zero entries of Phi skipped: the inertia rows of
    Phr are the identity), then the columns: the feature columns of the result are ``W``
    itself (Phi is the identity there) and are mirrored into the feature rows."""
    d = P.shape[0]
    W = np.zeros((15, d))
    for r in range(9):
        for m in range(9):
            a = Phr[r, m]
            if a != 0.0:
                for j in range(d):
                    W[r, j] += a * P[m, j]
    for r in range(6):
        for m in range(6):
            a = Pht[r, m]
            if a != 0.0:
                for j in range(d):
                    W[9 + r, j] += a * P[9 + m, j]
    for i in range(15):
        for j in range(9):
            s = 0.0
            for m in range(9):
                s += W[i, m] * Phr[j, m]
            P[i, j] = s
        for j in range(6):
            s = 0.0
            for m in range(6):
                s += W[i, 9 + m] * Pht[j, m]
            P[i, 9 + j] = s
        for j in range(15, d):
            P[i, j] = W[i, j]
            P[j, i] = W[i, j]
    for i in range(9):
        for j in range(9):
            P[i, j] += Qr[i, j]
    for i in range(6):
        for j in range(6):
            P[9 + i, 9 + j] += Qt[i, j]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _frame_coupling(ws, G, dt, Gam):
    """The rotation block's transition to the frame error u (``Gam`` (9, 3)): the upper
    right block of the 4th-order series of ``exp([[F, E], [0, 0]] dt)``, ``E`` = G on the
    rate rows (``discretise`` of the augmented F in ``filter.HuSteps.predict``), from the
    powers of F in the workspace of :func:`_rotation_discrete` (called first)."""
    F, A2, A3 = ws[0], ws[1], ws[2]
    dt2, dt3, dt4 = dt * dt, dt * dt * dt, dt * dt * dt * dt
    for i in range(9):
        for c in range(3):
            s = 0.0
            for m in range(3):
                coef = (
                    (dt if i == 3 + m else 0.0)
                    + F[i, 3 + m] * dt2 / 2
                    + A2[i, 3 + m] * dt3 / 6
                    + A3[i, 3 + m] * dt4 / 24
                )
                s += coef * G[m, c]
            Gam[i, c] = s


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _predict_cross(P, Gam, d):
    """After :func:`_predict_cov` (which carries u's rows and columns unchanged), the
    frame error's share of the transition: rows of the rotation block gain ``Gam P[u, :]``,
    columns its transpose, the block itself ``Gam P_uu Gam^T`` (u at ``d .. d + 2``)."""
    D = P.shape[0]
    Pu = P[:, d : d + 3].copy()  # (D, 3): Phi P[:, u]
    T1 = np.zeros((9, D))
    for i in range(9):
        for j in range(D):
            T1[i, j] = Gam[i, 0] * Pu[j, 0] + Gam[i, 1] * Pu[j, 1] + Gam[i, 2] * Pu[j, 2]
    for i in range(9):
        for j in range(D):
            P[i, j] += T1[i, j]
    for i in range(D):
        for j in range(9):
            P[i, j] += T1[j, i]
    GP = _mm(Gam, Pu[d : d + 3].copy())  # Gam P_uu
    for i in range(9):
        for j in range(9):
            P[i, j] += GP[i, 0] * Gam[j, 0] + GP[i, 1] * Gam[j, 1] + GP[i, 2] * Gam[j, 2]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _frame_transition(Co, Cn, A):
    """``frame.frame_error_transition`` of one run into ``A`` (3, 3)."""
    Lo = np.zeros((3, 3))
    Ln = np.zeros((3, 3))
    _chol3(Co, Lo)
    _chol3(Cn, Ln)
    A[:, :] = 0.0
    if not Lo[0, 0] * Lo[1, 1] * Lo[2, 2] > 0.0:
        return
    if np.linalg.eigvalsh(Co - Cn)[0] >= 0.0:
        Ci = np.empty((3, 3))
        _inv3(Co, Ci)
        _mm_into(Cn, Ci, A)
    else:
        Li = np.empty((3, 3))
        _inv3(Lo, Li)
        _mm_into(Ln, Li, A)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _turned_error(P, C, N, out):
    """``frame.turned_error_cov`` of one run, added to ``out`` (d, d): block ``(a, b)`` of
    the turned blocks (attitude with 1/2, rate, features) gains ``s_a s_b sum_mn C_mn E_m
    P_ab E_n^T``, ``E_m = [e_m x]``, P the filter's own covariance."""
    nb = 2 + N
    offs = np.empty(nb, dtype=np.int64)
    sc = np.ones(nb)
    offs[0] = _SA
    sc[0] = 0.5
    for blk in range(1, nb):
        offs[blk] = _SW if blk == 1 else _SF + 3 * (blk - 2)
    E = np.zeros((3, 3, 3))  # E[m] = [e_m x]
    E[0, 1, 2], E[0, 2, 1] = -1.0, 1.0
    E[1, 0, 2], E[1, 2, 0] = 1.0, -1.0
    E[2, 0, 1], E[2, 1, 0] = -1.0, 1.0
    T = np.empty((3, 3))
    for ba in range(nb):
        oa = offs[ba]
        for bb in range(nb):
            ob = offs[bb]
            w = sc[ba] * sc[bb]
            for i in range(3):
                for j in range(3):
                    T[i, j] = 0.0
            for m in range(3):
                for n_ in range(3):
                    c = C[m, n_]
                    if c == 0.0:
                        continue
                    for i in range(3):
                        for j in range(3):
                            acc = 0.0
                            for k in range(3):
                                em = E[m, i, k]
                                if em == 0.0:
                                    continue
                                for l in range(3):
                                    acc += em * P[oa + k, ob + l] * E[n_, j, l]
                            T[i, j] += c * acc
            for i in range(3):
                for j in range(3):
                    out[oa + i, ob + j] += w * T[i, j]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _absorb(P, dx, HP, S, nu):
    """One 3-row block of the sequential update (Hu 2024 eq. 40-42, Joseph form evaluated
    as P - (HP)^T S^-1 (HP) for the optimal gain); returns the block's NIS."""
    d = P.shape[0]
    Si = np.empty((3, 3))
    _inv3(S, Si)
    Kt = np.zeros((3, d))  # S^-1 H P = K^T
    for a in range(3):
        for c in range(3):
            s = Si[a, c]
            for j in range(d):
                Kt[a, j] += s * HP[c, j]
    for j in range(d):
        dx[j] += nu[0] * Kt[0, j] + nu[1] * Kt[1, j] + nu[2] * Kt[2, j]
    # whole rows (contiguous, vectorised); the caller symmetrises after the last block
    for i in range(d):
        h0, h1, h2 = HP[0, i], HP[1, i], HP[2, i]
        for j in range(d):
            P[i, j] -= h0 * Kt[0, j] + h1 * Kt[1, j] + h2 * Kt[2, j]
    nis = 0.0
    for a in range(3):
        for c in range(3):
            nis += nu[a] * Si[a, c] * nu[c]
    return nis


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _update(x, P, k, N, p_L, cov_L, usable, q_meas, R0, use_att, R_LI, f_lin, fej, x_lin):
    """``ekf_dpacf._update_sequential`` for one run: the DPACF attitude (eq. 31), then each
    visible feature (eq. 32-35), all linearised at ``x_lin`` (the prior, or an iterate of
    the iterated update: then each innovation adds ``H (x_lin boxminus prior)``). Returns
    (NIS, dof)."""
    d = P.shape[0]
    dx = np.zeros(d)
    nis = 0.0
    dof = 0
    # delta = x_lin boxminus x (zero unless iterating)
    dl = np.zeros(d)
    boxminus(x_lin[_NQ : _NQ + 4], x[_NQ : _NQ + 4], dl[_SA : _SA + 3])
    for i in range(_SW, d):
        dl[i] = x_lin[i + _SHIFT] - x[i + _SHIFT]
    Rq = np.empty((3, 3))
    quat_to_matrix(x_lin[_NQ : _NQ + 4], Rq)
    R_LT = _mm(R_LI[k], Rq.T.copy())
    HP = np.empty((3, d))
    S = np.empty((3, 3))
    nu = np.empty(3)
    if use_att:
        ok0 = True
        for i in range(4):
            if not np.isfinite(q_meas[k, i]):
                ok0 = False
        if ok0:
            for a in range(3):
                for j in range(d):
                    HP[a, j] = P[_SA + a, j]
                for c in range(3):
                    S[a, c] = HP[a, _SA + c] + R0[a, c]
            boxminus(q_meas[k], x_lin[_NQ : _NQ + 4], nu)
            for a in range(3):
                nu[a] += dl[_SA + a]
            nis += _absorb(P, dx, HP, S, nu)
            dof += 3
    r = x_lin[_NR : _NR + 3].copy()
    Hth = np.empty((3, 3))
    for i in range(N):
        if not usable[k, i]:
            continue
        fo = _NF + 3 * i
        fe = _SF + 3 * i
        fl = x_lin[fo : fo + 3].copy()
        if fej and np.isfinite(f_lin[i, 0]):
            fl[:] = f_lin[i]
        # Hth = R_LT [fl x]
        for a in range(3):
            Hth[a, 0] = R_LT[a, 1] * fl[2] - R_LT[a, 2] * fl[1]
            Hth[a, 1] = R_LT[a, 2] * fl[0] - R_LT[a, 0] * fl[2]
            Hth[a, 2] = R_LT[a, 0] * fl[1] - R_LT[a, 1] * fl[0]
        for a in range(3):
            for j in range(d):
                s = P[_SR + a, j]
                for c in range(3):
                    s += Hth[a, c] * P[_SA + c, j] + R_LT[a, c] * P[fe + c, j]
                HP[a, j] = s
        for a in range(3):
            for c in range(3):
                s = HP[a, _SR + c] + cov_L[k, i, a, c]
                for m in range(3):
                    s += HP[a, _SA + m] * Hth[c, m] + HP[a, fe + m] * R_LT[c, m]
                S[a, c] = s
            # innovation against the prediction at x_lin (plus H delta), minus what the
            # earlier blocks moved
            s = p_L[k, i, a] - r[a] - dx[_SR + a] + dl[_SR + a]
            for m in range(3):
                s -= R_LT[a, m] * x_lin[fo + m] + Hth[a, m] * dx[_SA + m] + R_LT[a, m] * dx[fe + m]
                s += Hth[a, m] * dl[_SA + m] + R_LT[a, m] * dl[fe + m]
            nu[a] = s
        nis += _absorb(P, dx, HP, S, nu)
        dof += 3
    for i in range(d):
        for j in range(i + 1, d):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s
    _boxplus(x, dx[: x.shape[0] - _SHIFT])  # P may carry consider parameters after the state
    return nis, dof


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _project(x, P, curvature):
    """``model.project_inertia`` for one run: the ratios moved onto c(p) = 0 along its normal
    (three Newton steps), |p_i| <= 0.999, the covariance's ratio rows and columns projected
    onto the tangent plane (T P T^T, T = I - n n^T), the curvature's variance set back."""
    d = P.shape[0]
    for _ in range(3):
        px, py, pz = x[_NP], x[_NP + 1], x[_NP + 2]
        c = px + py + pz + px * py * pz
        g0, g1, g2 = 1 + py * pz, 1 + px * pz, 1 + px * py
        s = c / (g0 * g0 + g1 * g1 + g2 * g2)
        x[_NP] -= s * g0
        x[_NP + 1] -= s * g1
        x[_NP + 2] -= s * g2
    for i in range(3):
        x[_NP + i] = min(max(x[_NP + i], -0.999), 0.999)
    px, py, pz = x[_NP], x[_NP + 1], x[_NP + 2]
    g = np.array([1 + py * pz, 1 + px * pz, 1 + px * py])
    gg = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
    n = g / np.sqrt(gg)
    T = np.eye(3)
    for a in range(3):
        for b in range(3):
            T[a, b] -= n[a] * n[b]
    rows = np.empty((3, d))  # T P[p, :]
    for a in range(3):
        for j in range(d):
            rows[a, j] = T[a, 0] * P[_SP, j] + T[a, 1] * P[_SP + 1, j] + T[a, 2] * P[_SP + 2, j]
    for a in range(3):
        for j in range(d):
            P[_SP + a, j] = rows[a, j]
    cols = np.empty((d, 3))  # P[:, p] T^T
    for i in range(d):
        for a in range(3):
            cols[i, a] = P[i, _SP] * T[a, 0] + P[i, _SP + 1] * T[a, 1] + P[i, _SP + 2] * T[a, 2]
    for i in range(d):
        for a in range(3):
            P[i, _SP + a] = cols[i, a]
    if curvature:
        _curvature_back(x, P)
    _symmetrise(P)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _curvature_back(x, P):
    """model.curvature_variance at the ratios in ``x``, set back along the gradient there."""
    px, py, pz = x[_NP], x[_NP + 1], x[_NP + 2]
    C = np.array([[0.0, pz, py], [pz, 0.0, px], [py, px, 0.0]])
    CP = _mm(C, P[_SP : _SP + 3, _SP : _SP + 3].copy())
    tr = CP[0, 0] + CP[1, 1] + CP[2, 2]
    v = 0.25 * tr * tr
    for a in range(3):
        for b in range(3):
            v += 0.5 * CP[a, b] * CP[b, a]
    g = np.array([1 + py * pz, 1 + px * pz, 1 + px * py])
    gg = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
    for a in range(3):
        for b in range(3):
            P[_SP + a, _SP + b] += v * g[a] * g[b] / (gg * gg)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _symmetrise(P):
    d = P.shape[0]
    for i in range(d):
        for j in range(i + 1, d):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _constrain(x, P, curvature, project=False):
    """``ekf_dpacf.constrain_inertia`` for one run: c(p) = px + py + pz + px py pz = 0 as a
    near-perfect scalar pseudo-measurement, then |p_i| <= 0.999; with ``project``,
    :func:`_project` instead."""
    if project:
        _project(x, P, curvature)
        return
    d = P.shape[0]
    px, py, pz = x[_NP], x[_NP + 1], x[_NP + 2]
    c = px + py + pz + px * py * pz
    g0, g1, g2 = 1 + py * pz, 1 + px * pz, 1 + px * py
    PH = np.empty(d)
    for i in range(d):
        PH[i] = P[i, _SP] * g0 + P[i, _SP + 1] * g1 + P[i, _SP + 2] * g2
    s = g0 * PH[_SP] + g1 * PH[_SP + 1] + g2 * PH[_SP + 2] + 1e-10
    dx = np.empty(d)
    for i in range(d):
        dx[i] = -PH[i] / s * c
    _boxplus(x, dx[: x.shape[0] - _SHIFT])
    for i in range(d):
        for j in range(d):
            P[i, j] -= PH[i] / s * PH[j]
    for i in range(3):
        x[_NP + i] = min(max(x[_NP + i], -0.999), 0.999)
    if curvature:  # ekf_dpacf.curvature_variance, set back along the new gradient
        _curvature_back(x, P)
    _symmetrise(P)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _diverged(x, P, N, max_rate):
    """``ekf_dpacf._diverged`` for one run."""
    for v in x:
        if not np.isfinite(v):
            return True
    for v in P.ravel():
        if not np.isfinite(v):
            return True
    w = math.sqrt(x[_NW] ** 2 + x[_NW + 1] ** 2 + x[_NW + 2] ** 2)
    if not w < max_rate:
        return True
    for i in range(3):
        if not abs(x[_NP + i]) < 10:
            return True
    for i in range(3 * N):
        if not abs(x[_NF + i]) < 1e3:
            return True
    return False


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _follow_branch(x, P, q_meas, N, flips, qflips, votes, need, f_first):
    """``ekf_dpacf._follow_dpacf_branch`` for one run (the features' first estimates
    ``f_first`` (N, 3) turned too); returns the new vote count and whether the state was
    turned."""
    for i in range(4):
        if not np.isfinite(q_meas[i]):
            return votes, False  # no measurement: the streak is kept
    Re = np.empty((3, 3))
    Rm = np.empty((3, 3))
    quat_to_matrix(x[_NQ : _NQ + 4], Re)
    quat_to_matrix(q_meas, Rm)
    D = _mm(Rm, Re.T.copy())
    best, which = 1e300, 0
    for f in range(3):
        s = 0.0
        for a in range(3):
            for c in range(3):
                e = D[a, c] - flips[f, a, c]
                s += e * e
        s = math.sqrt(s)
        if s < best:
            best, which = s, f
    if not best < 1.0:
        return 0, False
    votes += 1
    if votes < need:
        return votes, False
    sg = np.ones(P.shape[0])  # J = diag of +-1 (the turn is a diagonal matrix)
    for a in range(3):
        fa = flips[which, a, a]
        sg[_SA + a] = fa
        sg[_SW + a] = fa
        for i in range(N):
            sg[_SF + 3 * i + a] = fa
        if P.shape[0] > _SF + 3 * N:  # the frame error's coordinates turn too
            sg[_SF + 3 * N + a] = fa
    q = x[_NQ : _NQ + 4].copy()
    quat_multiply(qflips[which], q, x[_NQ : _NQ + 4])
    for a in range(3):
        fa = flips[which, a, a]
        x[_NW + a] *= fa
        for i in range(N):
            x[_NF + 3 * i + a] *= fa
            f_first[i, a] *= fa
    for i in range(P.shape[0]):
        for j in range(P.shape[0]):
            P[i, j] *= sg[i] * sg[j]
    return 0, True


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _turn(x, P, F, N, f_first):
    """``ekf_dpacf._turn_state`` for one run: re-express the state in a frame turned by the
    rotation ``F`` (new = F old) -- q <- F q, omega <- F omega, f_i <- F f_i, the features'
    first estimates too, and P <- J P J^T with F on the attitude, rate and feature blocks."""
    d = P.shape[0]
    qF = matrix_to_quat(F.reshape(1, 3, 3))[0]
    q = x[_NQ : _NQ + 4].copy()
    quat_multiply(qF, q, x[_NQ : _NQ + 4])
    v = np.empty(3)
    nb = 2 + N
    for blk in range(nb):
        if blk == 0:
            o = -1
        elif blk == 1:
            o = _NW
        else:
            o = _NF + 3 * (blk - 2)
        if o >= 0:
            for a in range(3):
                v[a] = F[a, 0] * x[o] + F[a, 1] * x[o + 1] + F[a, 2] * x[o + 2]
            x[o : o + 3] = v
    for i in range(N):
        for a in range(3):
            v[a] = F[a, 0] * f_first[i, 0] + F[a, 1] * f_first[i, 1] + F[a, 2] * f_first[i, 2]
        f_first[i] = v
    if d > _SF + 3 * N:  # the frame error as a consider parameter: its coordinates too
        nb += 1
    W = np.empty((3, d))
    for blk in range(nb):  # rows: P[blk, :] <- F P[blk, :]
        o = _SA if blk == 0 else (_SW if blk == 1 else _SF + 3 * (blk - 2))
        for a in range(3):
            for j in range(d):
                W[a, j] = F[a, 0] * P[o, j] + F[a, 1] * P[o + 1, j] + F[a, 2] * P[o + 2, j]
        P[o : o + 3, :] = W
    for blk in range(nb):  # columns: P[:, blk] <- P[:, blk] F^T
        o = _SA if blk == 0 else (_SW if blk == 1 else _SF + 3 * (blk - 2))
        for i in range(d):
            c0, c1, c2 = P[i, o], P[i, o + 1], P[i, o + 2]
            for a in range(3):
                P[i, o + a] = F[a, 0] * c0 + F[a, 1] * c1 + F[a, 2] * c2


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _chol3(C, L):
    """``ekf_dpacf._chol3`` for one 3x3 matrix (guarded lower Cholesky factor)."""
    L[:, :] = 0.0
    L[0, 0] = math.sqrt(max(C[0, 0], 0.0))
    if L[0, 0] > 0.0:
        L[1, 0] = C[1, 0] / L[0, 0]
        L[2, 0] = C[2, 0] / L[0, 0]
    L[1, 1] = math.sqrt(max(C[1, 1] - L[1, 0] * L[1, 0], 0.0))
    if L[1, 1] > 0.0:
        L[2, 1] = (C[2, 1] - L[2, 0] * L[1, 0]) / L[1, 1]
    L[2, 2] = math.sqrt(max(C[2, 2] - L[2, 0] * L[2, 0] - L[2, 1] * L[2, 1], 0.0))


P_TURN_MIN = 1e-9  # = ekf_dpacf.P_TURN_MIN (tested)
_TURN_Z, _TURN_W = TURN_NODES.copy(), TURN_WEIGHTS.copy()  # frame._turn_moments' rule


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _turn_points(x, mu, S, N, D, U):
    """``frame._turn_moments``' nodes for one run: ``U[s]`` (27, 3) = ``mu + L z_s`` (``S =
    L L^T``, ``z_s`` the Gauss-Hermite nodes ``frame.TURN_NODES``, weights ``_TURN_W``) and
    ``D[s]`` (27, 2 + N, 3) = ``[u; R(u) w - w; R(u) f_i - f_i]`` there."""
    L = np.empty((3, 3))
    _chol3(S, L)
    u = np.empty(3)
    qu = np.empty(4)
    Ru = np.empty((3, 3))
    for sp in range(_TURN_Z.shape[0]):
        for a in range(3):
            u[a] = mu[a] + L[a, 0] * _TURN_Z[sp, 0] + L[a, 1] * _TURN_Z[sp, 1]
            u[a] += L[a, 2] * _TURN_Z[sp, 2]
            U[sp, a] = u[a]
        exp_quat(u, qu)
        quat_to_matrix(qu, Ru)
        for a in range(3):
            D[sp, 0, a] = u[a]
        for blk in range(1, 2 + N):
            o = _NW if blk == 1 else _NF + 3 * (blk - 2)
            for a in range(3):
                D[sp, blk, a] = (
                    Ru[a, 0] * x[o] + Ru[a, 1] * x[o + 1] + Ru[a, 2] * x[o + 2] - x[o + a]
                )


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _node_moments(D, U, offs, m1, m2, EuD):
    """Over the nodes of :func:`_turn_points`: ``m1 = E[D]`` (d), ``m2 = E[D D^T]`` (d, d)
    and ``EuD = E[u D^T]`` (3, d), on the attitude, rate and feature entries (the others 0)."""
    m1[:] = 0.0
    m2[:, :] = 0.0
    EuD[:, :] = 0.0
    nb = offs.shape[0]
    for sp in range(D.shape[0]):
        w = _TURN_W[sp]
        for bi in range(nb):
            oi = offs[bi]
            for a in range(3):
                da = D[sp, bi, a] * w
                m1[oi + a] += da
                for c in range(3):
                    EuD[c, oi + a] += da * U[sp, c]
                for bj in range(nb):
                    oj = offs[bj]
                    for c in range(3):
                        m2[oi + a, oj + c] += da * D[sp, bj, c]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _consider_cov(x, P, Pxu, cross, C, p_turn, mu_turn, S_turn, flips, N, out):
    """``frame.frame_consider_cov`` for one run: out = Pc = P plus the second moment, over the
    27 Gauss-Hermite nodes of the frame error ``u ~ N(0, C)``, of ``D(u) = [u; R(u) w - w;
    0; 0; 0; R(u) f_i - f_i]``; with ``cross`` the cross terms ``A E[u D^T]`` and their
    transpose, ``A = Pxu C^+`` (``Pxu`` (d, 3), the consider parameter's cross-covariance);
    then the half turns' mixture ``frame.branch_mixture_cov`` (probabilities ``p_turn``, the
    frame error given each turn ``N(mu_turn[t], S_turn[t])``)."""
    nb = 2 + N
    d = P.shape[0]
    offs = np.empty(nb, dtype=np.int64)
    offs[0] = _SA
    for blk in range(1, nb):
        offs[blk] = _SW if blk == 1 else _SF + 3 * (blk - 2)
    ns = _TURN_Z.shape[0]
    D = np.zeros((ns, nb, 3))
    U = np.zeros((ns, 3))
    m1 = np.zeros(d)
    m2 = np.zeros((d, d))
    EuD = np.zeros((3, d))
    A = np.zeros((d, 3))
    _turn_points(x, np.zeros(3), C, N, D, U)
    _node_moments(D, U, offs, m1, m2, EuD)
    if cross:
        Ci = np.linalg.pinv(C)
        for i in range(d):
            for c in range(3):
                A[i, c] = Pxu[i, 0] * Ci[0, c] + Pxu[i, 1] * Ci[1, c] + Pxu[i, 2] * Ci[2, c]
    X = _mm(A, EuD)  # A E[u D^T]: zero without cross
    for i in range(d):
        for j in range(d):
            out[i, j] = P[i, j] + m2[i, j] + X[i, j] + X[j, i]
    if not (p_turn[0] > P_TURN_MIN or p_turn[1] > P_TURN_MIN or p_turn[2] > P_TURN_MIN):
        return
    Pc = out.copy()
    sg = np.ones(d)
    v = np.zeros(d)
    for t in range(3):
        pt = p_turn[t]
        if not pt > P_TURN_MIN:
            continue
        for i in range(d):
            sg[i] = 1.0
            v[i] = 0.0
        for blk in range(nb):  # J_t = diag(sg); v = F w - w, F f_i - f_i (F diagonal)
            for a in range(3):
                sg[offs[blk] + a] = flips[t, a, a]
        for blk in range(1, nb):
            o = _NW if blk == 1 else _NF + 3 * (blk - 2)
            for a in range(3):
                v[offs[blk] + a] = (flips[t, a, a] - 1.0) * x[o + a]
        # E[D], E[D D^T], E[u D^T] given the turn (only the attitude, rate and feature entries)
        mu = mu_turn[t]
        _turn_points(x, mu, S_turn[t], N, D, U)
        _node_moments(D, U, offs, m1, m2, EuD)
        if cross:  # eps = A u + e: E[(eps + D)(eps + D)^T] and E[eps + D] given the turn
            E = S_turn[t] - C
            for a in range(3):
                for c in range(3):
                    E[a, c] += mu[a] * mu[c]
            AE = _mm(A, E)
            X = _mm(A, EuD)
            for i in range(d):
                m1[i] += A[i, 0] * mu[0] + A[i, 1] * mu[1] + A[i, 2] * mu[2]
                for j in range(d):
                    m2[i, j] += (
                        AE[i, 0] * A[j, 0] + AE[i, 1] * A[j, 1] + AE[i, 2] * A[j, 2]
                        + X[i, j] + X[j, i]
                    )  # fmt: skip
        for i in range(d):
            jm_i = sg[i] * m1[i]
            att_i = _SA <= i < _SA + 3
            for j in range(d):
                if att_i or _SA <= j < _SA + 3:
                    comp = 0.0  # the attitude: below
                else:
                    comp = sg[i] * sg[j] * (P[i, j] + m2[i, j]) + v[i] * v[j]
                    comp += v[i] * sg[j] * m1[j] + jm_i * v[j]
                out[i, j] += pt * (comp - Pc[i, j])
        # the attitude's block: (pi / 2)^2 [e_t x] (P + E[D D^T])_att [e_t x]^T (frame.py)
        Ka = np.zeros((3, 3))
        Ma = np.empty((3, 3))
        for a in range(3):
            for c in range(3):
                Ma[a, c] = P[_SA + a, _SA + c] + m2[_SA + a, _SA + c]
        t1, t2 = (t + 1) % 3, (t + 2) % 3  # [e_t x]: e_t1 -> e_t2, e_t2 -> -e_t1
        Ka[t2, t1] = 0.5 * math.pi
        Ka[t1, t2] = -0.5 * math.pi
        KM = _mm(Ka, Ma)
        for a in range(3):
            for c in range(3):
                s = KM[a, 0] * Ka[c, 0] + KM[a, 1] * Ka[c, 1] + KM[a, 2] * Ka[c, 2]
                out[_SA + a, _SA + c] += pt * s
        out[_SA + t, _SA + t] += pt * math.pi * math.pi


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _recentre(x, p, R_LI, i):
    """``model.recentre_unseen`` for feature ``i`` of one run: ``f_i = R_LT^T (p - r)``."""
    Rq = np.empty((3, 3))
    quat_to_matrix(x[_NQ : _NQ + 4], Rq)
    R_LT = _mm(R_LI, Rq.T.copy())
    fo = _NF + 3 * i
    for a in range(3):
        s = 0.0
        for c in range(3):
            s += R_LT[c, a] * (p[c] - x[_NR + c])
        x[fo + a] = s


@njit(cache=True, fastmath=_FM, error_model="numpy")
def run_filter_kernel(
    t,
    p_L,
    cov_L,
    usable,
    known_at,
    q_meas,
    R0,
    R_LI,
    k0,
    x0,
    P0,
    use_dpacf,
    fej,
    att_every,
    flip_need,
    constrain_every,
    curvature,
    project,
    max_rate,
    s_r2,
    Pht,
    Qt,
    q_feat,
    flips,
    qflips,
    p_every,
    neutral,
    out_x,
    out_P,
    nis,
    nis_dof,
    diverged,
    flip_count,
    consider,
    R_GT,
    cov_frame,
    p_turn,
    mu_turn,
    S_turn,
    skip_start,
    att_update,
    iter_var,
    iter_max,
    frame_tau,
    schmidt,
):
    """All B runs, one after the other. Arrays as in ``run_filter`` (leading run axis);
    ``R0`` (B,n,3,3) is the attitude measurement covariance (inflation applied); ``out_x``
    (B,n,nom) and ``out_P`` (B,ceil(n/p_every),d,d) the history, the covariance of epoch
    ``j p_every`` in ``out_P[:, j]`` (campaigns need it only for the NEES, at about 1 Hz). Outputs are filled in place
    (NaN where inactive or not reported). The kernel never sees the truth: errors and NEES
    are the evaluation's (:mod:`tumblenav.evaluation`).
    ``consider``: the 'consider' frame model, with the front end's frames ``R_GT`` (B,n,3,3,
    NaN where none), their covariances ``cov_frame`` (B,n,3,3, finite), the probabilities
    of their half turns ``p_turn`` (B,n,3) and the frame error given each turn, ``mu_turn``
    (B,n,3,3) and ``S_turn`` (B,n,3,3,3). ``skip_start``: no update at the start epoch (a
    refined start, ``ekf_dpacf.refine_start_pose``, has used it). ``att_update``: update with
    the attitude measurement (else it only votes on the half turns). ``iter_var``: where the
    prior attitude's variance (trace) exceeds it, the update is iterated ``iter_max`` more
    times (relinearised at the last posterior; 0: never). ``frame_tau``: with ``consider``,
    the frame error's share of the rate noise (``model.frame_error_Qc``) with this largest
    correlation time (s; 0: none). ``schmidt``: with ``consider`` and ``frame_tau`` > 0, the
    frame error is a consider parameter instead (``frame_error_model: state``): P carries
    its three rows and columns after the state's, coupled through ``G``
    (:func:`_frame_coupling`), carried across the frame's solutions
    (:func:`_frame_transition`), its own block held at the frame's covariance."""
    B, n, N = usable.shape[0], usable.shape[1], usable.shape[2]
    d = P0.shape[1]
    schmidt = schmidt and consider and frame_tau > 0.0
    D = d + 3 if schmidt else d
    Gam = np.zeros((9, 3))
    A = np.zeros((3, 3))
    for b in range(B):
        x = neutral.copy()
        P = np.eye(D)
        active = False
        votes = 0
        f_first = np.full((N, 3), np.nan)
        ws = np.empty((9, 9, 9))  # workspace of _rotation_discrete
        Qf = np.zeros((3, 3))  # the frame error's share of the rate noise (_frame_error_qc)
        R_used = np.eye(3)  # 'consider': the frame the state is in, and its covariance
        C_used = np.zeros((3, 3))
        k_used = 0
        P_rep = np.empty((d, d))
        for k in range(n):
            if k > 0 and active:
                dt = t[k] - t[k - 1]
                G = np.zeros((3, 3))
                if schmidt:  # the frame error as a consider parameter: d omega/dt -= G u
                    G = -_frame_jac(x[_NW : _NW + 3], x[_NP : _NP + 3])  # (filter.HuSteps)
                elif consider and frame_tau > 0.0:  # white: its share of the rate noise
                    _frame_error_qc(x[_NW : _NW + 3], x[_NP : _NP + 3], C_used, frame_tau, Qf)
                Phr, Qr = _rotation_discrete(x[_NW : _NW + 3], x[_NP : _NP + 3], s_r2, dt, ws, Qf)
                if schmidt:
                    _frame_coupling(ws, G, dt, Gam)
                _rk4(x, dt)
                rv = x[_NR : _NR + 6].copy()
                for i in range(6):
                    s = 0.0
                    for m in range(6):
                        s += Pht[i, m] * rv[m]
                    x[_NR + i] = s
                _predict_cov(P, Phr, Qr, Pht, Qt)
                if schmidt:
                    _predict_cross(P, Gam, d)
                if q_feat > 0.0:  # features' random walk (uniform grid: one dt)
                    for i in range(_SF, d):
                        P[i, i] += q_feat
            start = k == k0[b] and not diverged[b]
            if start:
                x[:] = x0[b]
                P[:, :] = 0.0
                P[:d, :d] = P0[b]
                active = True
            if active and consider and np.all(np.isfinite(R_GT[b, k])):
                if start:
                    R_used[:, :] = R_GT[b, k]
                    if schmidt:
                        P[d:, d:] = cov_frame[b, k]
                elif np.any(R_GT[b, k] != R_used):  # re-solved: F = R_T'G R_GT
                    Ft = _mm(R_GT[b, k].T.copy(), R_used)
                    _turn(x, P, Ft, N, f_first)
                    R_used[:, :] = R_GT[b, k]
                    if schmidt:  # the new frame's error follows the old one's
                        _frame_transition(_mm(_mm(Ft, C_used), Ft.T.copy()), cov_frame[b, k], A)
                        Pu = P[:, d:].copy()
                        for i in range(D):
                            for a in range(3):
                                P[i, d + a] = (
                                    A[a, 0] * Pu[i, 0] + A[a, 1] * Pu[i, 1] + A[a, 2] * Pu[i, 2]
                                )
                        Pu = P[d:, :].copy()
                        for a in range(3):
                            for j in range(D):
                                P[d + a, j] = (
                                    A[a, 0] * Pu[0, j] + A[a, 1] * Pu[1, j] + A[a, 2] * Pu[2, j]
                                )
                C_used[:, :] = cov_frame[b, k]
                k_used = k
            if active:
                upd = not (start and skip_start)  # a refined start used its epoch already
                use_att = use_dpacf and (k % att_every == 0)
                if use_att and upd:
                    votes, turned = _follow_branch(
                        x, P, q_meas[b, k], N, flips, qflips, votes, flip_need, f_first
                    )
                    if turned:
                        flip_count[b] += 1
                use_att = use_att and att_update
                # first estimates (FEJ points; kept in every mode: they mark the features
                # seen so far); a feature first seen after the start has its prior mean
                # moved to the sighting first (model.recentre_unseen)
                for i in range(N):
                    at_start = start and known_at[b, k, i]
                    fresh = at_start or (usable[b, k, i] and not np.isfinite(f_first[i, 0]))
                    if fresh:
                        if not at_start:
                            _recentre(x, p_L[b, k, i], R_LI[b, k], i)
                        f_first[i] = x[_NF + 3 * i : _NF + 3 * i + 3]
                nis_k, dof_k = 0.0, 0
                if upd:
                    # iterated update when the prior attitude is poorly known (after a gap):
                    # relinearise at the posterior, from the same prior
                    its = 0
                    if iter_var > 0.0:
                        tr = P[_SA, _SA] + P[_SA + 1, _SA + 1] + P[_SA + 2, _SA + 2]
                        if tr > iter_var:
                            its = iter_max
                    x_pr = x.copy()
                    P_pr = P.copy()
                    nis_k, dof_k = _update(
                        x, P, k, N, p_L[b], cov_L[b], usable[b], q_meas[b], R0[b, k], use_att,
                        R_LI[b], f_first, fej, x_pr,
                    )  # fmt: skip
                    for _ in range(its):
                        x_it = x.copy()
                        x[:] = x_pr
                        P[:, :] = P_pr
                        nis_k, dof_k = _update(
                            x, P, k, N, p_L[b], cov_L[b], usable[b], q_meas[b], R0[b, k],
                            use_att, R_LI[b], f_first, fej, x_it,
                        )  # fmt: skip
                if start or k % constrain_every == 0:
                    _constrain(x, P, curvature, project)
                if schmidt:  # u is considered, never updated: its covariance is the frame's
                    P[d:, d:] = C_used
                if _diverged(x, P, N, max_rate):  # a run that blew up is stopped and counted
                    diverged[b] = True
                    active = False
                    x[:] = neutral
                    P[:, :] = np.eye(D)
                if active:
                    nis_dof[b, k] = dof_k
                    if dof_k > 0:
                        nis[b, k] = nis_k
            report = active and k % p_every == 0
            if report:
                if consider:
                    Px = P[:d, :d].copy()
                    _turned_error(P, C_used, N, Px)  # the filter's own error turned by u
                    # with the frame error as a consider parameter, the cross terms with u
                    # (frame.frame_consider_cov's P_xu; zeros and unused without)
                    Pxu = P[:d, d:].copy() if schmidt else np.zeros((d, 3))
                    _consider_cov(
                        x, Px, Pxu, schmidt, C_used, p_turn[b, k_used], mu_turn[b, k_used],
                        S_turn[b, k_used], flips, N, P_rep,
                    )  # fmt: skip
                else:
                    P_rep[:, :] = P
                out_P[b, k // p_every] = P_rep
            if active:
                out_x[b, k] = x
