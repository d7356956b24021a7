"""Kabir 2025 UKF start: given (e.g. the recipe's truth-based guess), triangulated from the
first measurements with q = identity, or identified from the first measurements (tumblenav
default): the feature set's attitude history, its rate, the inertia and the principal frame
(Hu 2024 eq. 13-17's least squares), with the identification's own covariance.

Why (issue 18): the body frame of Kabir's state is the principal frame, which the projections
do not show: only the Euler dynamics fix it. A start at q = identity is then as far from the
principal frame as the target's attitude happens to be (75-124 deg on the consistency
scenarios), while a small P0 claimed sub-degree attitude: errors of 17-75 deg at 200 sigma.
The identified start knows the frame to ``init_frame_sigma_rad`` and says so in P0; the
triangulated start now says it knows nothing of it (``init_attitude_sigma_rad``, with the
features' and rate's covariance following the frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.estimators.kabir2025.model import KabirGeometry, layout
from tumblenav.estimators.kabir2025.tuning import KabirTuning
from tumblenav.frontends import projections as proj
from tumblenav.frontends.inertia import inertia_design

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


@dataclass
class KabirStart:
    """Where and how a run starts: epoch ``k0``, nominal ``x0`` (9 + 3N), the error-state
    covariance ``P0_err`` (23-dim, rotation-vector attitude) and notes for the history."""

    k0: int
    x0: Array
    P0_err: Array
    info: dict[str, Any] = field(default_factory=dict)


def error_to_filter_cov(x: Array, P_err: Array, variant: Variant) -> Array:
    """The filter's own P0: the error-state covariance for ``mult``; for the additive UKF the
    4-component quaternion's, ``dq = 1/2 [dtheta; 0] (x) q`` plus a small variance along
    ``q`` itself (its norm direction, which the additive UKF renormalises away)."""
    if variant == "mult":
        return P_err
    n = P_err.shape[-1]
    q = x[3:7]
    E = rot.quat_multiply(np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1), q)  # (3, 4)
    T = np.zeros((n + 1, n))
    T[0:3, 0:3] = np.eye(3)
    T[3:7, 3:6] = 0.5 * E.T
    T[7:, 6:] = np.eye(n - 6)
    P = T @ P_err @ T.T
    v = 0.25 * float(np.min(np.diag(P_err)[3:6]))
    P[3:7, 3:7] += v * np.outer(q, q)
    return 0.5 * (P + P.T)


def _frame_jacobian(x: Array) -> Array:
    """d(error state)/d(eps) (23 x 3) of turning the body frame by ``eps`` (T' = exp(eps) T):
    ``omega, p -> exp(eps) omega, exp(eps) p``, ``q -> exp(eps) (x) q``; numerically."""
    N = (len(x) - 9) // 3
    lay = layout(N)

    def turned(e: Array) -> Array:
        R = rot.exp_map(e)
        y = x.copy()
        y[0:3] = R @ x[0:3]
        y[3:7] = rot.quat_multiply(rot.exp_quat(e), x[3:7])
        y[9:] = (x[9:].reshape(-1, 3) @ R.T).ravel()
        return y

    h = 1e-6
    J = np.zeros((lay.dim, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        J[:, i] = (lay.boxminus(turned(e), x) - lay.boxminus(turned(-e), x)) / (2 * h)
    return J


def start(
    scenario: Any, t: Array, z: Array, geom: KabirGeometry, tun: KabirTuning, sigma_p: float
) -> KabirStart:
    """The run's start (see the module docstring and ``init`` in :class:`KabirTuning`)."""
    N = z.shape[1]
    if tun.init == "identified":
        try:
            return _identified_start(t, z, geom, tun, sigma_p)
        except InputError as exc:
            # too short a run, or a pure spin: no inertia to identify. The filter still runs,
            # from the triangulated start that admits it knows no frame, and says so
            fallback = start(
                scenario, t, z, geom, tun.model_copy(update={"init": "triangulated"}), sigma_p
            )
            fallback.info["warning"] = (
                f"{str(exc).removeprefix('estimator.tuning.init: ')}: started as 'triangulated' "
                "instead (the attitude unknown, 1-sigma init_attitude_sigma_rad)"
            )
            return fallback
    x = np.zeros(9 + 3 * N)
    if tun.init == "given":
        x[0:3] = tun.init_omega_rad_s
        q = np.asarray(tun.init_q_TI, dtype=float)
        if not np.linalg.norm(q) > 0:
            raise InputError("estimator.tuning.init_q_TI: must be a nonzero quaternion")
        x[3:7] = rot.quat_normalize(q)
        p = np.asarray(tun.init_features_m, dtype=float).reshape(-1, 3)
        if p.shape[0] != N:
            raise InputError(
                f"estimator.tuning.init_features_m: {p.shape[0]} features given, the "
                f"measurements have {N}"
            )
        x[9:] = p.ravel()
        var = [tun.p0_omega_var] * 3 + [4.0 * tun.p0_quat_var] * 3  # dtheta = 2 dq_vec
        var += [tun.p0_k_var] * 2 + [tun.p0_feature_var] * (3 * N)
        return KabirStart(0, x, np.diag(var), {"init": "given"})
    x[0:3], x[3:7], x[9:] = _triangulated_start(t, z, geom)
    # q = identity says nothing of the principal frame: the frame is uncertain by
    # init_attitude_sigma_rad, and the rate and features (expressed in it) turn with it
    J = _frame_jacobian(x)
    P = (tun.init_attitude_sigma_rad**2) * (J @ J.T)
    var = [tun.p0_omega_var] * 3 + [0.0] * 3 + [tun.p0_k_var] * 2
    var += [tun.p0_feature_var * 1e-4] * (3 * N)  # triangulated: ~1.5 cm at p0_feature_var
    P += np.diag(var)
    return KabirStart(0, x, 0.5 * (P + P.T), {"init": "triangulated"})


def initial_state(
    scenario: Any, t: Array, z: Array, geom: KabirGeometry, tun: KabirTuning, variant: Variant
) -> tuple[Array, Array]:
    """``x0`` (nominal) and ``P0`` (24x24 for ``additive``, 23x23 for ``mult``) at the start
    epoch (:func:`start`; ``sigma_p`` from the tuning, else 1e-5 rad)."""
    sp = tun.sigma_p_rad if isinstance(tun.sigma_p_rad, float) else 1e-5
    s = start(scenario, t, z, geom, tun, sp)
    return s.x0, error_to_filter_cov(s.x0, s.P0_err, variant)


# --- identified start ----------------------------------------------------------------------


def _kabsch(g: Array, r: Array, w: NDArray[np.bool_]) -> Array:
    """R (B, 3, 3) minimising sum_i w_i |r_i - R g_i|^2 (points about the known mass centre,
    so no centroid); g (N, 3), r (B, N, 3), w (B, N)."""
    H = np.einsum("bn,bni,nj->bij", w.astype(float), np.nan_to_num(r), g)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((len(H), 3))
    D[:, 2] = d
    return (U * D[:, None, :]) @ Vt


def _principal(I_G: Array, ref: Array | None = None) -> tuple[Array, Array]:
    """Moments ascending (I1 < I2 < I3, as Kabir's 90/100/112) and R_GT (columns = T's axes in
    G), signs: each of the first two axes' largest component positive (or, with ``ref``,
    the signs closest to ``ref``), the third their cross product."""
    lam, V = np.linalg.eigh(0.5 * (I_G + I_G.T))
    for j in range(2):
        if ref is not None:
            s = np.sign(V[:, j] @ ref[:, j])
        else:
            s = np.sign(V[np.argmax(np.abs(V[:, j])), j])
        V[:, j] *= s if s != 0 else 1.0
    V[:, 2] = np.cross(V[:, 0], V[:, 1])
    return lam, V


def _triangulate(z: Array, geom: KabirGeometry) -> tuple[Array, NDArray[np.bool_]]:
    """Features in C (n, N, 3) from ``[u_R, v_R, u_L]`` (the disparity ``u_L - u_R``), and
    where available."""
    cl, cr = geom.centres_x
    ok = np.all(np.isfinite(z[..., [0, 1, 2]]), axis=-1)
    y = (cr - cl) / (z[..., 2] - z[..., 0])
    rho = np.stack([z[..., 2] * y + cl, y, z[..., 1] * y], -1)
    return np.where(ok[..., None], rho, np.nan), ok


def _identified_start(
    t: Array, z: Array, geom: KabirGeometry, tun: KabirTuning, sigma_p: float
) -> KabirStart:
    n, N = z.shape[:2]
    dt = float(t[1] - t[0]) if n > 1 else 1.0
    rho, ok = _triangulate(z, geom)
    r = (rho - geom.rho0_C[:, None, :]) @ geom.R_CI  # about the mass centre, in I (n, N, 3)
    have = np.flatnonzero(ok.sum(axis=1) >= 3)
    if len(have) == 0:
        raise InputError("estimator.tuning.init: 'identified' needs >= 3 stereo features")
    kt = int(have[0])
    tmpl_ok = ok[kt]
    common = ok & tmpl_ok[None, :]
    usable = common.sum(axis=1) >= 3
    # the first run of epochs (from kt) where >= 3 template features are seen
    stop = kt + int(np.argmin(usable[kt:])) if not usable[kt:].all() else n
    if tun.init_max_window_s is not None:
        stop = min(stop, kt + int(np.floor(tun.init_max_window_s / dt + 1e-9)) + 1)
    if stop - kt < 12:
        raise InputError(
            "estimator.tuning.init: 'identified' needs >= 12 epochs of >= 3 features at the start"
        )
    ks = np.arange(kt, stop)
    g = r[kt].copy()
    g[~tmpl_ok] = 0.0
    R_IG = _kabsch(g, r[ks], common[ks])
    # one refinement of the template: every epoch's points turned back into G, averaged
    back = np.einsum("bji,bnj->bni", R_IG, np.nan_to_num(r[ks]))  # R_IG^T r
    cnt = common[ks].sum(0)
    g = np.where(
        cnt[:, None] > 0, (back * common[ks][..., None]).sum(0) / np.maximum(cnt, 1)[:, None], 0.0
    )
    R_IG = _kabsch(g, r[ks], common[ks])
    resid = np.where(
        common[ks][..., None], np.nan_to_num(r[ks]) - np.einsum("bij,nj->bni", R_IG, g), 0.0
    )
    sig_r2 = float(np.sum(resid**2) / max(3 * common[ks].sum() - 3 * len(ks), 1))
    # central rates of G in G at epochs ks[L:-L], over +- L epochs (init_rate_lag)
    spread = float(np.sum(g[tmpl_ok] ** 2))
    L = _rate_lag(R_IG, dt, tun.init_rate_lag, sig_r2 / max(spread, 1e-9))
    if len(ks) - 2 * L < 10:
        raise InputError(
            "estimator.tuning.init: 'identified' needs >= 10 central rates at the start"
        )
    dR = np.einsum("bji,bjk->bik", R_IG[: -2 * L], R_IG[2 * L :])  # R_IG(k-L)^T R_IG(k+L)
    w_G = rot.log_map(dR) / (2.0 * L * dt)  # (m, 3), at ks[L:-L]
    R_GI = np.swapaxes(R_IG[L:-L], -1, -2)
    a, b = inertia_design(w_G, R_GI)
    a = a.reshape(-1, 3, 8)
    b = b.reshape(-1, 3)
    best = None
    m_min = 10
    m = m_min
    while True:
        m = min(m, len(w_G))
        A = a[:m].reshape(-1, 8)
        B = b[:m].reshape(-1)
        res = _solve_frame(A, B, m)
        if res is not None and (best is None or res["sigma_frame"] < best["sigma_frame"]):
            best = dict(res, m=m)
        if res is not None and res["sigma_frame"] < tun.init_frame_sigma_rad:
            break
        if m >= len(w_G):
            break
        m = int(np.ceil(m * 1.15))
    if best is None:
        raise InputError(
            "estimator.tuning.init: 'identified' could not identify the inertia from the first "
            f"{(stop - kt) * dt:.0f} s (the rate direction does not move: a pure spin?); use "
            "init: triangulated or given"
        )
    m = best["m"]
    kc = int(ks[m - 1 + L])  # epoch of the last central rate used (its difference: ks[m-1+2L])
    R_GT = best["R_GT"]
    lam = best["lam"]
    # features never seen at the template epoch: from the first window epoch they are seen
    g_all = g.copy()
    for i in np.flatnonzero(~tmpl_ok):
        seen = np.flatnonzero(ok[ks[: m + 2 * L], i])
        if len(seen):
            j = seen[0]
            g_all[i] = R_IG[j].T @ r[ks[j], i]
    x = _identified_state(R_IG[m - 1 + L], w_G[m - 1], g_all, R_GT, lam)
    lay = layout(N)
    # covariance: the identification's (numerical Jacobian of the state in l) ...
    l0 = best["X"][:5]
    Jl = np.zeros((lay.dim, 5))
    for j in range(5):
        h = 1e-6 * max(1.0, abs(l0[j]))
        xs = []
        for sgn in (1.0, -1.0):
            lj = l0.copy()
            lj[j] += sgn * h
            lam_j, R_j = _principal(_inertia(lj), ref=R_GT)
            xs.append(_identified_state(R_IG[m - 1 + L], w_G[m - 1], g_all, R_j, lam_j))
        Jl[:, j] = (lay.boxminus(xs[0], x) - lay.boxminus(xs[1], x)) / (2 * h)
    P = Jl @ best["cov_l"] @ Jl.T
    # ... plus the measurements' own: the rate (the least squares' residual level, 3x for the
    # overlapping differences), G's attitude at kc (the Kabsch residuals over the points'
    # spread) and the template (its residuals over the epochs that saw each point)
    var_att = max(3.0 * sig_r2 / max(spread, 1e-9), (0.1 * sigma_p) ** 2)
    var_w = max(3.0 * best["s2"], 2.0 * var_att / (L * dt) ** 2)
    P[0:3, 0:3] += var_w * np.eye(3)
    P[3:6, 3:6] += var_att * np.eye(3)
    var_p = 3.0 * sig_r2 / np.maximum(cnt, 1) + (0.1 * sigma_p * 10.0) ** 2
    var_p = np.where(cnt > 0, var_p, tun.p0_feature_var)
    P[8:, 8:] += np.diag(np.repeat(var_p, 3))
    P[6:8, 6:8] += 1e-8 * np.eye(2)
    info = {
        "init": "identified",
        "start_s": float(t[kc]),
        "window_s": [float(t[kt]), float(t[ks[m - 1 + 2 * L]])],
        "rate_lag": L,
        "frame_sigma_rad": float(best["sigma_frame"]),
        "inertia_condition": float(best["cond"]),
    }
    if best["sigma_frame"] >= tun.init_frame_sigma_rad:
        info["warning"] = (
            f"identified start: the principal frame is known only to "
            f"{np.degrees(best['sigma_frame']):.1f} deg (1 sigma) after "
            f"{(ks[m - 1 + 2 * L] - kt) * dt:.0f} s of observation; the filter starts with that "
            "covariance"
        )
    return KabirStart(kc, x, 0.5 * (P + P.T), info)


def _rate_lag(R_IG: Array, dt: float, lag: int | None, var_att: float) -> int:
    """The central differences' half-width in epochs (``init_rate_lag``): the given one, or
    the fewest that bring the rate's noise (``sqrt(2 var_att) / (2 L dt)``, ``var_att`` the
    attitudes' noise per axis) below 1 % of the rate, at most as many as turn the target by
    0.8 rad per epoch of half-width (the difference's truncation), a tenth of the window
    and 50."""
    if lag is not None:
        return int(lag)
    step = rot.log_map(np.einsum("bji,bjk->bik", R_IG[:-1], R_IG[1:]))
    turn = float(np.median(np.linalg.norm(step, axis=-1))) if len(step) else 0.0
    if turn <= 0.0:
        return 1
    L_noise = int(np.ceil(np.sqrt(2.0 * var_att) / (2.0 * 0.01 * turn)))
    L_max = max(1, min(int(np.floor(0.8 / turn)), 50, len(R_IG) // 10))
    return max(1, min(L_noise, L_max))


def _inertia(l: Array) -> Array:
    return np.array([[1.0, l[2], l[3]], [l[2], l[0], l[4]], [l[3], l[4], l[1]]])


def _identified_state(R_IG: Array, w_G: Array, g: Array, R_GT: Array, lam: Array) -> Array:
    """Kabir's state from G's attitude and rate, the template (in G) and the principal frame."""
    R_TI = R_GT.T @ R_IG.T
    x = np.zeros(9 + 3 * len(g))
    x[0:3] = R_GT.T @ w_G
    x[3:7] = rot.matrix_to_quat(R_TI)
    x[7:9] = [np.log(lam[0] / lam[1]), np.log(lam[2] / lam[1])]
    x[9:] = (g @ R_GT).ravel()
    return x


def _solve_frame(A: Array, B: Array, m: int) -> dict[str, Any] | None:
    """Hu 2024 eq. 13's least squares on ``m`` epochs with its covariance (the residual
    variance, 3x for the overlapping central differences), the principal frame and its
    1-sigma (largest axis, rad) by the eigenvector perturbation; None if not identifiable."""
    col = np.linalg.norm(A, axis=0)
    if not np.all(col > 0):
        return None
    As = A / col
    sv = np.linalg.svd(As, compute_uv=False)
    cond = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
    if not cond < 1e8:
        return None
    Xs, *_ = np.linalg.lstsq(As, B, rcond=None)
    X = Xs / col
    rr = A @ X - B
    s2 = float(np.sum(rr**2) / max(3 * m - 8, 1))
    Ninv = np.linalg.inv(As.T @ As) / np.outer(col, col)
    cov = 3.0 * s2 * Ninv
    I_G = _inertia(X[:5])
    lam, R_GT = _principal(I_G)
    if not (lam[0] > 0 and lam[0] + lam[1] >= lam[2]):
        return None
    # eigenvector perturbation (as frontends.stereo_points.inertia_ls, ascending order here)
    Jphi = np.zeros((3, 5))
    for j in range(5):
        E = np.zeros(5)
        E[j] = 1.0
        dI = _inertia(E) - _inertia(np.zeros(5))
        dI[0, 0] = 0.0
        r1, r2, r3 = R_GT[:, 0], R_GT[:, 1], R_GT[:, 2]
        Jphi[0, j] = (r3 @ dI @ r2) / (lam[1] - lam[2])
        Jphi[1, j] = -(r3 @ dI @ r1) / (lam[0] - lam[2])
        Jphi[2, j] = (r2 @ dI @ r1) / (lam[0] - lam[1])
    cov_l = cov[:5, :5]
    cov_phi = Jphi @ cov_l @ Jphi.T
    sig = float(np.sqrt(max(np.linalg.eigvalsh(cov_phi).max(), 0.0)))
    if not np.isfinite(sig):
        return None
    return {
        "X": X,
        "cov_l": cov_l,
        "s2": s2,
        "lam": lam,
        "R_GT": R_GT,
        "sigma_frame": sig,
        "cond": cond,
    }


def _triangulated_start(t: Array, z: Array, geom: KabirGeometry) -> tuple[Array, Array, Array]:
    """At ``t[0]``: q_TI = identity (T := I); features triangulated in C; omega_C by least
    squares on ``w_dot = A omega`` (Kabir 2025 eq. 18-19) with the flow from the one-sided
    second-order difference of the first three epochs' projections (else ``z[0]``'s flow)."""
    z0 = z[0]
    cl, cr = geom.centres_x
    ok = np.all(np.isfinite(z0[:, [0, 1, 2]]), axis=1)
    if ok.sum() < 2:
        raise InputError("estimator.tuning.init: 'triangulated' needs >= 2 stereo features at t0")
    y = (cr - cl) / (z0[:, 2] - z0[:, 0])  # disparity u_L - u_R = b / y
    rho = np.stack([z0[:, 2] * y + cl, y, z0[:, 1] * y], -1)
    rho0 = geom.rho0_C[0]
    flow = z0[:, 5:9]
    if len(t) >= 3 and np.isclose(t[2] - t[1], t[1] - t[0]):
        w = z[:3, :, 0:4]
        one_sided = (-3.0 * w[0] + 4.0 * w[1] - w[2]) / (2.0 * (t[1] - t[0]))
        flow = np.where(np.isfinite(one_sided), one_sided, flow)
    A_R, A_L = proj.flow_matrices(rho, rho0, geom.centres_x)
    A = np.concatenate([A_R, A_L], axis=1).reshape(-1, 3)  # rows du_R, dv_R, du_L, dv_L
    J = proj.projection_jacobian(rho, geom.centres_x)[:, ::-1].reshape(len(z0), 4, 3)
    b = (flow - J @ geom.rho0_dot_C[0]).reshape(-1)  # flow of the rotation alone
    use = np.repeat(ok, 4) & np.isfinite(b)
    if use.sum() < 6:
        raise InputError("estimator.tuning.init: 'triangulated' needs the flow of >= 2 features")
    omega_C = np.linalg.lstsq(A[use], b[use], rcond=None)[0]
    R_TC = geom.R_CI.T  # q_TI = identity: T = I
    p = np.where(ok[:, None], (rho - rho0) @ R_TC.T, 0.0)
    return R_TC @ omega_C, rot.IDENTITY.copy(), p.ravel()
