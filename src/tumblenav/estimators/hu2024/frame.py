"""The DPACF frame in the filter: its half-turn branch (followed), and the 'consider' model of
its error (re-expressing the state when the front end re-solves the frame, the reported
covariance with the frame's error and half turns). Beyond the paper."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.estimators.base import (
    StateLayout,
)
from tumblenav.estimators.hu2024.model import _FLIPS

Array = NDArray[np.float64]


def frame_jacobian(x: Array, lay: StateLayout) -> Array:
    """``d(error state) / d u`` (B, d, 3) for a rotation ``u`` (in T) of the principal frame
    in which the state is expressed: the attitude moves by ``u``, the rate and every feature
    turn with it, ``d omega = -[omega x] u``, ``d f_i = -[f_i x] u`` (first order)."""
    B = x.shape[0]
    N = (lay.nominal_dim - lay.nom("features").start) // 3
    Ju = np.zeros((B, lay.dim, 3))
    Ju[:, lay.err("attitude")] = np.eye(3)
    Ju[:, lay.err("rate")] = -rot.skew(x[:, lay.nom("rate")])
    f = x[:, lay.nom("features")].reshape(B, N, 3)
    Ju[:, lay.err("features")] = -rot.skew(f).reshape(B, 3 * N, 3)
    return Ju


def _chol3(C: Array) -> Array:
    """Lower Cholesky factor of (B, 3, 3) positive semi-definite matrices, zero columns where
    a pivot is not positive (the same guarded formulas as the compiled ``_chol3``)."""
    L = np.zeros_like(C)
    with np.errstate(divide="ignore", invalid="ignore"):
        L[:, 0, 0] = np.sqrt(np.maximum(C[:, 0, 0], 0.0))
        ok = L[:, 0, 0] > 0
        L[:, 1, 0] = np.where(ok, C[:, 1, 0] / L[:, 0, 0], 0.0)
        L[:, 2, 0] = np.where(ok, C[:, 2, 0] / L[:, 0, 0], 0.0)
        L[:, 1, 1] = np.sqrt(np.maximum(C[:, 1, 1] - L[:, 1, 0] ** 2, 0.0))
        ok = L[:, 1, 1] > 0
        L[:, 2, 1] = np.where(ok, (C[:, 2, 1] - L[:, 2, 0] * L[:, 1, 0]) / L[:, 1, 1], 0.0)
        L[:, 2, 2] = np.sqrt(np.maximum(C[:, 2, 2] - L[:, 2, 0] ** 2 - L[:, 2, 1] ** 2, 0.0))
    return L


P_TURN_MIN = 1e-9  # half turns less likely than this are left out (= kernels.P_TURN_MIN)


def _turn_nodes() -> tuple[Array, Array]:
    """The 27 nodes ``z`` (27, 3) and weights (27,) of the three-point Gauss-Hermite product
    rule for ``z ~ N(0, I_3)``: per axis ``0, +-sqrt(3)`` with weights 2/3, 1/6, exact for
    polynomials of degree up to 5 in each coordinate, so for every fourth moment
    ``E[z_a z_b z_c z_d]`` (issue 18)."""
    g, w = np.array([-np.sqrt(3.0), 0.0, np.sqrt(3.0)]), np.array([1.0, 4.0, 1.0]) / 6.0
    idx = np.array(np.meshgrid(range(3), range(3), range(3), indexing="ij")).reshape(3, -1).T
    return g[idx], np.prod(w[idx], axis=1)


TURN_NODES, TURN_WEIGHTS = _turn_nodes()


def _turn_moments(x: Array, mu: Array, S: Array, lay: StateLayout) -> tuple[Array, Array, Array]:
    """``E[D]`` (B, d), ``E[D D^T]`` (B, d, d) and ``E[D u^T]`` (B, d, 3) of ``D(u) =
    turn(x, exp(u)) boxminus x = [u; R(u) w - w; 0; 0; 0; R(u) f_i - f_i]`` for ``u ~ N(mu,
    S)`` (mu (B, 3), S (B, 3, 3)), over the 27 nodes ``mu + L z`` (``S = L L^T``) of the
    Gauss-Hermite product rule (:data:`TURN_NODES`).

    Its fourth moments are exact, the second moment of D's quadratic part ``[u x]^2 f / 2``
    with them, cross terms ``u_a u_b`` included. The six points ``mu +- sqrt(3) L e_i`` used
    before hold that part only along three directions: with the frame 1-2 degrees off
    (hu_occ30, at 25 m and features 2.5 m out) the quadratic part is ~1 mm of non-rigid
    shape, which the features' own covariance soon no longer covers (features NEES/dof 6.1
    with six points, 0.69 with 27; issue 18). ``E[D u^T]`` on the same nodes is the
    statistical linearisation of ``D`` that :func:`frame_consider_cov` needs for the
    cross terms with the filter's error (the rule is exact for ``E[u u^T] = S + mu mu^T``)."""
    B = x.shape[0]
    N = (lay.nominal_dim - lay.nom("features").start) // 3
    L = _chol3(np.nan_to_num(S))
    U = mu[:, None, :] + TURN_NODES @ np.swapaxes(L, -1, -2)  # (B, 27, 3)
    R = rot.exp_map(U)  # (B, 27, 3, 3)
    m = len(TURN_WEIGHTS)
    D = np.zeros((B, m, lay.dim))
    D[:, :, lay.err("attitude")] = U
    w = x[:, None, lay.nom("rate"), None]
    D[:, :, lay.err("rate")] = (R @ w)[..., 0] - w[..., 0]
    f = x[:, lay.nom("features")].reshape(B, 1, N, 3)
    D[:, :, lay.err("features")] = (f @ np.swapaxes(R, -1, -2) - f).reshape(B, m, 3 * N)
    Dw = D * TURN_WEIGHTS[:, None]
    Dt = np.swapaxes(Dw, -1, -2)
    return Dw.sum(axis=1), Dt @ D, Dt @ U


def frame_consider_cov(
    x: Array,
    P: Array,
    cov_frame: Array,
    lay: StateLayout,
    p_turn: Array | None = None,
    mu_turn: Array | None = None,
    S_turn: Array | None = None,
    P_xu: Array | None = None,
) -> Array:
    """The covariance the filter reports with the 'consider' frame model (beyond the paper).

    The filter's state is expressed in the front end's DPACF frame, whose error ``u`` against
    the true principal frame (``cov_frame``, from the least-squares covariance of the
    inertia, Hu 2024 eq. 14 and 17) changes only slowly, as the identification accumulates.
    Fed to the filter as white noise at every epoch (Hu 2024 eq. 31), that error was
    averaged down as if it were independent from epoch to epoch, and the attitude and the
    features' common rotation became over-confident (block NEES/dof 20 and 38, see
    docs/results/hu2024.md). Here the filter measures only the white G-attitude part and
    the frame's error is a consider parameter: the error against the truth is the filter's
    error in its frame plus the state turned by ``u`` minus the state, independent of it,
    so the reported covariance is ``P`` plus the second moment of
    ``D(u) = turn(x, exp(u)) boxminus x = [u; R(u) w - w; 0; 0; 0; R(u) f_i - f_i]``
    (to first order ``Ju u``, :func:`frame_jacobian`), over the 27 nodes of a Gauss-Hermite
    rule (:func:`_turn_moments`): at 1e-6 rad the features' shape is known to micrometres while
    the frame is known to a tenth of a degree, and the quadratic part of the turn,
    ``[u x]^2 f / 2``, is then many of the shape's sigmas. With ``p_turn`` (B, 3) and the
    frame error given each turn, ``mu_turn`` (B, 3, 3) and ``S_turn`` (B, 3, 3, 3), all three
    from ``frontends.inertia.branch_statistics``, the half turns of the frame are added,
    :func:`branch_mixture_cov`. With ``P_xu`` (B, d, 3), the filter's error's
    cross-covariance with ``u`` (the frame error carried as a consider parameter,
    ``frame_error_model: state``), the error ``eps + D(u)`` has the cross terms
    ``A E[u D^T]`` and its transpose too, ``A = P_xu C^+`` (statistically linearised on the
    rule's nodes, which keeps the sum positive semi-definite; the first order ``Ju P_ux``
    did not), also in the half turns' components. And the filter's own error is turned by
    ``u`` too (:func:`turned_error_cov`)."""
    B = x.shape[0]
    C = np.nan_to_num(cov_frame)
    P = P + turned_error_cov(P, C, lay)
    _, D2, Du = _turn_moments(x, np.zeros((B, 3)), C, lay)
    out = P + D2
    A = None
    if P_xu is not None:
        # the cross terms E[eps D^T] = A E[u D^T], A = P_xu C^+ (eps's regression on u), on
        # the nodes of D2 itself: the sum is then P - A C A^T (>= 0 for a joint covariance
        # [[P, P_xu], [P_ux, C]] >= 0) plus sum_s w_s (A u_s + D_s)(A u_s + D_s)^T, positive
        # semi-definite. The first-order cross terms Ju P_ux used before are not: at the
        # rule's nodes D falls short of Ju u by O(|u|^2) (R(u) w - w bends away from [u x] w)
        # and where the filter's error and u are nearly fully correlated (after the frame's
        # own re-solutions) that made the sum indefinite: eigenvalues to -1.8e-6 and NEES
        # of -4.5e3 in hu_occ30 run 19 (issue 18, twenty-third session).
        A = P_xu @ np.linalg.pinv(C)
        X = A @ np.swapaxes(Du, -1, -2)
        out = out + X + np.swapaxes(X, -1, -2)
    if p_turn is not None:
        assert mu_turn is not None and S_turn is not None  # the three come together
        out = branch_mixture_cov(x, P, out, p_turn, mu_turn, S_turn, lay, A=A, C=C)
    return out


_GEN = rot.skew(np.eye(3))  # E_m = [e_m x]: [u x] = sum_m u_m E_m


def turned_error_cov(P: Array, C: Array, lay: StateLayout) -> Array:
    """(B, d, d): the second moment of the filter's own error turned by the frame error
    (beyond the paper; 'consider' frame model, issue 18). Against the true principal frame
    the filter's error ``eps`` (in its own frame) is turned too: the rate's and each
    feature's by ``[u x] eps`` (``R(u) = I + [u x] + ...``), the attitude's by
    ``[u x] eps / 2`` (the composition of two small rotations), while the position and
    velocity (in L) and the ratios are not. With ``u ~ N(0, C)`` independent of ``eps ~
    N(0, P)`` (their correlation enters only third moments), block ``(a, b)`` gains
    ``s_a s_b E[[u x] P_ab [u x]^T] = s_a s_b sum_mn C_mn E_m P_ab E_n^T``. Negligible where
    the frame is known to a fraction of a milliradian; with the frame 2-5 degrees off and
    the mass centre known to 2 cm (hu_big12) it is a millimetre on every feature, which the
    position does not share, while their sum, the features' position in L, is measured to
    a fraction of it."""
    N = (lay.nominal_dim - lay.nom("features").start) // 3
    idx = np.concatenate(
        [np.arange(lay.err("attitude").start, lay.err("attitude").stop),
         np.arange(lay.err("rate").start, lay.err("rate").stop),
         np.arange(lay.err("features").start, lay.err("features").stop)]
    )  # fmt: skip
    nb = 2 + N
    sc = np.ones(nb)
    sc[0] = 0.5
    Pt = P[:, idx][:, :, idx].reshape(-1, nb, 3, nb, 3)
    O = np.einsum("zmn,mik,zakbl,njl->zaibj", C, _GEN, Pt, _GEN)
    O = O * sc[None, :, None, None, None] * sc[None, None, None, :, None]
    out = np.zeros_like(P)
    out[:, idx[:, None], idx[None, :]] = O.reshape(-1, 3 * nb, 3 * nb)
    return out


def branch_mixture_cov(
    x: Array,
    P: Array,
    Pc: Array,
    p_turn: Array,
    mu_turn: Array,
    S_turn: Array,
    lay: StateLayout,
    A: Array | None = None,
    C: Array | None = None,
) -> Array:
    """Second moment about the filter's estimate of the two-branch mixture (B, d, d): with
    probability ``p_a`` (``frontends.inertia.branch_statistics``) the truth lies on the
    frame turned by a half turn ``F_a`` about T's axis ``a`` (beyond the paper).

    The sign rules of the DPACF (Hu 2024 eq. 17) make the posterior bimodal near their
    boundary: the estimate is on one branch, the truth may be on the other. ``P``: the
    filter's covariance; ``Pc``: its reported one on this branch (:func:`frame_consider_cov`).
    On the turned branch the error is ``Delta_a + J_a (eps + D(u))``: ``Delta_a = [+-pi e_a;
    F_a w - w; 0; 0; 0; F_a f_i - f_i]`` (the sign of the half-turn rotation vector is
    arbitrary), ``J_a`` (``F_a`` on the attitude, rate and feature blocks, a diagonal of
    signs) turning the filter's own error ``eps ~ N(0, P)`` and the frame error's effect
    ``D(u)``, where, given the turn, ``u ~ N(mu_a, S_a)`` lies beyond the rule's margin.
    So the covariance about the estimate (the mode) is ``(1 - sum p_a) Pc + sum_a p_a (J_a
    (P + E[D D^T]) J_a + M_a + v E[D]^T J_a + J_a E[D] v^T)``, ``M_a`` the average over the
    two signs of ``Delta Delta^T`` (``pi^2 e_a e_a^T`` on the attitude plus ``v v^T``, ``v``
    the non-attitude part), turns with ``p_a <= P_TURN_MIN`` left out. On the attitude the
    small error does not enter as ``J_a eps`` but as ``+-(pi / 2) e_a x eps`` (the rotation
    vector of a half turn composed with ``exp(eps)``, its sign as the boxminus picks it):
    its block is ``(pi / 2)^2 [e_a x] (P + E[D D^T])_att [e_a x]^T`` and, the sign being
    random, it has no cross terms with the other blocks. With ``A`` (B, d, 3),
    the filter's error's regression on the frame error (``eps = A u + e``, ``Cov(e) = P - A
    C A^T``, ``C`` (B, 3, 3) the frame's covariance; :func:`frame_consider_cov`), ``eps`` is
    not independent of the turned branch's ``u``: ``P + E[D D^T]`` becomes the second moment
    of ``eps + D``, ``P - A C A^T + E[(A u + D)(A u + D)^T]`` (on the rule's nodes), and
    ``E[D]`` becomes ``A mu_a + E[D]``: each component a second moment, the mixture positive
    semi-definite."""
    N = (lay.nominal_dim - lay.nom("features").start) // 3
    sa = lay.err("attitude")
    out = Pc.copy()
    for a in range(3):
        sel = np.flatnonzero(p_turn[:, a] > P_TURN_MIN)
        if not len(sel):
            continue
        F = _FLIPS[a]
        sg = np.ones(lay.dim)  # J_a = diag(sg)
        for name in ("attitude", "rate", "features"):
            sl = lay.err(name)
            sg[sl] = np.tile(np.diag(F), (sl.stop - sl.start) // 3)
        xs = x[sel]
        w = xs[:, lay.nom("rate")]
        f = xs[:, lay.nom("features")].reshape(len(sel), N, 3)
        v = np.zeros((len(sel), lay.dim))
        v[:, lay.err("rate")] = w @ F.T - w
        v[:, lay.err("features")] = (f @ F.T - f).reshape(len(sel), -1)
        mu, S = mu_turn[sel, a], S_turn[sel, a]
        m1, m2, Du = _turn_moments(xs, mu, S, lay)
        M = P[sel] + m2
        if A is not None and C is not None:
            As = A[sel]
            Euu = S + mu[:, :, None] * mu[:, None, :]
            X = As @ np.swapaxes(Du, -1, -2)  # E[eps D^T] = A E[u D^T]
            M = M + As @ (Euu - C[sel]) @ np.swapaxes(As, -1, -2) + X + np.swapaxes(X, -1, -2)
            m1 = m1 + (As @ mu[:, :, None])[..., 0]
        Jm = m1 * sg
        comp = M * np.outer(sg, sg) + v[:, :, None] * v[:, None, :]
        comp += v[:, :, None] * Jm[:, None, :] + Jm[:, :, None] * v[:, None, :]
        # the attitude: exp(eps) composed with a half turn about e_a is the rotation vector
        # +-(pi - |e_a . eps|) e_a +- (pi / 2) e_a x eps (to first order; the sign as the
        # boxminus picks it, either with even odds), not J_a eps: its part across e_a is
        # turned by 90 degrees and scaled by pi / 2, and with the random sign it carries no
        # correlation with the other blocks (beyond the paper; issue 18, twenty-third
        # session: hu_occ20 run 43, on the turned branch at 112-120 s and 147-157 s with
        # p = 0.48, whole-state NEES/dof 1e3 while every block's was below 3.1)
        K = (np.pi / 2) * rot.skew(np.eye(3)[a])
        comp[:, sa, :] = 0.0
        comp[:, :, sa] = 0.0
        comp[:, sa, sa] = K @ M[:, sa, sa] @ K.T
        comp[:, sa.start + a, sa.start + a] += np.pi**2
        out[sel] += p_turn[sel, a, None, None] * (comp - Pc[sel])
    return out


def _turn_state(x, P, b, F, lay, f_first=None):
    """Re-express the state of runs ``b`` in a frame turned by ``F`` (B_b, 3, 3), new
    coordinates ``= F`` old: ``q <- F q``, ``omega <- F omega``, ``f_i <- F f_i`` and
    ``P <- J P J^T`` (J: F on the attitude, rate and feature blocks). Exact: the same physical
    state in other coordinates. The features' first estimates (FEJ points) turn with them."""
    qF = rot.matrix_to_quat(F)
    x[b, lay.nom("attitude")] = rot.quat_multiply(qF, x[b, lay.nom("attitude")])
    x[b, lay.nom("rate")] = (F @ x[b, lay.nom("rate"), None])[..., 0]
    N = (lay.nominal_dim - lay.nom("features").start) // 3
    f = x[b, lay.nom("features")].reshape(len(b), N, 3)
    x[b, lay.nom("features")] = (f @ np.swapaxes(F, -1, -2)).reshape(len(b), -1)
    D = P.shape[-1]  # lay.dim, + 3 with the frame error as a consider parameter (its
    J = np.tile(np.eye(D), (len(b), 1, 1))  # coordinates turn with the frame's)
    for name in ("attitude", "rate"):
        sl = lay.err(name)
        J[:, sl, sl] = F
    sf0 = lay.err("features").start
    for i in range(N):
        J[:, sf0 + 3 * i : sf0 + 3 * i + 3, sf0 + 3 * i : sf0 + 3 * i + 3] = F
    if D > lay.dim:
        J[:, lay.dim :, lay.dim :] = F
    P[b] = J @ P[b] @ np.swapaxes(J, -1, -2)
    if f_first is not None:
        f_first[b] = f_first[b] @ np.swapaxes(F, -1, -2)


def frame_error_transition(C_old: Array, C_new: Array) -> Array:
    """``A`` (B,3,3) with ``Cov(u_new, u_old) = A C_old``: how the error of the front end's
    re-solved frame follows the previous one's (both in the new frame's coordinates), for
    the frame error carried as a consider parameter (``frame_error_model: state``; beyond
    the paper). The frame is a growing least squares: for nested best linear unbiased
    estimates the later error is the earlier one's regression, ``Cov(u_new, u_old) =
    C_new``, so ``A = C_new C_old^-1``; where ``C_old - C_new`` is not positive
    semi-definite (a new template, another noise model) that would not be a covariance,
    and ``A = L_new L_old^-1`` (Cholesky factors: the whitened error kept) is used. Either
    keeps the joint covariance positive semi-definite. Zero where ``C_old`` is not
    positive definite."""
    Lo, Ln = _chol3(np.nan_to_num(C_old)), _chol3(np.nan_to_num(C_new))
    det_o = np.prod(np.diagonal(Lo, axis1=-2, axis2=-1), axis=-1)
    ok = det_o > 0
    Ci = np.linalg.inv(np.where(ok[:, None, None], np.nan_to_num(C_old), np.eye(3)))
    Li = np.linalg.inv(np.where(ok[:, None, None], Lo, np.eye(3)))
    nested = np.linalg.eigvalsh(np.nan_to_num(C_old - C_new))[:, 0] >= 0.0
    A = np.where(nested[:, None, None], np.nan_to_num(C_new) @ Ci, Ln @ Li)
    return np.where(ok[:, None, None], A, 0.0)


def _reframe(x, P, R_GT, R_used, active, lay, f_first=None):
    """'consider' frame model: when the front end re-solves its DPACF frame (``R_GT`` (B,3,3),
    NaN where there is none), re-express the state in the new frame (:func:`_turn_state` with
    ``F = R_T'G R_GT``, including the half turns of a branch change). ``R_used`` (B,3,3): the
    frame each run's state is in; updated in place. Returns the runs that have a frame now."""
    ok = active & np.all(np.isfinite(R_GT), axis=(-1, -2))
    if not ok.any():
        return ok
    R_new = np.where(ok[:, None, None], R_GT, np.eye(3))
    F = np.swapaxes(R_new, -1, -2) @ np.nan_to_num(R_used)
    move = ok & np.any(R_new != R_used, axis=(-1, -2))  # re-solved (frames are held between)
    b = np.flatnonzero(move)
    if len(b):
        _turn_state(x, P, b, F[b], lay, f_first)
    R_used[ok] = R_GT[ok]
    return ok


def _follow_dpacf_branch(x, P, q_meas, active, lay, votes, need, flips, f_first=None):
    """Keep the filter on the principal frame that the DPACF rule selects now.

    The DPACF frame is unique for a given inertia, but the identified inertia changes as
    data accumulate; early on it can select the frame turned by 180 degrees about a
    principal axis (a 180-degree attitude innovation that no linear update can absorb).
    When the DPACF attitude and the filter's differ by such a turn for ``need`` consecutive
    measurements, the filter state is turned accordingly: the turn ``F`` is a symmetry of
    the torque-free model (``p`` is unchanged), so ``q <- F q``, ``omega <- F omega``,
    ``f_i <- F f_i`` and ``P <- J P J^T`` are exact. The turns are counted. The features'
    first estimates (``f_first``, (B, N, 3), FEJ linearisation points) are turned with them.
    """
    ok = active & np.all(np.isfinite(q_meas), axis=-1)
    if not ok.any():
        return x, P, votes
    R_est = rot.quat_to_matrix(x[:, lay.nom("attitude")])
    R_meas = rot.quat_to_matrix(np.where(ok[:, None], q_meas, rot.IDENTITY))
    D = R_meas @ np.swapaxes(R_est, -1, -2)  # in T: measured frame relative to the filter's
    dist = np.linalg.norm(D[:, None] - _FLIPS[None], axis=(-1, -2))  # (B, 3)
    which = np.argmin(dist, axis=1)
    near = ok & (dist[np.arange(len(D)), which] < 1.0)  # within ~40 deg of a half turn
    votes = np.where(near, votes + 1, np.where(ok, 0, votes))  # no measurement: streak kept
    go = votes >= need
    if go.any():
        b = np.flatnonzero(go)
        _turn_state(x, P, b, _FLIPS[which[go]], lay, f_first)
        votes[b] = 0
        flips[b] += 1
    return x, P, votes
