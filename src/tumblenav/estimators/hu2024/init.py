"""Hu 2024 filter start: the mass centre and features from the rotation seen before the start,
the refined start pose, the initial state and covariance (beyond the paper, see each function)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.estimators.base import (
    StateLayout,
)
from tumblenav.estimators.hu2024.frame import frame_jacobian
from tumblenav.estimators.hu2024.tuning import HuTuning
from tumblenav.frontends import stereo_points
from tumblenav.frontends.inertia import inertia_ratios

Array = NDArray[np.float64]


def _rotation_window(
    fe: stereo_points.PointsFrontEnd, b: int, k: int, n_orbit: float, window_s: float
) -> tuple[NDArray[np.int64], Array, Array] | None:
    """The start batches' data window: the epochs ``j`` of the first ``window_s`` of G
    attitudes up to epoch k (causal), R_LG there (m,3,3) and the Hill (CW) position rows
    ``Phi`` (m,3,6) of the mass centre's ``[r_0, v_0]``; None with fewer than 10 epochs."""
    from tumblenav.dynamics.relative_orbit import cw_stm

    t = fe.t
    have = np.flatnonzero(np.all(np.isfinite(fe.R_GI[b, : k + 1]), axis=(-1, -2)))
    if len(have) < 10:
        return None
    j = have[t[have] <= t[have[0]] + window_s]
    R_LG = _R_LI_at(fe, b, j) @ np.swapaxes(fe.R_GI[b, j], -1, -2)
    return j, R_LG, cw_stm(n_orbit, t[j] - t[j[0]])[:, :3, :]


def force_deviation_cov(t: Array, n_orbit: float, q_t: float) -> Array:
    """Covariance (m,3,m,3) of ``r(t_j) - Phi_CW(t_j - t_0) [r_0; v_0]`` at the times ``t``
    (m,) under a white random acceleration of spectral density ``q_t`` (m^2/s^3 per axis,
    the filter's sigma_t^2, Hu 2024 eq. 4-5): the deviation ``d`` from the Hill motion of
    the window's first state, ``d(t_0) = 0``, ``Cov(d_j, d_j') = [Phi(t_j - t_j') P_j']_rr``
    for ``t_j >= t_j'`` with ``P`` its covariance (``cw_discrete`` steps)."""
    from tumblenav.dynamics.relative_orbit import cw_discrete, cw_stm

    m = len(t)
    P = np.zeros((m, 6, 6))
    for j in range(1, m):
        Phi, Qd = cw_discrete(n_orbit, q_t, float(t[j] - t[j - 1]))
        P[j] = Phi @ P[j - 1] @ Phi.T + Qd
    lag = np.maximum(t[:, None] - t[None, :], 0.0)
    Phi_lag = cw_stm(n_orbit, lag.ravel()).reshape(m, m, 6, 6)
    C = Phi_lag[..., :3, :] @ P[None, :, :, :3]  # (m,m,3,3), valid for t_j >= t_j'
    low = (t[:, None] >= t[None, :])[..., None, None]
    C = np.where(low, C, np.swapaxes(C, 0, 1).swapaxes(-1, -2))
    return np.ascontiguousarray(np.transpose(C, (0, 2, 1, 3)))


def mass_centre_from_rotation(
    fe: stereo_points.PointsFrontEnd,
    b: int,
    k: int,
    n_orbit: float,
    window_s: float = 30.0,
    q_t: float = 0.0,
) -> tuple[Array, Array] | None:
    """Batch least squares for the mass centre before the filter starts (beyond Hu 2024).

    Every feature seen at epoch j obeys ``p_L,i(j) = r(j) + R_LG(j) (g_i - c_G)``, with the G
    template ``g_i``, the measured G attitude ``R_LG = R_LI R_GI^T``, the constant mass centre
    ``c_G`` in G and the mass-centre position ``r(j) = Phi_CW(t_j - t_0) [r_0; v_0]`` (Hill,
    Hu 2024 eq. 4-5, no disturbance over the window). That is linear in ``[r_0, v_0, c_G]``;
    the rotation of the target separates ``c_G`` from the translation.

    The window is the first ``window_s`` of G attitudes (the closest, most precise data),
    ending at epoch k at the latest (causal). Each point is weighted by the inverse of its
    triangulation covariance plus what the G attitude error ``cov_G`` does to it
    (``R_LG [(g_i - c) x] cov_G [(g_i - c) x]^T R_LG^T``, at the centroid, then at the first
    solution); the covariance is scaled by the reduced chi-square when that exceeds one.
    With the random force the filter assumes (``q_t``, its sigma_t^2), the Hill motion is
    not exact over the window: the covariance gains what the force does to the estimate
    (:func:`force_deviation_cov`, as ``stereo_points.joint_features``' ``cov_dev``).

    Returns ``(c_G, cov_c_G)``, or None when the window holds too little rotation to tell
    ``c_G`` (its 1-sigma above 0.5 m).
    """
    window = _rotation_window(fe, b, k, n_orbit, window_s)
    if window is None:
        return None
    j, R_LG, Phi = window
    use = fe.usable[b, j] & fe.known_at[b, k][None, :]
    if use.sum() < 12:
        return None
    g = np.nan_to_num(fe.template_at(k)[b])  # (N,3), as known at k
    jj, ii = np.nonzero(use)
    d = fe.p_L[b, j[jj], ii] - (R_LG[jj] @ g[ii][..., None])[..., 0]  # (M,3)
    A = np.concatenate([Phi[jj], -R_LG[jj]], axis=2)  # (M,3,9)
    c = np.mean(g[fe.known_at[b, k]], axis=0)
    for _ in range(2):
        lever = R_LG[jj] @ rot.skew(g[ii] - c)  # d error per G attitude error (in G)
        C = fe.cov_L[b, j[jj], ii] + lever @ fe.cov_G[b, j[jj]] @ np.swapaxes(lever, -1, -2)
        try:
            W = np.linalg.inv(C)  # (M,3,3)
            AtW = np.swapaxes(A, -1, -2) @ W
            N = np.sum(AtW @ A, axis=0)
            rhs = np.sum(AtW @ d[..., None], axis=0)[:, 0]
            Ninv = np.linalg.inv(N)
        except np.linalg.LinAlgError:  # degenerate data: keep the centroid guess
            return None
        if not (np.all(np.isfinite(Ninv)) and np.all(np.isfinite(rhs))):
            return None
        x = Ninv @ rhs
        c = x[6:]
    res = d - (A @ x[:, None])[..., 0]
    chi2 = float(np.einsum("mi,mij,mj->", res, W, res))
    expect = float(max(3 * len(d) - 9, 1))
    cov_x = Ninv
    if q_t > 0:  # the force's deviation from the Hill motion, common to an epoch's points
        Q = force_deviation_cov(fe.t[j], n_orbit, q_t)
        S = np.zeros((len(j), 9, 3))
        np.add.at(S, jj, AtW)
        Wsum = np.zeros((len(j), 3, 3))
        np.add.at(Wsum, jj, W)
        S2 = np.transpose(S, (1, 0, 2)).reshape(9, -1)
        SQS = S2 @ Q.reshape(S2.shape[1], -1) @ S2.T
        cov_x = Ninv + Ninv @ SQS @ Ninv
        Qd = np.einsum("jajb->jab", Q)
        expect += float(np.einsum("jab,jba->", Wsum, Qd) - np.trace(Ninv @ SQS))
    cov_c = cov_x[6:, 6:] * max(1.0, chi2 / max(expect, 1.0))
    if not np.all(np.isfinite(cov_c)) or np.sqrt(np.max(np.linalg.eigvalsh(cov_c))) > 0.5:
        return None
    return c, cov_c


# chi-square (3 dof, 99.9 %) of the joint fit's mass centre against mass_centre_prior
MASS_CENTRE_GATE = 16.27


def mass_centre_prior(g: Array, kn: NDArray[np.bool_], sigma_m: float) -> Array:
    """(3,3) covariance of the mass centre about the catalogued features' centroid (in the
    template's frame): their own spread about that centroid, the body's extent as far as
    the features show it (the mass centre lies within the body, not near the features'
    centroid: 8 features in +-2.5 m put it 1.4 m off on consistency/hu_occ30), plus
    ``sigma_m``^2 (``p0_mass_centre_m``) per axis. Before issue 18's twenty-second
    session it was ``sigma_m``^2 alone."""
    pts = g[kn]
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    spread = np.cov(pts.T, bias=True) if len(pts) >= 2 else np.zeros((3, 3))
    return spread + sigma_m**2 * np.eye(3)


def features_from_rotation(
    fe: stereo_points.PointsFrontEnd,
    b: int,
    k: int,
    n_orbit: float,
    window_s: float = 30.0,
    q_t: float = 0.0,
    prior_cov: Array | None = None,
) -> tuple[Array, Array, NDArray[np.bool_]] | None:
    """Joint batch least squares for the features about the mass centre (beyond Hu 2024).

    The model of :func:`mass_centre_from_rotation` with the features' coordinates about the
    mass centre, ``f_i = g_i - c_G`` (in G), as unknowns instead of the template ``g_i`` of
    one sighting: ``p_L,i(j) = Phi_CW(t_j - t_0) [r_0; v_0] + R_LG(j) f_i``, linear in
    ``[r_0, v_0, f_1 .. f_N]``. With the template fixed, its errors (those of one stereo
    sighting: 8 mm deep at 17 m, 2e-5 rad) could only be absorbed by ``c_G`` and the fit put
    the mass centre 6 mm off (median) with a 1-sigma below 1 mm (hu2024), 97 mm off in a
    slower tumble (benchmarks/hu2024_mass_centre.py); here every feature is fitted to all its views in the window, so the template's
    errors do not enter, and the features come out refined over the views (their depth error
    averaged over the tumble) with an honest joint covariance.

    The window, the weights and the random force ``q_t`` are those of
    :func:`mass_centre_from_rotation` (the lever arm of the G attitude error is ``f_i``). Returns ``(f_G, cov_f, fitted)``: ``f_G`` (N,3) and
    ``cov_f`` (3N,3N) in G, for the features seen in the window (``fitted``); or None when
    the mass centre is not determined (the 1-sigma of the features' common shift above
    0.5 m: too little rotation in the window) or too few points.

    With ``prior_cov`` (3,3, in G; :func:`mass_centre_prior`, the body's extent about the
    catalogued features' centroid) the fit is used with its own covariance however weakly
    the rotation determines the mass centre, unless it puts the mass centre outside the
    body (beyond ``MASS_CENTRE_GATE`` of the prior): the rotation barely shows it along
    the spin axis (generalisation/g_slowrecede under the paper's q_t 2e-6: 1-sigma 0.55 m
    at 54 s, 0.16 m at 200 s), and the 0.5 m rejection sent such runs to the centroid,
    which is not the mass centre (1.4 m off on consistency/hu_occ30 with 8 features), and
    the filter kept its mass centre 0.3-1.4 m off at a 1-sigma of 1-2 cm (issue 18,
    twenty-second session). Fused with that prior instead, the fit's estimate moves
    towards the centroid, and the filter was over-confident again (position NEES/dof
    10-190 on four scenarios at the paper's Q against 0.4-8 unfused): the fit's
    covariance, under the paper's random force, is the conservative one.
    """
    N = fe.usable.shape[2]
    window = _rotation_window(fe, b, k, n_orbit, window_s)
    if window is None:
        return None
    j, R_LG, Phi = window
    g = fe.template_at(k)[b]  # as known at k (the initial lever arms)
    kn = fe.known_at[b, k]
    out = stereo_points.joint_features(
        Phi,
        R_LG,
        fe.p_L[b, j],
        fe.cov_L[b, j],
        fe.cov_G[b, j],
        fe.usable[b, j] & kn[None, :],
        g - np.nanmean(g[kn], axis=0),
        cov_dev=force_deviation_cov(fe.t[j], n_orbit, q_t) if q_t > 0 else None,
        free_attitudes=True,
    )
    if out is None:
        return None
    _, f, cov, idx = out
    # the features' common shift (a mass centre error) must be determined
    nf = len(idx)
    S = np.kron(np.ones((1, nf)) / nf, np.eye(3))
    if prior_cov is not None:
        # the mass centre the fit puts about the catalogued features' centroid (the
        # features' mean about the mass centre is the template's about the centroid less
        # that offset) must lie within the body: within the prior's 99.9 % ellipsoid
        off = np.mean(g[idx], axis=0) - np.nanmean(g[kn], axis=0) - S @ f.ravel()
        if off @ np.linalg.solve(prior_cov, off) > MASS_CENTRE_GATE:
            return None
    elif np.sqrt(np.max(np.linalg.eigvalsh(S @ cov @ S.T))) > 0.5:
        return None
    f_G = np.full((N, 3), np.nan)
    f_G[idx] = f
    cov_f = np.zeros((3 * N, 3 * N))
    sel = (3 * idx[:, None] + np.arange(3)).ravel()
    cov_f[np.ix_(sel, sel)] = cov
    fitted = np.zeros(N, dtype=bool)
    fitted[idx] = True
    return f_G, cov_f, fitted


@dataclass
class _Init:
    k0: NDArray[np.int64]  # (B,) first filter epoch (-1: never)
    x0: Array  # (B, nom)
    P0: Array  # (B, d, d)


def refine_start_pose(
    p: Array, cov: Array, f: Array, q: Array, r: Array, R_LI: Array, iters: int = 20
) -> tuple[Array, Array, Array] | None:
    """Gauss-Newton fit of the attitude ``q`` (q_TI) and position ``r`` (in L) to one epoch's
    feature points ``p`` (M, 3) in L with covariances ``cov`` (M, 3, 3), given the features
    ``f`` (M, 3) in T: minimises ``sum_i |p_i - r - R_LT(q) f_i|^2`` in the metric of
    ``cov_i`` (the measurement model of Hu 2024 eq. 32-35), with ``q <- exp(dtheta) q`` and
    the Jacobian ``[R_LT [f_i x], I]`` (the filter's). Returns the refined ``q``, ``r`` and
    the 6x6 covariance of ``(dtheta, dr)``, or None if the fit is not determined (fewer than
    three points, singular) or does not lower the cost.

    Why (beyond the paper): the filter used to start from the DPACF attitude of one epoch,
    whose G attitude comes from an isotropically weighted alignment (Kabsch) of the same
    points; at 150-190 m with a 1 m baseline the depth error (0.5 m) dwarfs the lateral one
    (3 mm) and that attitude is off by tens of degrees, while the first update, linearised
    there, claimed a few degrees. With the full covariances the lateral precision fixes the
    attitude to a fraction of a degree, and iterating removes the linearisation error."""
    W = np.linalg.inv(cov)
    M = len(p)
    if M < 3:
        return None

    def cost_and_normal(q_, r_):
        R_LT = R_LI @ rot.quat_to_matrix(q_).T
        y = p - r_ - f @ R_LT.T
        H = np.zeros((M, 3, 6))
        H[:, :, :3] = R_LT @ rot.skew(f)
        H[:, :, 3:] = np.eye(3)
        HtW = np.swapaxes(H, -1, -2) @ W
        A = np.sum(HtW @ H, axis=0)
        g = np.sum(HtW @ y[..., None], axis=0)[:, 0]
        c = float(np.sum(y[:, None, :] @ W @ y[..., None]))
        return c, A, g

    c0, A, g = cost_and_normal(q, r)
    qk, rk, ck = q, r, c0
    for _ in range(iters):
        try:
            d = np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(d)):
            return None
        qn = rot.quat_multiply(rot.exp_quat(d[:3]), qk)
        rn = rk + d[3:]
        cn, An, gn = cost_and_normal(qn, rn)
        if not cn <= ck * (1 + 1e-12):
            break
        qk, rk, ck, A, g = qn, rn, cn, An, gn
        if np.linalg.norm(d[:3]) < 1e-10:
            break
    if not (ck <= c0 and np.all(np.isfinite(A))) or np.linalg.cond(A) > 1e12:
        return None
    return qk, rk, np.linalg.inv(A)


# variance per axis (m^2) of a feature taken from the template (one stereo sighting, or
# one refinement) rather than fitted at the start: the features' own 1 cm
TEMPLATE_VAR_M2 = 1e-4


def template_features_cov(
    cov_fit: Array, fit: NDArray[np.bool_], kn: NDArray[np.bool_], unseen_sigma_m: float
) -> Array:
    """(3N, 3N) covariance (in G) of the start's features about the mass centre: the joint
    fit's (:func:`features_from_rotation`, ``cov_fit`` (3N, 3N), nonzero on the ``fit``
    features); a feature catalogued (``kn``) but not fitted (seen at fewer than three of the
    window's epochs) is its template less the mass centre the fit puts in the template,
    ``f_i = g_i - c``, ``c = mean_fit(g_j - f_j)``, so its error ``dg_i - mean_fit(dg_j) +
    S df_fit`` (``S``: the mean over the fitted features) carries the fit's common shift:
    ``S C S^T`` on every such feature and between them, ``S C`` with the fitted ones, plus
    the templates' own 1 cm (``TEMPLATE_VAR_M2``; its mean over the fitted ones common to
    all); features never seen take ``unseen_sigma_m``^2.

    Why (tumblenav, issue 18, twenty-fifth session): these features had the template's
    1 cm alone, independent of the fit. Under self-occlusion the features in view at the
    start may all be ones the window hardly saw (consistency/hu_conv14 run 10 at 148 s:
    three fitted, six in view, none of them fitted, the fit's common shift at a 1-sigma of
    0.28-0.71 m), and the start then placed the mass centre 0.48 m off at a 1-sigma of
    0.035 m (position NEES/dof 578; 1.04 now)."""
    N = len(kn)
    idx = np.flatnonzero(fit)
    tmpl = kn & ~fit
    A = np.zeros((3 * N, 3 * N))  # feature errors as a linear map of the fitted ones
    for i in idx:
        A[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = np.eye(3)
    if len(idx):
        S = np.kron(np.ones((1, len(idx))) / len(idx), np.eye(3))
        sel = (3 * idx[:, None] + np.arange(3)).ravel()
        for i in np.flatnonzero(tmpl):
            A[3 * i : 3 * i + 3, sel] = S
    common = TEMPLATE_VAR_M2 / max(len(idx), 1)  # the fitted templates' mean, in c
    var = np.where(tmpl, TEMPLATE_VAR_M2, np.where(kn, 0.0, unseen_sigma_m**2))
    own = common * np.outer(tmpl, tmpl) + np.diag(var)  # per feature pair, each axis alike
    return A @ cov_fit @ A.T + np.kron(own, np.eye(3))


def pose_feature_sensitivity(
    C6: Array, R_LT: Array, f: Array, cov: Array, use: NDArray[np.bool_]
) -> Array:
    """``G`` (6, 3N): how the refined start pose's error (:func:`refine_start_pose`, its
    covariance ``C6``) follows the errors of the features ``f`` (N,3) it was fitted with.
    At the fit, ``sum_i H_i^T W_i y_i = 0`` with ``y_i = H_i e_z + R_LT e_f,i + eps_i``
    (``e`` truth minus estimate, ``H_i = [R_LT [f_i x], I]``, ``W_i = cov_i^-1``), so
    ``e_z = -C6 sum_i H_i^T W_i (R_LT e_f,i + eps_i)``: ``G[:, i] = C6 H_i^T W_i R_LT``,
    ``Cov(e_z) = C6 + G P_f G^T`` and ``Cov(e_z, e_f) = -G P_f`` (beyond the paper).
    ``cov`` (M,3,3): the used points' covariances (``use`` (N,), M of them)."""
    N = len(f)
    G = np.zeros((6, 3 * N))
    W = np.linalg.inv(cov)
    for m, i in enumerate(np.flatnonzero(use)):
        H = np.concatenate([R_LT @ rot.skew(f[i]), np.eye(3)], axis=1)  # (3, 6)
        G[:, 3 * i : 3 * i + 3] = C6 @ H.T @ W[m] @ R_LT
    return G


def _initial_state(
    fe: stereo_points.PointsFrontEnd,
    tun: HuTuning,
    use_dpacf: bool,
    lay: StateLayout,
    n_orbit: float = 0.0,
    frame_in_P0: bool = True,
    refine: bool = False,
    not_before: NDArray[np.int64] | None = None,
    q_t: float = 0.0,
) -> _Init:
    """The start of each run: its epoch ``k0`` (the first where the gates hold; with
    ``not_before`` (B,), no earlier than that: a re-initialisation after a run lost track,
    from that epoch's measurements as at the start), the state and its covariance."""
    B, n, N = fe.usable.shape
    ready = np.all(np.isfinite(fe.q_TI), axis=-1) & np.all(np.isfinite(fe.omega_G), axis=-1)
    ready &= fe.usable.sum(axis=-1) >= 3  # fe: the filter's view (filter_view), gated frames
    if not_before is not None:
        ready &= np.arange(n)[None, :] >= np.asarray(not_before)[:, None]
    if tun.max_ratio_sigma is not None:  # both estimators, so that they start together
        var_p = np.nan_to_num(np.diagonal(fe.cov_ratios, axis1=-2, axis2=-1), nan=np.inf)
        ratios_ok = np.sqrt(var_p.max(axis=-1)) < tun.max_ratio_sigma
        # ... but not for longer than max_ratio_wait_s after the frame became good enough
        t_ready = np.where(ready.any(axis=1), fe.t[np.argmax(ready, axis=1)], np.inf)
        waited = fe.t[None, :] >= t_ready[:, None] + tun.max_ratio_wait_s
        ready &= ratios_ok | waited
    k0 = np.where(ready.any(axis=1), np.argmax(ready, axis=1), -1)
    x0 = np.zeros((B, lay.nominal_dim))
    P0 = np.zeros((B, lay.dim, lay.dim))
    for b in range(B):
        k = k0[b]
        if k < 0:
            continue
        R_GI = fe.R_GI[b, k]
        if use_dpacf:
            R_TG = fe.R_GT[b, k].T
            q = fe.q_TI[b, k]
            p = inertia_ratios(fe.moments[b, k])
            cov_att = fe.cov_TI[b, k] - fe.cov_frame[b, k]  # white part (G attitude)
            cov_frame = fe.cov_frame[b, k]
        else:  # Aghili & Parsa-style start: T := G, spherical inertia, large attitude sigma
            R_TG = np.eye(3)
            q = rot.matrix_to_quat(R_GI)
            p = np.zeros(3)
            cov_att = 1e-6 * np.eye(3)
            cov_frame = tun.p0_attitude_rad**2 * np.eye(3)
        R_LT = _R_LI_at(fe, b, k) @ rot.quat_to_matrix(q).T
        u = fe.usable[b, k]
        kn = fe.known_at[b, k]  # catalogued by the start (causal)
        g = fe.template_at(k)[b]  # as known at the start
        gbar = np.nanmean(g[kn], axis=0)  # mass centre guess: the feature centroid
        prior_G = mass_centre_prior(g, kn, tun.p0_mass_centre_m)
        Sc = R_TG @ prior_G @ R_TG.T  # its covariance (in T)
        joint = None  # (f_G, cov_f, fitted) of features_from_rotation
        if tun.mass_centre_init == "rotation":
            batch = mass_centre_from_rotation(fe, b, k, n_orbit, q_t=q_t)
            if batch is not None:
                gbar, cov_c = batch
                floor = tun.p0_mass_centre_floor_m**2 * np.eye(3)
                Sc = R_TG @ (cov_c + floor) @ R_TG.T
        elif tun.mass_centre_init == "joint":
            joint = features_from_rotation(fe, b, k, n_orbit, q_t=q_t, prior_cov=prior_G)
            if joint is not None:
                fit_kn = joint[2] & kn
                gbar = np.mean(g[fit_kn] - joint[0][fit_kn], axis=0)  # mass centre in G
        fG = np.nan_to_num(g - gbar)  # features about the mass centre, in G
        F = None  # with the joint fit: the features' covariance (3N, 3N, in T)
        if joint is not None:
            fG = np.where(fit_kn[:, None], joint[0], fG)
            RT = np.kron(np.eye(N), R_TG)
            F = RT @ template_features_cov(joint[1], fit_kn, kn, tun.p0_unseen_feature_m) @ RT.T
        f = np.where(kn[:, None], (R_TG @ fG.T).T, 0.0)
        # r such that the predicted features match the measured ones on average:
        # r = mean_i (p_L,i - R_LT f_i) over the visible, catalogued features (weighted)
        use = u & kn
        wts = np.where(use, 1.0 / np.trace(fe.cov_L[b, k], axis1=-2, axis2=-1), 0.0)
        resid = np.nan_to_num(fe.p_L[b, k]) - f @ R_LT.T
        r0 = np.sum(wts[:, None] * resid, 0) / wts.sum()
        C6 = None  # covariance of (attitude, position) from the refined start
        C6f = None  # ... and its cross-covariance with the features (6, 3N)
        if refine:
            # the points' covariances, plus the template's 1 cm where the features are not
            # the joint fit's (whose own covariance enters below)
            cov_fit = fe.cov_L[b, k, use] + (0.0 if F is not None else TEMPLATE_VAR_M2) * np.eye(3)
            fit = refine_start_pose(fe.p_L[b, k, use], cov_fit, f[use], q, r0, _R_LI_at(fe, b, k))
            if fit is not None:
                q, r0, C6 = fit
                R_LT = _R_LI_at(fe, b, k) @ rot.quat_to_matrix(q).T
                if F is not None:
                    G6 = pose_feature_sensitivity(C6, R_LT, f, cov_fit, use)
                    C6f = -G6 @ F
                    C6 = C6 + G6 @ F @ G6.T
        w = R_TG @ fe.omega_G[b, k]
        # velocity: with mass_centre_init 'rotation' or 'joint', of the mass centre, by
        # differencing at k and k - h the point ``p_L,i - R_LG f_G,i`` (f_G,i = g_i - gbar,
        # or the joint fit's feature) of the features seen at both
        # (the centroid's velocity adds omega x (centroid - mass centre)); else of the
        # centroid of the features seen at both
        h = min(tun.frontend.rate_half_window * 2, k)
        common = u & fe.usable[b, k - h] & kn if h > 0 else u
        G_ok = (
            tun.mass_centre_init in ("rotation", "joint")
            and h > 0
            and bool(np.all(np.isfinite(fe.R_GI[b, [k, k - h]])))
        )
        if G_ok and common.sum() >= 3:
            gc = fG[common]
            cen = [
                np.mean(
                    fe.p_L[b, j, common] - gc @ (_R_LI_at(fe, b, j) @ fe.R_GI[b, j].T).T, axis=0
                )
                for j in (k, k - h)
            ]
            v = (cen[0] - cen[1]) / (fe.t[k] - fe.t[k - h])
        elif h > 0 and (u & fe.usable[b, k - h]).sum() >= 3:
            both = u & fe.usable[b, k - h]
            v = (fe.p_L[b, k, both].mean(0) - fe.p_L[b, k - h, both].mean(0)) / (
                fe.t[k] - fe.t[k - h]
            )
        else:
            v = np.zeros(3)
        x0[b, lay.nom("attitude")] = q
        x0[b, lay.nom("rate")] = w
        x0[b, lay.nom("inertia")] = p
        x0[b, lay.nom("position")] = r0
        x0[b, lay.nom("velocity")] = v
        x0[b, lay.nom("features")] = f.ravel()
        # covariance: the unknown mass-centre offset c (in T) correlates r and every f_i:
        # r = r0 + R_LT c, f_i = f0_i - c.
        P = np.zeros((lay.dim, lay.dim))
        P[lay.err("attitude"), lay.err("attitude")] = cov_att if C6 is None else C6[:3, :3]
        var_w = tun.p0_rate_rad_s**2
        if refine:  # plus the variance of the front end's rate (0.1 rad/s at 190 m, 2e-5 rad)
            var_w += float(np.nan_to_num(fe.var_omega[b, k]))
        P[lay.err("rate"), lay.err("rate")] = var_w * np.eye(3)
        # the ratios: for ekf-dpacf the least-squares covariance of the front end's ratios
        # at the start (beyond the paper; a start 0.29 off with sigma 0.077 was seen) plus
        # p0_inertia^2; ekf-baseline starts from a sphere with sigma 0.5
        P[lay.err("inertia"), lay.err("inertia")] = (
            tun.p0_inertia**2 * np.eye(3) + np.nan_to_num(fe.cov_ratios[b, k])
            if use_dpacf
            else 0.5**2 * np.eye(3)
        )
        sr = lay.err("position")
        P[sr, sr] = R_LT @ Sc @ R_LT.T
        sf0 = lay.err("features").start
        sa, sfe = lay.err("attitude"), lay.err("features")
        if F is not None:
            # features: the joint fit's covariance (in T); without the refined pose,
            # r0 = sum_i w_i (p_L,i - R_LT f_i) / sum w, so its error is -R_LT W f_err with
            # W = [w_i I] / sum w
            P[sfe, sfe] = F
            if C6f is None:
                Wr = np.kron((wts / wts.sum())[None, :], np.eye(3))  # (3, 3N)
                P[sr, sr] = R_LT @ Wr @ F @ Wr.T @ R_LT.T
                P[sr, sfe] = -R_LT @ Wr @ F
                P[sfe, sr] = P[sr, sfe].T
        if C6f is not None:  # the refined pose's error, correlated with the features'
            assert C6 is not None  # C6f comes with C6
            P[sa, sa], P[sr, sr] = C6[:3, :3], C6[3:, 3:]
            P[sa, sfe], P[sr, sfe] = C6f[:3], C6f[3:]
            P[sfe, sa], P[sfe, sr] = C6f[:3].T, C6f[3:].T
            P[sa, sr], P[sr, sa] = C6[:3, 3:], C6[3:, :3]
        elif C6 is not None:
            P[sr, sr] += C6[3:, 3:]
            P[sa, sr] = C6[:3, 3:]
            P[sr, sa] = C6[3:, :3]
        P[lay.err("velocity"), lay.err("velocity")] = tun.p0_velocity_m_s**2 * np.eye(3)
        for i in range(N if joint is None else 0):
            si = slice(sf0 + 3 * i, sf0 + 3 * i + 3)
            if kn[i]:
                P[si, sr] = -Sc @ R_LT.T
                P[sr, si] = -R_LT @ Sc
                for j in range(N):
                    if kn[j]:
                        sj = slice(sf0 + 3 * j, sf0 + 3 * j + 3)
                        P[si, sj] = Sc
                P[si, si] = Sc + TEMPLATE_VAR_M2 * np.eye(3)
            else:
                P[si, si] = tun.p0_unseen_feature_m**2 * np.eye(3)
        # The principal frame itself is uncertain (DPACF error, or unknown for the baseline):
        # a rotation u of the frame moves the attitude by u and rotates the rate and every
        # feature (frame_jacobian; unseen features are at 0). With the 'consider' frame
        # model the filter works in the front end's frame and adds this when it reports.
        if frame_in_P0:
            Ju = frame_jacobian(x0[b][None], lay)[0]
            P += Ju @ cov_frame @ Ju.T
        P0[b] = positive_definite(0.5 * (P + P.T))
    return _Init(k0=k0, x0=x0, P0=P0)


# the smallest eigenvalue of the start covariance's correlation matrix (positive_definite)
START_CORR_FLOOR = 1e-10


def positive_definite(P: Array, floor: float = START_CORR_FLOOR) -> Array:
    """``P`` with the eigenvalues of its correlation matrix raised to ``floor`` at least
    (beyond Hu 2024; unchanged when they all are).

    Why (issue 18): the joint start holds the features' common shift (the mass centre) to
    centimetres and their shape to micrometres at 1e-6 rad (hu2024): correlation matrix
    condition ~1e11. Assembled from its parts (the fit's, the refined pose's and their
    cross terms) round-off left an eigenvalue at -2.6e-10; every precise update then
    shrank the other directions and not that one (a congruence keeps the sign), so it grew
    relative to them (-1e-6 after 40 s, the Joseph form alike) until the update broke
    (NIS < 0) and 3 of 500 runs kept the mass centre 0.1 m off at a 1-sigma of 1 mm
    (NEES/dof 4e3-1.1e4). A floor of 1e-10 adds at most 1e-5 of a state's 1-sigma in any
    direction; runs whose start was positive definite are unchanged."""
    s = np.sqrt(np.maximum(np.diag(P), 0.0))
    ok = s > 0
    if not ok.any():
        return P
    S = np.outer(s[ok], s[ok])
    C = P[np.ix_(ok, ok)] / S
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    if w.min() >= floor:
        return P
    out = P.copy()
    out[np.ix_(ok, ok)] = ((V * np.maximum(w, floor)) @ V.T) * S
    return 0.5 * (out + out.T)


def _R_LI_at(fe: stereo_points.PointsFrontEnd, b: int, k: int | NDArray[np.intp]) -> Array:
    assert fe.R_LI is not None  # set by filter.frontend
    return fe.R_LI[b, k]
