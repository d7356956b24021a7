"""Hu 2024's filter model: state layout, error dynamics (eq. 28-30), process noise, propagation
(eq. 2, 21, 36-39), the feature measurement (eq. 32-35) and the inertia constraint."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import rk4_step
from tumblenav.dynamics.relative_orbit import cw_discrete, hill_matrix
from tumblenav.dynamics.rigid_body import euler_rhs_coefficients
from tumblenav.estimators.base import (
    Block,
    StateLayout,
)

Array = NDArray[np.float64]


def layout(n_features: int) -> StateLayout:
    return StateLayout(
        (
            Block("attitude", "quat", 3),
            Block("rate", "vector", 3),
            Block("inertia", "vector", 3),
            Block("position", "vector", 3),
            Block("velocity", "vector", 3),
            Block("features", "vector", 3 * n_features),
        )
    )


def euler_ratios_rhs(w: Array, p: Array) -> Array:
    """Hu 2024 eq. 21-22: ``omega' = K(omega) = [px wy wz, py wx wz, pz wx wy]``: the Euler
    equations with coefficients ``p`` (:func:`tumblenav.dynamics.rigid_body.euler_rhs_coefficients`)."""
    return euler_rhs_coefficients(w, p)


def noise_gain(p: Array) -> Array:
    """Diagonal of Hu 2024 eq. 22 J(p) = diag(1, Ix/Iy, Ix/Iz) in terms of p."""
    return np.stack(
        [
            np.ones(p.shape[:-1]),
            (1 - p[..., 1]) / (1 + p[..., 0]),
            (1 + p[..., 2]) / (1 - p[..., 0]),
        ],
        -1,
    )


def core_F(w: Array, p: Array, n_orbit: float, rotation_only: bool = False) -> Array:
    """(…,15,15) error dynamics of [dtheta, domega, dp, dr, dv] (Hu 2024 eq. 29-30, Hamilton);
    with ``rotation_only`` the (…,9,9) rotational block alone."""
    lead = w.shape[:-1]
    F = np.zeros(lead + ((9, 9) if rotation_only else (15, 15)))
    F[..., 0:3, 0:3] = -rot.skew(w)
    F[..., 0:3, 3:6] = -np.eye(3)
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    z = np.zeros(lead)
    F[..., 3:6, 3:6] = np.stack(  # M(omega, p), eq. 30
        [
            np.stack([z, px * wz, px * wy], -1),
            np.stack([py * wz, z, py * wx], -1),
            np.stack([pz * wy, pz * wx, z], -1),
        ],
        -2,
    )
    F[..., 3:6, 6:9] = np.stack(  # N(omega), eq. 30
        [
            np.stack([wy * wz, z, z], -1),
            np.stack([z, wx * wz, z], -1),
            np.stack([z, z, wx * wy], -1),
        ],
        -2,
    )
    if rotation_only:
        return F
    F[..., 9:15, 9:15] = hill_matrix(n_orbit)  # Hu 2024 eq. 4-5
    return F


def core_Qc(p: Array, sigma_r2: float, sigma_t2: float) -> Array:
    """Continuous process noise G Q G^T of the 15-state core (Hu 2024 eq. 28)."""
    Q = np.zeros(p.shape[:-1] + (15, 15))
    j = noise_gain(p)
    Q[..., 3:6, 3:6] = sigma_r2 * (j[..., :, None] * j[..., None, :]) * np.eye(3)
    Q[..., 12:15, 12:15] = sigma_t2 * np.eye(3)
    return Q


def frame_error_rate_jacobian(w: Array, p: Array) -> Array:
    """``G = d(omega') / d u`` (…,3,3): how a small rotation ``u`` between the frame the
    filter's state is in (the DPACF frame T') and the true principal frame T changes the
    angular acceleration that the Euler equations give in T' (beyond the paper).

    Here the coordinates in T' are ``R`` times those in T, ``R = exp([u x])``: in T' the
    true inertia is ``R I R^T``,
    not diagonal, and ``omega' = R K(R^T omega, p)`` (``K`` Hu 2024 eq. 21, the truth's
    ratios) rather than the filter's ``K(omega, p)``. To first order in u (``R = I + [u x]``):
    ``omega' = K(omega) + [u x] K(omega) - M(omega, p) [u x] omega``, i.e.
    ``G = M(omega, p) [omega x] - [K(omega) x]`` with ``M = dK/domega`` (eq. 30).

    Sign: the consider model's ``u`` (:func:`tumblenav.estimators.hu2024.frame.frame_jacobian`
    and ``frame_consider_cov``: the truth's coordinates are ``exp([u x])`` times the filter
    frame's) is the inverse rotation of this one, so the rate error there gains ``-G u``
    (``frame_error_model: state``; tested by finite differences). The white model
    (:func:`frame_error_Qc`) does not depend on the sign."""
    M = core_F(w, p, 0.0, rotation_only=True)[..., 3:6, 3:6]
    return M @ rot.skew(w) - rot.skew(euler_ratios_rhs(w, p))


def frame_error_Qc(w: Array, p: Array, cov_frame: Array, tau_max_s: float) -> Array:
    """Rate-block spectral density (…,3,3, rad^2/s^3) that stands for the DPACF frame's
    error in the rate dynamics (beyond the paper; 'consider' frame model).

    The frame error ``u ~ N(0, cov_frame)`` is constant over the time the front end holds a
    frame and changes only slowly when it re-solves it, so it adds ``G(t) u``
    (:func:`frame_error_rate_jacobian`) to the angular acceleration. ``G`` turns with the
    rate in the body (the polhode): over a window much longer than the polhode's time
    ``tau = |omega| / |K(omega)|`` (the time Euler's terms take to change the rate by its own
    size) the signal averages out, over a shorter one it acts as a bias. As white noise it
    is given the density that makes the rate's error variance right at ``tau``: a bias
    ``G u`` gives ``G cov_frame G^T tau^2`` over ``tau``, white noise ``S tau``, so
    ``S = G cov_frame G^T tau``, with ``tau <= tau_max_s`` (a spin near a principal axis,
    where ``K`` vanishes: the bias persists, and the window is the filter's memory)."""
    G = frame_error_rate_jacobian(w, p)
    k = np.linalg.norm(euler_ratios_rhs(w, p), axis=-1)
    wn = np.linalg.norm(w, axis=-1)
    tau = np.where(k * tau_max_s > wn, wn / np.maximum(k, 1e-300), tau_max_s)
    S = G @ np.nan_to_num(cov_frame) @ np.swapaxes(G, -1, -2)
    return tau[..., None, None] * 0.5 * (S + np.swapaxes(S, -1, -2))


def _translation_discrete(n_orbit: float, sigma_t2: float, dt: float) -> tuple[Array, Array]:
    """Phi and Q_k of the translational block (Hu 2024 eq. 4-5, 38-39): constant for a given
    dt (:func:`tumblenav.dynamics.relative_orbit.cw_discrete`)."""
    return cw_discrete(n_orbit, sigma_t2, dt)


def propagate_rotation(q: Array, w: Array, p: Array, dt: float) -> tuple[Array, Array]:
    """RK4 of the nominal attitude and rate (Hu 2024 eq. 2, 21) over ``dt``
    (:func:`tumblenav.dynamics.integrators.rk4_step`), the quaternion renormalised."""
    q_new, w_new = rk4_step(
        lambda q_, w_: (rot.quat_derivative(q_, w_), euler_rhs_coefficients(w_, p)), (q, w), dt
    )
    return q_new / np.linalg.norm(q_new, axis=-1, keepdims=True), w_new


def feature_measurement(
    x: Array, R_LI: Array, lay: StateLayout, jac: bool = False
) -> tuple[Array, Array | None]:
    """Hu 2024 eq. 32: ``y_i = r + R_LT f_i`` for all features, (…,N,3); with ``jac`` also
    the Jacobian (…,3N,dim) w.r.t. the error state (eq. 35 with the Hamilton sign)."""
    q = x[..., lay.nom("attitude")]
    r = x[..., lay.nom("position")]
    # annotated: numpy's stubs pick reshape's 0-d overload for a shape built as a tuple sum
    f: Array = x[..., lay.nom("features")].reshape(x.shape[:-1] + (-1, 3))
    R_LT = R_LI @ np.swapaxes(rot.quat_to_matrix(q), -1, -2)
    y = r[..., None, :] + np.einsum("...ij,...kj->...ki", R_LT, f)
    if not jac:
        return y, None
    N = f.shape[-2]
    H = np.zeros(x.shape[:-1] + (3 * N, lay.dim))
    Hth = R_LT[..., None, :, :] @ rot.skew(f)  # (…,N,3,3)
    sf = lay.err("features").start
    for i in range(N):
        rows = slice(3 * i, 3 * i + 3)
        H[..., rows, lay.err("attitude")] = Hth[..., i, :, :]
        H[..., rows, lay.err("position")] = np.eye(3)
        H[..., rows, sf + 3 * i : sf + 3 * i + 3] = R_LT
    return y, H


def recentre_unseen(x: Array, R_LI: Array, p_L: Array, fresh: Array, lay: StateLayout) -> Array:
    """The prior mean of each feature in ``fresh`` (…,N) moved to its first sighting,
    ``f_i = R_LT^T (p_L,i - r)`` (the inverse of Hu 2024 eq. 32 at the prior), so that its
    first update and its first-estimates Jacobian (``R_LT [f_i x]``) are linearised there
    and not at the placeholder 0 of a feature not seen at the start (tumblenav default).

    Only for features whose prior is still the uninformative one of the start
    (``p0_unseen_feature_m``, uncorrelated with the rest of the state): moving the mean of a
    3 m prior by its first sighting changes the information by a fraction (measurement /
    prior variance) of order 1e-5, and the update then carries the attitude's share of the
    feature's error (``[f x] dtheta``) into its covariance. With the old placeholder the
    Jacobian of such a feature stayed ``R_LT [0 x] = 0`` for good (first estimates), and
    under self-occlusion, where most features appear after the start, the filter locked
    onto a wrong answer with confidence."""
    sf = lay.nom("features")
    q = x[..., lay.nom("attitude")]
    r = x[..., lay.nom("position")]
    R_LT = R_LI @ np.swapaxes(rot.quat_to_matrix(q), -1, -2)
    f_new = np.einsum("...ji,...kj->...ki", R_LT, p_L - r[..., None, :])  # R_LT^T (p - r)
    f = x[..., sf].reshape(x.shape[:-1] + (-1, 3))
    f = np.where(fresh[..., None], f_new, f)
    out = x.copy()
    out[..., sf] = f.reshape(x.shape[:-1] + (-1,))
    return out


_FLIPS = np.array(
    [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
)


MAX_REINITS = 20  # restarts of a run that lost track (filter.run_filter), at most


def _diverged(x: Array, P: Array, lay: StateLayout) -> NDArray[np.bool_]:
    """Runs whose state left any physical range (non-finite, |omega| above MAX_RATE_RAD_S,
    |p| > 10, features beyond 1 km)."""
    fin = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(P), axis=(1, 2))
    w = np.linalg.norm(x[:, lay.nom("rate")], axis=1)
    p = np.abs(x[:, lay.nom("inertia")]).max(axis=1)
    f = np.abs(x[:, lay.nom("features")]).max(axis=1, initial=0.0)
    return ~fin | ~(w < MAX_RATE_RAD_S) | ~(p < 10) | ~(f < 1e3)


def inertia_constraint(p: Array, jac: bool = False):
    """Physical constraint of Hu's ratios (eq. 19): ``c(p) = px + py + pz + px py pz = 0``.

    It holds for every inertia (expand the ratios over a common denominator); the filter's
    three ratios have only two degrees of freedom, and off the constraint the Euler
    equations (21) no longer conserve energy and can diverge.
    """
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    c = px + py + pz + px * py * pz
    if not jac:
        return c
    return c, np.stack([1 + py * pz, 1 + px * pz, 1 + px * py], -1)


def curvature_variance(p: Array, Pp: Array) -> Array:
    """Variance that the curvature of ``c(p) = 0`` leaves along its gradient.

    Both the estimate and the truth lie on the surface, so their difference ``dp`` obeys
    ``g . dp = -1/2 dp^T C dp`` (to second order; ``C`` the Hessian of c: zero diagonal,
    ``C_xy = pz``, ``C_xz = py``, ``C_yz = px``) rather than ``g . dp = 0``. For a Gaussian
    ``dp`` with covariance ``Pp`` its second moment is
    ``1/2 tr(C Pp C Pp) + 1/4 tr(C Pp)^2`` (Isserlis)."""
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    z = np.zeros_like(px)
    C = np.stack(
        [np.stack([z, pz, py], -1), np.stack([pz, z, px], -1), np.stack([py, px, z], -1)], -2
    )
    CP = C @ Pp
    tr = np.trace(CP, axis1=-2, axis2=-1)
    return 0.5 * np.sum(CP * np.swapaxes(CP, -1, -2), axis=(-1, -2)) + 0.25 * tr**2


def constrain_inertia(
    x: Array,
    P: Array,
    lay: StateLayout,
    active=None,
    r: float = 1e-10,
    curvature: bool = False,
    project: bool = False,
):
    """Apply ``c(p) = 0`` as a (nearly) perfect scalar pseudo-measurement (Simon 2010, "estimate
    projection" by a Kalman update) and keep every ratio inside |p_i| < 1 (triangle inequality).
    Runs where ``active`` is False are left alone.

    With ``curvature`` (beyond Hu 2024), the variance along the constraint gradient is then
    set back to what the surface's curvature leaves (:func:`curvature_variance`): applied
    again and again as a perfect measurement it would shrink to ``r / n`` while the true
    error across the tangent plane is of the order of the tangent variance times the
    curvature (measured: z-scores of 500 along the gradient, docs/results/hu2024.md).

    With ``project`` (beyond Hu 2024 and Simon 2010's measurement form; issue 18), the
    estimate is instead moved onto the surface along its normal (Newton steps on ``c``, the
    other states untouched) and the error covariance projected onto the tangent plane,
    ``P <- T P T^T`` with ``T = I - n n^T`` on the ratios' rows and columns: see
    :func:`project_inertia`."""
    if project:
        return project_inertia(x, P, lay, active, curvature)
    sp = lay.nom("inertia")
    ep = lay.err("inertia")
    c, g = inertia_constraint(x[:, sp], jac=True)
    if active is not None:
        c = np.where(active, c, 0.0)
        g = g * active[:, None]
    PH = (P[:, :, ep] @ g[..., None])[..., 0]  # P H^T, H nonzero on the p block only
    s = np.sum(g * PH[:, ep], axis=1) + r
    K = PH / s[:, None]
    x = lay.boxplus(x, (-K * c[:, None])[:, : lay.dim])  # P may carry consider parameters
    P = P - K[:, :, None] * PH[:, None, :]
    clip = np.clip(x[:, sp], -0.999, 0.999)
    x[:, sp] = clip if active is None else np.where(active[:, None], clip, x[:, sp])
    if curvature:
        _curvature_back(x, P, lay, active)
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


def _curvature_back(x: Array, P: Array, lay: StateLayout, active=None) -> None:
    """In place: the variance :func:`curvature_variance` leaves along the constraint's
    gradient ``g`` at the ratios in ``x``, set back on ``P`` (``v m m^T``, ``m = g / |g|^2``,
    so that ``g . (v m m^T) . g = v``); runs where ``active`` is False are left alone."""
    sp, ep = lay.nom("inertia"), lay.err("inertia")
    _, g = inertia_constraint(x[:, sp], jac=True)
    v = curvature_variance(x[:, sp], P[:, ep, ep])
    m = g / np.sum(g * g, axis=1, keepdims=True)
    add = v[:, None, None] * m[:, :, None] * m[:, None, :]
    if active is not None:
        add = add * np.asarray(active)[:, None, None]
    P[:, ep, ep] += add


def project_inertia(x: Array, P: Array, lay: StateLayout, active=None, curvature: bool = True):
    """``c(p) = 0`` by projection (beyond Hu 2024; issue 18, the ratios' over-confidence).

    The ratios' estimate goes to the nearest point of the surface (Newton steps along the
    gradient ``g``, ``p <- p - c g / |g|^2``, three of them: ``c`` is cubic, and the step
    is second order in the distance), the other states stay where they are; then
    ``|p_i| <= 0.999``. The covariance loses the component along the unit normal
    ``n = g / |g|``: ``P <- T P T^T``, ``T = I - n n^T`` on the ratios' rows and columns (the
    cross-covariances with every other state included); with ``curvature`` the variance
    that the surface's curvature leaves along the gradient is set back
    (:func:`curvature_variance`), as in :func:`constrain_inertia`.

    Why not the pseudo-measurement (Simon 2010's estimate projection by a Kalman update,
    :func:`constrain_inertia`): between two applications the linear updates move the
    ratios along the tangent plane, and the surface curves away from it, so ``c`` grows by
    ``1/2 dp^T C dp``; they also build up covariance between the normal component (whose
    variance is only the curvature's) and the tangent plane, correlation that the truth
    does not have (the normal error ``1/2 dp^T C dp`` is uncorrelated with a Gaussian
    ``dp``). A near-perfect measurement of ``c`` then moves the tangent components by that
    spurious regression, ``-c P_tn / P_nn``: measured on hu_selfocc20, steps of 0.01 in
    the ratios at each application while their sigma was 0.04, and ratios that end 0.03
    off at a sigma of 0.003 (docs/results/consistency.md, twenty-second session). Where the
    normal component is uncorrelated with the rest (the start: an isotropic prior), the
    projection and the measurement agree (tests/test_ekf_dpacf.py)."""
    sp = lay.nom("inertia")
    ep = lay.err("inertia")
    B = x.shape[0]
    on = np.ones(B, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    p = x[:, sp].copy()
    for _ in range(3):
        c, g = inertia_constraint(p, jac=True)
        p = p - (c / np.sum(g * g, axis=1))[:, None] * g
    p = np.clip(p, -0.999, 0.999)
    x = x.copy()
    x[:, sp] = np.where(on[:, None], p, x[:, sp])
    _, g = inertia_constraint(x[:, sp], jac=True)
    gg = np.sum(g * g, axis=1)
    n = g / np.sqrt(gg)[:, None]
    T = np.eye(3) - n[:, :, None] * n[:, None, :]
    T = np.where(on[:, None, None], T, np.eye(3))
    P = P.copy()
    P[:, ep, :] = T @ P[:, ep, :]
    P[:, :, ep] = P[:, :, ep] @ np.swapaxes(T, -1, -2)
    if curvature:
        _curvature_back(x, P, lay, on)
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


def _neutral_state(lay: StateLayout) -> Array:
    x = np.zeros(lay.nominal_dim)
    x[lay.nom("attitude")] = rot.IDENTITY
    return x


# A rate estimate above one turn per second is a filter that blew up: ten times the fastest
# tumble reported for malfunctioning spacecraft (36 deg/s, Hu 2024 Sec. 5 citing [27]).
MAX_RATE_RAD_S = 2 * np.pi


CONSTRAIN_EVERY = 10  # epochs between projections onto the inertia constraint
