"""The actual error covariance of Kabir 2025's UKF against the one it reports: a covariance
analysis of the mismatched filter (Gelb 1974 Sec. 7.2), shared by ``ukf``, ``ukf-mult`` and
``ukf-gp`` (tumblenav addition, issue 18).

The filter's model differs from the truth in three ways the analysis counts:

* its Q on the rigid parameters (inertia ratios, features) is a floor
  (:func:`~.tuning.derive_tuning`): a random walk the rigid truth does not have;
* the measured flow is eq. 27's stencil of the same noisy projections the filter also
  updates with, so its noise is correlated with theirs at ``t +- dt, +- 2 dt`` and with the
  flows of the neighbouring epochs (the filter counts it as independent, diagonal R);
* the stencil sees the truth's random torque over ``t +- 2 dt``: a rate error common to every
  feature's flow and correlated with the process noise of the steps it spans (the filter
  counts it as independent noise per component, ``flow_process_noise_rad_s``).

Linearised along the estimate (Kabir 2025 eq. 8-10 for ``F``, eq. 22-23 for ``H``, finite
differences), the actual error is propagated with the filter's gains and the truth's noise,
the projection noise of the epochs a later flow reuses and the process noise of the steps a
flow spans kept in the analysis' state::

    filter:  P_f <- F P_f F^T + Q,     K = P_f H^T (H P_f H^T + R)^-1,  P_f <- (I-KH) P_f
    actual:  e <- F e + G w,           e <- (I-KH) e - K v,  v = M n + A dw + white

with ``n`` the projection noise at ``t_k-2 .. t_k+2``, ``M`` eq. 27's stencil for the flow rows,
``dw`` the stencil's rate error (the integrated rate walk through eq. 27, on a two-term
Legendre basis per step and axis, which spans it exactly), ``A`` the flow's Jacobian on the rate
and ``w`` the truth's process noise (``q_r (I_max / I_i)^2`` about principal axis ``i``,
:mod:`tumblenav.dynamics.disturbances`; the filter's Q of the rate, ``derive_tuning``, is
``q_r`` about every axis). :func:`report_actual` maps the UKF's covariance onto ``P_a``.

Measured (issue 18, 20 runs, ukf; ``covariance_report`` of
:class:`~.tuning.KabirTuning`): NEES/dof kabir_geometry_observed 0.705 -> 1.02, with every block
near 1 (features 0.58 -> 1.01); kabir_rate005_observed 0.939 -> 1.04,
kabir_inertia_observed 0.968 -> 0.996; kabir_paper_observed 1.07 -> 1.15, its rate and attitude
blocks over-confident (1.7, 2.2) in a way the analysis does not explain (a quiet truth,
q_r = 2.5e-13, gives 0.98 there). The seventh session explained it: the body chart's update
took the turn of the principal frame against the feature set as measured; with the filter and
this analysis in the world chart (``update_chart``, ``actual_covariance(world=True)``)
kabir_paper_observed is 1.01 (docs/results/consistency.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.estimators.base import EstimateHistory
from tumblenav.estimators.kabir2025 import model as ukf_model
from tumblenav.estimators.kabir2025 import observations as ukf_obs
from tumblenav.estimators.kabir2025.tuning import rate_q

Array = NDArray[np.float64]

# Kabir 2025 eq. 27 on the projection noise at t_k-2 .. t_k+2 (times 1 / dt)
_STENCIL = np.array([1.0, -8.0, 0.0, 8.0, -1.0]) / 12.0
_R3 = float(np.sqrt(3.0))
# eq. 27's rate error from a white angular acceleration dW, per step of the stencil (steps
# k-1, k, k+1, k+2, step j spanning (t_j-1, t_j]) on the orthonormal basis 1, sqrt(3)(2s - 1)
# of each step (s in [0, 1]), times sqrt(q) dt^1.5 / (12 dt): the stencil of
# theta(t_k + j dt) - theta(t_k) - j dt omega(t_k) (tumblenav, issue 18); the squares sum to
# 256 / 12, i.e. variance 0.148 q dt, :data:`~.tuning._STENCIL_WALK`.
_WALK_COEF = np.array(
    [[0.5, _R3 / 6.0], [-2.5, -7.0 * _R3 / 6.0], [2.5, -7.0 * _R3 / 6.0], [-0.5, _R3 / 6.0]]
)
# one step's process noise on the same basis: the rate's change sqrt(q dt) xi_0 and the
# attitude's sqrt(q) dt^1.5 (xi_0 / 2 - xi_1 / (2 sqrt 3)) (the integral of (t_k - u) dW)
_ATT_COEF = np.array([0.5, -0.5 / _R3])


def step_jacobians(lay: Any, x: Array, t: Array, idx: NDArray[Any], ks: NDArray[Any]) -> Array:
    """(m, d, d) Jacobians of the rigid-body step ``k-1 -> k`` (Kabir 2025 eq. 8-10,
    :func:`~.model.propagate_rotation`) over the error components ``idx`` (rate, attitude,
    inertia ratios), by finite differences along ``x[k-1]``; identity where ``x`` is not finite."""
    nr, na, nk = lay.nom("rate"), lay.nom("attitude"), lay.nom("inertia")
    d = len(idx)
    eps = 1e-6
    xs = x[ks - 1]
    ok = np.all(np.isfinite(xs), axis=1)
    dX = np.zeros((len(ks), d + 1, lay.dim))
    dX[:, 1:, idx] = eps * np.eye(d)
    X = lay.boxplus(np.repeat(np.where(ok[:, None], xs, 0.0)[:, None, :], d + 1, axis=1), dX)
    dts = t[ks] - t[ks - 1]
    F = np.repeat(np.eye(d)[None], len(ks), axis=0)
    for dt in np.unique(dts):  # one batch per step length (one at a constant rate)
        sel = (dts == dt) & ok
        if not sel.any():
            continue
        w1, q1 = ukf_model.propagate_rotation(X[sel][..., nr], X[sel][..., na], X[sel][..., nk], dt)
        X1 = X[sel].copy()
        X1[..., nr] = w1
        X1[..., na] = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
        E = lay.boxminus(X1[:, 1:], X1[:, :1])[..., idx] / eps  # (m, perturbation j, error)
        F[sel] = np.swapaxes(E, 1, 2)
    return F


def predicted_states(lay: Any, x: Array, t: Array, ks: NDArray[Any]) -> Array:
    """(m, nominal) the rigid-body step ``k-1 -> k`` of ``x[k-1]`` (the filter's prediction of
    the mean, :func:`~.model.propagate_rotation`); NaN where ``x[k-1]`` is not finite."""
    nr, na, nk = lay.nom("rate"), lay.nom("attitude"), lay.nom("inertia")
    xs = np.array(x[ks - 1], dtype=float)
    ok = np.all(np.isfinite(xs), axis=1)
    dts = t[ks] - t[ks - 1]
    out = np.full_like(xs, np.nan)
    for dt in np.unique(dts):
        sel = (dts == dt) & ok
        if not sel.any():
            continue
        w1, q1 = ukf_model.propagate_rotation(xs[sel][:, nr], xs[sel][:, na], xs[sel][:, nk], dt)
        y = xs[sel].copy()
        y[:, nr] = w1
        y[:, na] = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
        out[sel] = y
    return out


def world_jacobians(lay: Any, x: Array, eps: float = 1e-6) -> Array:
    """(m, d, d) Jacobians of the world chart's error (:func:`~.model.world_chart_points`:
    rate and features in I, attitude and inertia ratios as they are) on the body chart's at
    the states ``x`` (m, nominal), by central differences; identity where ``x`` is not
    finite."""
    d = lay.dim
    ok = np.all(np.isfinite(x), axis=1)
    x0 = np.where(ok[:, None], x, 0.0)
    x0[~ok, lay.nom("attitude")] = [0.0, 0.0, 0.0, 1.0]  # a placeholder
    dX = np.concatenate([eps * np.eye(d), -eps * np.eye(d)])
    X = lay.boxplus(
        np.repeat(x0[:, None, :], 2 * d, axis=1), np.broadcast_to(dX, (len(x), 2 * d, d))
    )
    runs = np.ones(len(x), dtype=bool)
    W = ukf_model.world_chart_points(X, runs, to_world=True)
    W0 = ukf_model.world_chart_points(x0[:, None, :], runs, to_world=True)
    E = lay.boxminus(W, np.broadcast_to(W0, W.shape))  # (m, 2d, d)
    J = np.swapaxes((E[:, :d] - E[:, d:]) / (2 * eps), 1, 2)
    J[~ok] = np.eye(d)
    return J


def measurement_jacobians(
    lay: Any, geom: Any, x: Array, ks: NDArray[Any], eps: float = 1e-7
) -> Array:
    """(m, N, 9, d) Jacobians of Kabir 2025 eq. 22-23 (:func:`~.observations.measurement_model`,
    the instantaneous flow) over every error component (rate, attitude, inertia ratios,
    features) at the states ``x`` (m, nominal) of epochs ``ks``, by finite differences."""
    d = lay.dim
    dX = np.zeros((len(ks), d + 1, d))
    dX[:, 1:, :] = eps * np.eye(d)
    X = lay.boxplus(np.repeat(x[:, None, :], d + 1, axis=1), dX)
    h = ukf_obs.measurement_model(
        X, geom.R_CI, geom.rho0_C[ks][:, None, :], geom.rho0_dot_C[ks][:, None, :], geom.centres_x
    )  # (m, d + 1, N, 9)
    return np.moveaxis((h[:, 1:] - h[:, :1]) / eps, 1, -1)


def floor_congruence(Pf: Array, Pa: Array) -> Array:
    """The symmetric positive-definite ``S`` with ``S P_f S = P_a`` (``P_f``, ``P_a`` SPD):
    ``P_f^-1/2 (P_f^1/2 P_a P_f^1/2)^1/2 P_f^-1/2``. Applied as ``S P S`` to a covariance
    ``P`` close to ``P_f`` it gives one close to ``P_a`` and keeps it positive definite."""
    w, V = np.linalg.eigh(0.5 * (Pf + Pf.T))
    w = np.maximum(w, 1e-300)
    h = (V * np.sqrt(w)) @ V.T
    hi = (V / np.sqrt(w)) @ V.T
    m, U = np.linalg.eigh(h @ (0.5 * (Pa + Pa.T)) @ h)
    mid = (U * np.sqrt(np.maximum(m, 0.0))) @ U.T
    return hi @ mid @ hi


def filter_update(
    Pf: Array, H_k: Array, z_k: Array, R_k: Array
) -> tuple[NDArray[np.bool_], Array, Array, Array, Array, Array]:
    """The filter's update at one epoch, as the analysis replays it: the usable components
    ``rows`` (finite measurement, positive variance) of ``z_k`` (N, 9) with variances ``R_k``,
    their Jacobian ``H`` (from ``H_k`` (N, 9, d)), the full variance vector ``R_k`` (flat),
    the gain ``K``, ``A = I - K H`` and the filter's covariance after the update (Joseph
    form)."""
    d = Pf.shape[0]
    zk, Rk = z_k.reshape(-1), R_k.reshape(-1)
    rows = np.isfinite(zk) & np.isfinite(Rk) & (Rk > 0)
    H = H_k.reshape(-1, d)[rows]
    S = H @ Pf @ H.T + np.diag(Rk[rows])
    K = np.asarray(np.linalg.solve(S, H @ Pf).T, dtype=np.float64)
    A = np.eye(d) - K @ H
    return rows, H, Rk, K, A, A @ Pf @ A.T + (K * Rk[rows]) @ K.T


def _stencil_map(N: int, dt: float) -> Array:
    """(9N, 5 * 4N): the measurement noise of one epoch from the projection noise
    ``[u_R, v_R, u_L, v_L]`` of every feature at ``t_k-2 .. t_k+2``: the projections
    themselves, the disparity ``u_L - u_R`` and eq. 27's stencil for the flow."""
    M = np.zeros((N, 9, 5, N, 4))
    for i in range(N):
        for c in range(4):
            M[i, c, 2, i, c] = 1.0
            M[i, 5 + c, :, i, c] = _STENCIL / dt
        M[i, 4, 2, i, 2], M[i, 4, 2, i, 0] = 1.0, -1.0
    return M.reshape(9 * N, 20 * N)


@dataclass(frozen=True)
class AnalysisSetup:
    """What a covariance analysis of the filter along its estimate ``hist`` needs (shared by
    :func:`actual_covariance` and ``ukf_gp.rigid_floor_correction``): the first epoch with an
    estimate ``k0``, the estimates ``x``, the error indices of the blocks (``dyn``: rate,
    attitude, inertia, the ones the dynamics move), the filter's Q per step split into the
    rate/attitude part (``q_moving``) and the rigid floor (``q_rigid``), the transition
    Jacobians ``Fd`` over ``dyn`` for the steps ``ks`` and the measurement Jacobians ``Hk`` at
    the epochs with a real measurement (``Hof``: epoch -> row of ``Hk``)."""

    k0: int
    x: Array
    er: NDArray[Any]
    ea: NDArray[Any]
    dyn: NDArray[Any]
    q_moving: Array
    q_rigid: Array
    ks: NDArray[Any]
    Fd: Array
    Hk: Array
    Hof: dict[int, int]


def analysis_setup(
    hist: EstimateHistory, t: Array, z: Array, tun: Any, geom: Any
) -> AnalysisSetup | None:
    """The pieces of :class:`AnalysisSetup` for ``hist`` (None: no estimate with a finite
    covariance)."""
    lay = hist.layout
    n, d = len(t), lay.dim
    if hist.P is None:
        return None
    okP = np.array([p is not None and np.all(np.isfinite(p)) for p in hist.P])
    x = np.array(hist.x, dtype=float)
    good = np.flatnonzero(okP & np.all(np.isfinite(x), axis=1))
    if len(good) == 0:
        return None
    k0 = int(good[0])
    E = np.arange(d)
    er, ea = E[lay.err("rate")], E[lay.err("attitude")]
    ek, ef = E[lay.err("inertia")], E[lay.err("features")]
    dyn = np.r_[er, ea, ek]
    q_moving, q_rigid = moving_q(lay, tun), np.zeros(d)
    q_rigid[ek], q_rigid[ef] = float(tun.q_k_var or 0.0), float(tun.q_feature_var or 0.0)
    ks = np.arange(k0 + 1, n)
    Fd = step_jacobians(lay, x, t, dyn, ks)
    real = np.flatnonzero(np.any(np.isfinite(z[..., 0]), axis=1))
    real = real[(real >= k0) & np.all(np.isfinite(x[real]), axis=1)]
    Hk = measurement_jacobians(lay, geom, x[real], real)
    Hof = dict(zip(real.tolist(), range(len(real)), strict=True))
    return AnalysisSetup(k0, x, er, ea, dyn, q_moving, q_rigid, ks, Fd, Hk, Hof)


def actual_covariance(
    hist: EstimateHistory,
    t: Array,
    z: Array,
    R: Array,
    tun: Any,
    geom: Any,
    q_r: float,
    flow_walk_var: float = 0.0,
    world: bool = False,
    innovations: dict[int, tuple[NDArray[np.bool_], Array, Array]] | None = None,
) -> tuple[Array, Array]:
    """``P_f`` and ``P_a`` (n, d, d) after each epoch (NaN before the filter's start): the
    filter's covariance and the actual error's, linearised along ``hist`` (module docstring),
    from the filter's covariance at its start. ``z``, ``R`` (n, N, 9) the measurements and
    the variances the filter used; ``tun`` its resolved tuning (Q); ``q_r`` the scenario's
    ``process_noise.rotational_rad2_s4``; ``flow_walk_var`` the per-component variance the
    filter's ``sigma_o`` gave the rate walk (``flow_process_noise_rad_s`` squared: the
    analysis counts that error as the common one it is instead). ``world``: the filter updates
    in the world chart (``update_chart``), and so does the analysis: the error in the world
    chart at each estimate (its Jacobian ``J`` on the body chart's, :func:`world_jacobians`),
    the step ``J(f(x_k-1)) F J(x_k-1)^-1``, the update ``H J(x_k)^-1`` (no column on the
    attitude: the projections do not see it there); ``P_f``, ``P_a`` are returned in the body
    chart at the estimate. ``innovations``, if given, receives per updated epoch the
    components used (flat, ``z[k]``'s order), the innovations' covariance the filter states,
    ``H P H^T + R``, and their actual one, ``nu = H e + M n + A dw + white`` over the
    analysis' state before the update (the flows reuse the projections the prediction has
    already been updated with)."""
    lay = hist.layout
    n, d = len(t), lay.dim
    N = z.shape[1]
    m = 4 * N
    Pf_out = np.full((n, d, d), np.nan)
    Pa_out = np.full((n, d, d), np.nan)
    su = analysis_setup(hist, t, z, tun, geom) if n >= 2 else None
    if su is None:
        return Pf_out, Pa_out
    k0, x, ks, Fd, Hk, Hof, dyn = su.k0, su.x, su.ks, su.Fd, su.Hk, su.Hof, su.dyn
    er, ea = su.er, su.ea
    Qf = np.diag(su.q_moving + su.q_rigid)
    Qcoast = np.diag(su.q_moving)  # no Q on the rigid parameters where nothing is measured
    dt = float(np.median(np.diff(t)))
    Rp = R[..., 0:4]
    s2 = float(np.nanmax(Rp)) if np.isfinite(Rp).any() else 0.0  # the sensor's sigma_p^2
    M = _stencil_map(N, dt)
    stencil_var = s2 * float(np.sum(_STENCIL**2)) / dt**2
    is_flow = np.arange(9 * N) % 9 >= 5
    # the analysis' state after the update at k: the error (d), the projection noise at
    # t_k-1 .. t_k+2 (4m) and the process noise of steps k .. k+2 (3 x 6: per rate axis the
    # two basis coefficients)
    D = d + 4 * m + 18
    C = np.zeros((D, D))
    Pf = np.array(hist.P[k0], dtype=float)
    Pf_out[k0] = Pa_out[k0] = Pf
    if world:
        Jx = world_jacobians(lay, x)  # at the estimates
        Jp = world_jacobians(lay, predicted_states(lay, x, t, ks))  # at the predictions
        Jx_inv = np.linalg.inv(Jx)
        Pf = Jx[k0] @ Pf @ Jx[k0].T
    C[:d, :d] = Pf
    C[d : d + 4 * m, d : d + 4 * m] = s2 * np.eye(4 * m)
    C[d + 4 * m :, d + 4 * m :] = np.eye(18)
    Db = D + m + 6  # with the projection noise at t_k+2 and the process noise of step k+2
    ie = np.arange(d)
    inw = d + np.arange(5 * m)  # noise t_k-2 .. t_k+2 in the extended state
    ipw = d + 5 * m + np.arange(24)  # process noise of steps k-1 .. k+2
    keep = np.r_[ie, inw[m:], ipw[6:]]
    F = np.eye(d)
    kk = x[:, lay.nom("inertia")]
    for j, k in enumerate(ks.tolist()):
        F[np.ix_(dyn, dyn)] = Fd[j]
        i = Hof.get(k)
        Qk = Qf if i is not None else Qcoast
        Fk = F
        if world:
            Fk = Jp[j] @ F @ Jx_inv[k - 1]
            Qk = Jp[j] @ Qk @ Jp[j].T
        Pf = Fk @ Pf @ Fk.T + Qk
        # the truth's process noise over step k, per principal axis (I_max / I_i)^2
        mk = np.exp(np.array([kk[k - 1, 0], 0.0, kk[k - 1, 1]]))
        sq = np.sqrt(q_r * (mk.max() / mk) ** 2) if np.all(np.isfinite(mk)) else np.zeros(3)
        G = np.zeros((d, 6))  # step k's coefficients (axis a: columns 2a, 2a + 1)
        att_from_rate = Fd[j][3:6, 0:3] / dt  # ~ the attitude's response per unit rate
        for a in range(3):
            G[er[a], 2 * a] = sq[a] * np.sqrt(dt)
            G[ea, 2 * a : 2 * a + 2] = np.outer(att_from_rate[:, a], sq[a] * dt**1.5 * _ATT_COEF)
        # [e, noise k-2..k+1, process k-1..k+1] and the fresh noise at t_k+2 and of step
        # k+2, in the order [e, noise k-2..k+2, process k-1..k+2]; then the prediction
        Cb = np.zeros((Db, Db))
        old = np.r_[ie, inw[: 4 * m], ipw[:18]]
        Cb[np.ix_(old, old)] = C
        Cb[np.ix_(inw[4 * m :], inw[4 * m :])] = s2 * np.eye(m)
        Cb[np.ix_(ipw[18:], ipw[18:])] = np.eye(6)
        L = np.eye(Db)
        L[:d, :d] = Fk
        L[:d, ipw[6:12]] = Jp[j] @ G if world else G  # step k: the second of the window
        Cb = L @ Cb @ L.T
        if i is not None:
            Hb = Hk[i]
            Pf_prior = Pf
            rows, H, Rk, K, A, Pf = filter_update(Pf, Hb @ Jx_inv[k] if world else Hb, z[k], R[k])
            flow = is_flow[rows]
            white = np.where(flow, np.maximum(Rk[rows] - stencil_var - flow_walk_var, 0.0), 0.0)
            # the stencil's rate error: per axis a, its coefficients on steps k-1 .. k+2
            W = np.zeros((3, 24))
            for s_ in range(4):
                for a in range(3):
                    W[a, 6 * s_ + 2 * a : 6 * s_ + 2 * a + 2] = (
                        sq[a] * dt**0.5 / 12.0 * _WALK_COEF[s_]
                    )
            # the flow's response to the body rate's walk (the stencil sees the truth's)
            Hr = np.where(flow[:, None], Hb.reshape(-1, d)[rows][:, er], 0.0)
            if innovations is not None:  # nu = H e + M n + Hr W w + white
                Lnu = np.zeros((len(H), Db))
                Lnu[:, :d], Lnu[:, inw], Lnu[:, ipw] = H, M[rows], Hr @ W
                S_a = Lnu @ Cb @ Lnu.T + np.diag(white)
                innovations[k] = (rows, H @ Pf_prior @ H.T + np.diag(Rk[rows]), S_a)
            T = np.eye(Db)
            T[:d, :d] = A
            T[:d, inw] = -K @ M[rows]
            T[:d, ipw] = -K @ Hr @ W
            Cb = T @ Cb @ T.T
            Cb[:d, :d] += (K * white) @ K.T
        C = Cb[np.ix_(keep, keep)]
        if world:
            Pf_out[k] = Jx_inv[k] @ Pf @ Jx_inv[k].T
            Pa_out[k] = Jx_inv[k] @ C[:d, :d] @ Jx_inv[k].T
        else:
            Pf_out[k], Pa_out[k] = Pf, C[:d, :d]
    return Pf_out, Pa_out


def _upper_cholesky(P: Array) -> Array:
    """Upper-triangular ``U`` with ``U U^T = P`` (``P`` SPD)."""
    J = np.arange(len(P))[::-1]
    L = np.linalg.cholesky(0.5 * (P + P.T)[np.ix_(J, J)])
    return np.asarray(L[np.ix_(J, J)], dtype=np.float64)


def actual_map(Pf: Array, Pa: Array) -> Array:
    """The upper-triangular ``T = U_a U_f^-1`` (``U U^T = P``, :func:`_upper_cholesky`) with
    ``T P_f T^T = P_a``: applied as ``T P T^T`` to a covariance ``P`` close to ``P_f`` it gives
    one close to ``P_a``, positive definite; its rows of the last components (the rigid
    parameters, last in the error state) do not mix in the earlier ones, so a covariance whose
    rigid block stays fixed (a coast) keeps a fixed rigid block."""
    Uf, Ua = _upper_cholesky(Pf), _upper_cholesky(Pa)
    return np.asarray(np.linalg.solve(Uf.T, Ua.T).T, dtype=np.float64)


def moving_q(lay: Any, tun: Any) -> Array:
    """The filter's Q per step on the rate and attitude (the moving states), zero elsewhere
    (d,): as :func:`analysis_setup`'s ``q_moving``."""
    E = np.arange(lay.dim)
    q = np.zeros(lay.dim)
    q[E[lay.err("rate")]] = rate_q(tun.q_omega_var)
    q[E[lay.err("attitude")]] = 4.0 * float(tun.q_quat_var or 0.0)  # a quarter per component
    return q


def coast_ensemble(
    hist: EstimateHistory,
    t: Array,
    k0: int,
    ks: NDArray[Any],
    P0: Array,
    q_moving: Array,
    samples: int = 1000,
    seed: int = 0,
) -> Array:
    """The covariance of the error about the estimate through a coast: ``(len(ks), d, d)`` at
    the epochs ``ks`` (consecutive, after ``k0``, none with a measurement) from the error
    covariance ``P0`` at ``k0``.

    An ensemble of the moving states (rate, attitude, inertia ratios: the only ones the
    dynamics read) drawn from ``P0`` (antithetic, whitened so that its second moment is ``P0``
    exactly), each member propagated through the torque-free dynamics (Kabir 2025 eq. 8-10,
    the filter's propagation) with the scenario's random walk (``q_moving``, per step) on the
    rate and attitude, over the whole coast without re-approximating it by a Gaussian at each
    step; the second moment of its errors about the estimate (``hist.x``, the propagated centre
    point) is the covariance the NEES needs, whatever the shape (a rate error shifts the
    polhode's phase: a banana). The features, which no dynamics move, keep ``P0``; their
    correlation with the moving states follows through the ensemble's correlation with its
    start (exact for a Gaussian start: the features are a linear regression on the moving
    states plus an independent rest). tumblenav, issue 18: the cubature rule's points at
    +- sqrt(d) sigma, d = 8 + 3N, overstate a quadratic effect d/3 times (kabir_inertia's
    coast conservative, NEES/dof 0.74) and, started from the filter's covariance, kept its
    correlations between the moving and the rigid states (kabir_gp_rate005, a quiet truth:
    1.34)."""
    lay = hist.layout
    d = lay.dim
    E = np.arange(d)
    m = np.r_[E[lay.err("rate")], E[lay.err("attitude")], E[lay.err("inertia")]]
    o = np.setdiff1d(E, m)
    sw, sq, sk = lay.nom("rate"), lay.nom("attitude"), lay.nom("inertia")
    P0 = 0.5 * (np.asarray(P0, dtype=float) + np.asarray(P0, dtype=float).T)
    S0 = P0[np.ix_(m, m)]
    rng = np.random.default_rng(seed)
    half = max(samples // 2, len(m) + 1)
    xi = rng.standard_normal((half, len(m)))
    xi = np.r_[xi, -xi]
    W = np.linalg.cholesky(xi.T @ xi / len(xi))
    xi = np.linalg.solve(W, xi.T).T  # second moment exactly I
    try:
        F0 = np.linalg.cholesky(S0 + 1e-300 * np.eye(len(m)))
    except np.linalg.LinAlgError:  # semi-definite: a symmetric root of its non-negative part
        lam, V = np.linalg.eigh(S0)
        F0 = V * np.sqrt(np.clip(lam, 0.0, None))
    e0 = xi @ F0.T  # (M, 8), second moment S0
    x0 = np.asarray(hist.x[k0], dtype=float)
    w = x0[sw] + e0[:, 0:3]
    q = rot.boxplus_fast(np.broadcast_to(x0[sq], (len(e0), 4)), e0[:, 3:6])
    kk = x0[sk] + e0[:, 6:8]
    sd = np.sqrt(q_moving[m[:6]])
    A = np.linalg.pinv(S0, hermitian=True) @ P0[np.ix_(m, o)]  # features = A^T e0 + the rest
    out = np.empty((len(ks), d, d))
    k_prev = k0
    for j, k in enumerate(np.asarray(ks).tolist()):
        w, q = ukf_model.propagate_rotation_compiled(w, q, kk, float(t[k] - t[k_prev]))
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        if np.any(sd > 0):
            nz = rng.standard_normal((len(e0), 6)) * sd
            w = w + nz[:, 0:3]
            q = rot.boxplus_fast(q, nz[:, 3:6])
        xk = np.asarray(hist.x[k], dtype=float)
        D = np.concatenate(
            [w - xk[sw], rot.boxminus_fast(q, np.broadcast_to(xk[sq], q.shape)), kk - xk[sk]],
            axis=-1,
        )
        Pk = P0.copy()
        Pk[np.ix_(m, m)] = D.T @ D / len(D)
        Pk[np.ix_(m, o)] = (D.T @ e0 / len(D)) @ A
        Pk[np.ix_(o, m)] = Pk[np.ix_(m, o)].T
        out[j] = Pk
        k_prev = k
    return out


def write_coast(
    hist: EstimateHistory, t: Array, k0: int, ks: NDArray[Any], P0: Array, q_moving: Array
) -> None:
    """``hist.P`` at the coast epochs ``ks`` from :func:`coast_ensemble` started with ``P0``
    at ``k0``. In place."""
    assert hist.P is not None
    for P, k in zip(coast_ensemble(hist, t, k0, ks, P0, q_moving), ks.tolist(), strict=True):
        hist.P[k] = P


def report_actual(
    hist: EstimateHistory,
    Pf: Array,
    Pa: Array,
    measured: NDArray[np.bool_],
    t: Array,
    q_moving: Array,
) -> None:
    """``hist.P <- T P T^T`` with ``T`` (:func:`actual_map`) mapping ``P_f`` onto ``P_a`` at
    each ``measured`` epoch. Through the epochs without a measurement after one (a coast) the
    covariance is :func:`coast_ensemble`'s from the one reported at its last measured epoch:
    the coast of the actual error, not the filter's. Mapping the filter's coast covariance
    instead (the map was made for the updates' small spread) made NEES/dof 100-1700 in the
    in-loss windows; mapping only its rigid block kept the filter's correlations between the
    rigid and the moving states (kabir_gp_rate005, quiet truth, seeds 0-9: NEES/dof 1.39-2.07
    over the coast against 1.08-1.13 now). In place."""
    if hist.P is None:
        return
    ok = np.all(np.isfinite(Pf), axis=(1, 2)) & np.all(np.isfinite(Pa), axis=(1, 2))
    T = None
    n = len(hist.t)
    k = 0
    while k < n:
        P = hist.P[k]
        if P is None or not np.all(np.isfinite(P)):
            k += 1
            continue
        if ok[k] and measured[k]:
            try:
                T = actual_map(Pf[k], Pa[k])
            except np.linalg.LinAlgError:  # not positive definite: keep the last map
                pass
        if T is not None:
            hist.P[k] = T @ np.asarray(P, dtype=float) @ T.T
        j = k + 1  # a coast after k, from the covariance reported at k
        while j < n and not measured[j] and hist.P[j] is not None:
            j += 1
        if j > k + 1 and T is not None:
            write_coast(hist, t, k, np.arange(k + 1, j), np.asarray(hist.P[k]), q_moving)
        k = j
