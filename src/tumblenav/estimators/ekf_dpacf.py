"""Hu 2024 error-state EKF with the DPACF attitude measurement (``ekf-dpacf``), and the same
filter without DPACF (``ekf-baseline``, principal frame left free as Aghili & Parsa 2009).

State (Hu 2024 eq. 24) ``x = [q_TI, omega_TI_T, p, r_L, v_L, f_1..f_N]`` with Hu's inertia
ratios ``p = [(Iy-Iz)/Ix, (Iz-Ix)/Iy, (Ix-Iy)/Iz]`` (eq. 19); error state (eq. 26)
``dx = [dtheta, domega, dp, dr, dv, df_1..df_N]``, ``q = exp(dtheta) (x) q_hat`` (eq. 27 in
tumblenav's Hamilton convention: the JPL sign of Hu's eq. 27/29/35 flips, see
:mod:`tumblenav.rotations`).

Error dynamics (Hu 2024 eq. 28-30, re-derived for the Hamilton error)::

    dtheta' = -[omega x] dtheta - domega        (Hu eq. 29 prints +I for the JPL error)
    domega' = M(omega, p) domega + N(omega) dp + J(p) n_r
    dr' = dv,   dv' = E1 dr + E2 dv + n_t       (Hu eq. 4-5)

Measurements: the DPACF attitude ``y0 = q_TI`` (eq. 31, front end
:mod:`tumblenav.frontends.stereo_points`) with ``H0 = [I3 0 ...]``, and every triangulated
feature in L (eq. 32) ``y_i = r + R_LT f_i`` with ``dy_i/dtheta = R_LT [f_i x]``
(Hu eq. 35 prints ``-R[f x]`` for the JPL error), ``dy_i/dr = I``, ``dy_i/df_i = R_LT``.

Discretisation: ``Phi = exp(F dt)`` (eq. 38) by a 4th-order series (|F dt| = 0.10 at 10 Hz
for hu2024 because of the -I block: 9e-11 from ``expm`` at 0.1 rad/s, 5e-8 at 0.5 rad/s) and
``Q_k`` (eq. 39) by the Van Loan series to third order in dt (the attitude block starts at
dt^3, so its relative error is of order |F dt|: 0.3% for hu2024); nominal attitude and
rate by RK4. Update: Joseph form (eq. 41), gain eq. 42, multiplicative quaternion update
(eq. 44), and beyond the paper a per-feature chi-square innovation gate (rejections counted).

The filter runs B Monte Carlo runs at once (every array has a leading run axis): this is the
vectorisation that makes a 2000-run campaign take seconds (benchmarks/hu2024_campaign.py).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy import stats

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import discretise, rk4_step
from tumblenav.dynamics.relative_orbit import cw_discrete, hill_matrix
from tumblenav.dynamics.rigid_body import euler_rhs_coefficients
from tumblenav.errors import InputError
from tumblenav.estimators.base import (
    Belief,
    Block,
    EstimateHistory,
    StateLayout,
    StepInfo,
    fold,
    register,
)
from tumblenav.estimators.base import parse_tuning as base_parse_tuning
from tumblenav.estimators.context import context_from_scenario
from tumblenav.frontends import stereo_points
from tumblenav.frontends.inertia import branch_statistics, inertia_ratios
from tumblenav.frontends.stereo_points import StereoPointsTuning
from tumblenav.measurements import STEREO_TRACKS

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


class HuTuning(BaseModel):
    """``estimator.tuning`` keys of ekf-dpacf (all optional), with its defaults;
    :class:`BaselineTuning` holds ekf-baseline's. Two defaults follow another key, and the
    validated model shows the value used: ``dpacf_frame_error`` is 'white' with
    ``dpacf_measurement: frame``, and ``attitude_update`` is on unless the frame error is
    'consider'."""

    model_config = ConfigDict(extra="forbid")
    uses_dpacf: ClassVar[bool] = True
    sigma_t2_m2_s4: float | None = Field(
        None,
        ge=0,
        description="translational process noise (m^2/s^4); null: the scenario's "
        "process_noise.translational_m2_s4 (the mission's assumption, in the context)",
    )
    sigma_r2_rad2_s4: float | None = Field(
        None,
        ge=0,
        description="rotational process noise (rad^2/s^4); null: the scenario's "
        "process_noise.rotational_rad2_s4",
    )
    p0_rate_rad_s: float = Field(0.02, gt=0, description="initial 1-sigma of the rate (rad/s)")
    p0_inertia: float = Field(
        0.05,
        gt=0,
        description="1-sigma of each ratio p at the start, added (ekf-dpacf) to the front "
        "end's least-squares covariance of the ratios",
    )
    p0_mass_centre_m: float = Field(0.5, gt=0, description="CM offset from the feature centroid")
    p0_velocity_m_s: float = Field(0.2, gt=0, description="initial 1-sigma of the velocity (m/s)")
    p0_unseen_feature_m: float = Field(
        3.0, gt=0, description="initial 1-sigma of features not yet seen (m)"
    )
    p0_attitude_rad: float = Field(0.5, gt=0, description="ekf-baseline initial attitude sigma")
    attitude_meas_every: int = Field(1, ge=1, description="use the DPACF attitude every k epochs")
    attitude_corr_time_s: float = Field(
        0.0, ge=0, description="correlation time of the DPACF frame error (R0 inflation)"
    )
    gate_probability: float | None = Field(
        None, gt=0, lt=1, description="per-feature chi-square innovation gate; default: none"
    )
    max_dpacf_sigma_rad: float = Field(0.05, gt=0, description="start once DPACF is this good")
    max_ratio_sigma: float | None = Field(
        0.01,
        gt=0,
        description="the filter starts only once the largest 1-sigma of the front end's "
        "inertia ratios is below this as well (beyond the paper: earlier, the least-squares "
        "ratios can be 4 sigma off, and the filter learns the ratios slowly, so its ratios "
        "stay near their start; ekf-baseline keeps the gate so that both start at the same "
        "epoch); null: no gate. 0.01 is reachable by about 30 s with the template's "
        "refinement: inertia RMSE 0.0049 over 100 runs at 2e-5 rad instead of 0.0123 with "
        "0.03, for a start 8 s later (benchmarks/hu2024_start_gate.py)",
    )
    dpacf_measurement: Literal["attitude", "frame"] = Field(
        "attitude",
        description="'attitude': Hu 2024 eq. 31 (q_TI = q_TG q_GI, every epoch); 'frame': the "
        "DPACF rotation R_TG against the filter's features (beyond the paper)",
    )
    frame_meas_every: int = Field(50, ge=1, description="epochs between frame measurements")
    first_estimates_jacobian: bool = Field(
        True,
        description="linearise dy_i/dtheta at each feature's first estimate (FEJ); off for "
        "ekf-baseline (which starts far from any principal frame, where frozen first "
        "estimates make it diverge)",
    )
    flip_epochs: int = Field(
        50, ge=1, description="DPACF measurements a half turn away before the filter follows"
    )
    constraint_curvature: bool = Field(
        True,
        description="keep the variance that the inertia constraint's curvature leaves along "
        "its gradient (beyond the paper; see constrain_inertia); off for ekf-baseline (whose ratios start at a sphere with 1-sigma 0.5, where the "
        "second-order term is meaningless: 216 instead of 183 of 500 runs at 1e-6 rad "
        "stopped as diverged)",
    )
    mass_centre_init: Literal["joint", "rotation", "centroid"] = Field(
        "joint",
        description="'centroid': the filter starts with the mass centre at the feature "
        "centroid (1-sigma p0_mass_centre_m); 'rotation': from a batch least squares over "
        "the rotation seen before the start, with the features fixed at their template "
        "(beyond the paper, mass_centre_from_rotation); 'joint': the same batch with the "
        "features about the mass centre as unknowns (features_from_rotation), which also "
        "gives the features refined over those views; both fall back to the centroid when "
        "the batch cannot tell the mass centre. 'rotation' for ekf-baseline (with 'joint' its tighter start on features expressed in its free, "
        "wrong principal frame stopped 71 instead of 14 of 500 runs at 2e-5 rad as diverged)",
    )
    iterate_sigma_rad: float = Field(
        0.1,
        ge=0,
        description="where the prior attitude's 1-sigma (rms over the axes) exceeds this, "
        "the update is iterated (relinearised at its posterior, from the same prior, "
        "iterate_max more times; beyond the paper): after a long occlusion the attitude "
        "is tens of degrees uncertain and the update linearised at the prior put the "
        "position and features off by several sigma. 0: never, ekf-baseline's default "
        "(the paper's comparison filter, whose free frame starts tens of degrees "
        "uncertain). Not with gate_probability",
    )
    iterate_max: int = Field(2, ge=0, description="the iterated update's extra iterations")

    p0_mass_centre_floor_m: float = Field(
        0.015,
        ge=0,
        description="1-sigma per axis added to the batch mass centre's covariance "
        "(mass_centre_init 'rotation': its least-squares covariance misses the template "
        "and G-attitude errors; measured errors per axis 3-14 mm rms, "
        "benchmarks/hu2024_mass_centre.py) and, with 'joint', to the features' common "
        "shift (the joint fit takes the G-attitude errors as white: median NEES/dof of the "
        "common shift 1.85 in a slow tumble, 0.07 rad/s, benchmarks/hu2024_mass_centre.py "
        "--scenario docs/results/scenarios/generalisation/g_slowrecede.yaml)",
    )
    dpacf_frame_error: Literal["consider", "white"] = Field(
        "consider",
        description="how the error of the DPACF frame itself (the least-squares principal axes, "
        "cov_frame, slowly varying) enters: 'white': as part of the eq. 31 attitude noise at "
        "every epoch (Hu 2024); 'consider': the filter works in the front end's frame, "
        "re-expresses its state whenever that frame is re-solved, measures only the white "
        "G-attitude part, and adds the frame's covariance to the covariance it reports "
        "(beyond the paper, see frame_consider_cov); 'white' by default with "
        "dpacf_measurement 'frame', and for ekf-baseline",
    )
    attitude_update: bool = Field(
        False,
        description="update with the DPACF attitude of Hu 2024 eq. 31. With "
        "dpacf_frame_error 'consider' that measurement is only the G attitude, a fit to the "
        "same feature points as the feature measurements (eq. 32-35): fusing both counts "
        "those points twice (beyond the paper). Default: off with 'consider' (the DPACF "
        "frame enters as the frame the state is expressed in, its half-turn votes still "
        "use the attitude), on with 'white' (the default follows dpacf_frame_error)",
    )
    refine_start: bool = Field(
        True,
        description="start from a Gauss-Newton fit of the attitude and position to the start "
        "epoch's feature points with their full covariances (refine_start_pose; beyond the "
        "paper), whose covariance is the initial one, and use that epoch only there; off for "
        "ekf-baseline (which has no principal frame to start in)",
    )
    sigma_f2_m2_s: float = Field(
        0.0,
        ge=0,
        description="random walk of each feature's position in T (m^2/s, per axis): what the "
        "rigid, exactly-known-template model leaves out (beyond the paper; Hu 2024 has none)",
    )
    branch_mixture: bool = Field(
        True,
        description="with dpacf_frame_error 'consider': the reported covariance also holds "
        "the half turns of the frame, weighted by the probability that the true inertia "
        "selects them (frontends.inertia.branch_statistics; beyond the paper)",
    )
    max_ratio_wait_s: float = Field(
        30.0,
        ge=0,
        description="with max_ratio_sigma: start anyway once the DPACF frame has been good "
        "enough for this long (a motion that leaves the ratios poorly determined must not "
        "keep the filter from starting)",
    )

    frontend: StereoPointsTuning = Field(
        default_factory=StereoPointsTuning,
        description="the stereo-points front end's settings (StereoPointsTuning); both "
        "estimators share the front end, so that they start on the same data",
    )

    @model_validator(mode="before")
    @classmethod
    def _front_end_keys(cls, raw: Any) -> Any:
        """Front-end keys given at the top level (as before they moved) go to ``frontend``."""
        if not isinstance(raw, dict):
            return raw
        moved = {k: raw[k] for k in StereoPointsTuning.model_fields if k in raw}
        if not moved:
            return raw
        rest = {k: v for k, v in raw.items() if k not in moved}
        return {**rest, "frontend": {**moved, **dict(raw.get("frontend") or {})}}

    @model_validator(mode="after")
    def _dependent_defaults(self) -> HuTuning:
        """The two defaults that follow another key (see the class docstring), and the one
        combination that cannot work."""
        given = self.model_fields_set
        if "dpacf_frame_error" not in given and self.dpacf_measurement == "frame":
            self.dpacf_frame_error = "white"
        consider = self.uses_dpacf and self.dpacf_frame_error == "consider"
        if consider and self.dpacf_measurement == "frame":
            raise ValueError(
                "dpacf_frame_error 'consider' works with dpacf_measurement 'attitude' only"
            )
        if "attitude_update" not in given:
            self.attitude_update = not consider
        return self


class BaselineTuning(HuTuning):
    """``estimator.tuning`` keys of ekf-baseline: :class:`HuTuning`'s, with the defaults of
    the paper's comparison filter (Aghili & Parsa 2009: no DPACF, a free principal frame)."""

    uses_dpacf: ClassVar[bool] = False
    first_estimates_jacobian: bool = False
    constraint_curvature: bool = False
    mass_centre_init: Literal["joint", "rotation", "centroid"] = "rotation"
    iterate_sigma_rad: float = Field(0.0, ge=0)
    dpacf_frame_error: Literal["consider", "white"] = "white"
    attitude_update: bool = True
    refine_start: bool = False


def parse_tuning(raw: dict[str, Any], use_dpacf: bool = True) -> HuTuning:
    """ekf-dpacf's (``use_dpacf``) or ekf-baseline's settings from ``estimator.tuning``."""
    return base_parse_tuning(raw, HuTuning if use_dpacf else BaselineTuning)


# --- model pieces (batched over a leading run axis) --------------------------------------


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
    f = x[..., lay.nom("features")].reshape(x.shape[:-1] + (-1, 3))
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


# --- the filter -------------------------------------------------------------------------


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
    R_LG = fe.R_LI[b, j] @ np.swapaxes(fe.R_GI[b, j], -1, -2)
    return j, R_LG, cw_stm(n_orbit, t[j] - t[j[0]])[:, :3, :]


def mass_centre_from_rotation(
    fe: stereo_points.PointsFrontEnd, b: int, k: int, n_orbit: float, window_s: float = 30.0
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
    dof = max(3 * len(d) - 9, 1)
    cov_c = Ninv[6:, 6:] * max(1.0, chi2 / dof)
    if not np.all(np.isfinite(cov_c)) or np.sqrt(np.max(np.linalg.eigvalsh(cov_c))) > 0.5:
        return None
    return c, cov_c


def features_from_rotation(
    fe: stereo_points.PointsFrontEnd, b: int, k: int, n_orbit: float, window_s: float = 30.0
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

    The window and the weights are those of :func:`mass_centre_from_rotation` (the lever arm
    of the G attitude error is ``f_i``). Returns ``(f_G, cov_f, fitted)``: ``f_G`` (N,3) and
    ``cov_f`` (3N,3N) in G, for the features seen in the window (``fitted``); or None when
    the mass centre is not determined (the 1-sigma of the features' common shift above
    0.5 m: too little rotation in the window) or too few points.
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
    )
    if out is None:
        return None
    _, f, cov, idx = out
    # the features' common shift (a mass centre error) must be determined
    nf = len(idx)
    S = np.kron(np.ones((1, nf)) / nf, np.eye(3))
    if np.sqrt(np.max(np.linalg.eigvalsh(S @ cov @ S.T))) > 0.5:
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


def _initial_state(
    fe: stereo_points.PointsFrontEnd,
    tun: HuTuning,
    use_dpacf: bool,
    lay: StateLayout,
    n_orbit: float = 0.0,
    frame_in_P0: bool = True,
    refine: bool = False,
) -> _Init:
    B, n, N = fe.usable.shape
    ready = np.all(np.isfinite(fe.q_TI), axis=-1) & np.all(np.isfinite(fe.omega_G), axis=-1)
    ready &= fe.usable.sum(axis=-1) >= 3  # fe: the filter's view (filter_view), gated frames
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
        Sc = tun.p0_mass_centre_m**2 * np.eye(3)  # its covariance (in T)
        joint = None  # (f_G, cov_f, fitted) of features_from_rotation
        if tun.mass_centre_init == "rotation":
            batch = mass_centre_from_rotation(fe, b, k, n_orbit)
            if batch is not None:
                gbar, cov_c = batch
                floor = tun.p0_mass_centre_floor_m**2 * np.eye(3)
                Sc = R_TG @ (cov_c + floor) @ R_TG.T
        elif tun.mass_centre_init == "joint":
            joint = features_from_rotation(fe, b, k, n_orbit)
            if joint is not None:
                fit_kn = joint[2] & kn
                gbar = np.mean(g[fit_kn] - joint[0][fit_kn], axis=0)  # mass centre in G
                Sc = tun.p0_mass_centre_floor_m**2 * np.eye(3)  # common floor (in T)
        fG = np.nan_to_num(g - gbar)  # features about the mass centre, in G
        if joint is not None:
            fG = np.where(fit_kn[:, None], joint[0], fG)
        f = np.where(kn[:, None], (R_TG @ fG.T).T, 0.0)
        # r such that the predicted features match the measured ones on average:
        # r = mean_i (p_L,i - R_LT f_i) over the visible, catalogued features (weighted)
        use = u & kn
        wts = np.where(use, 1.0 / np.trace(fe.cov_L[b, k], axis1=-2, axis2=-1), 0.0)
        resid = np.nan_to_num(fe.p_L[b, k]) - f @ R_LT.T
        r0 = np.sum(wts[:, None] * resid, 0) / wts.sum()
        C6 = None  # covariance of (attitude, position) from the refined start
        if refine:
            fit = refine_start_pose(
                fe.p_L[b, k, use],
                fe.cov_L[b, k, use] + 1e-4 * np.eye(3),  # + the features' own 1 cm (below)
                f[use],
                q,
                r0,
                _R_LI_at(fe, b, k),
            )
            if fit is not None:
                q, r0, C6 = fit
                R_LT = _R_LI_at(fe, b, k) @ rot.quat_to_matrix(q).T
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
                np.mean(fe.p_L[b, j, common] - gc @ (fe.R_LI[b, j] @ fe.R_GI[b, j].T).T, axis=0)
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
        if joint is not None:
            # features: the joint fit's covariance (in T) plus the common floor Sc and 1 cm
            # each (as below); r0 = sum_i w_i (p_L,i - R_LT f_i) / sum w, so its error is
            # -R_LT W f_err with W = [w_i I] / sum w
            F = np.zeros((3 * N, 3 * N))
            RT = np.kron(np.eye(N), R_TG)
            F[:] = (
                RT
                @ np.where(
                    np.repeat(fit_kn, 3)[:, None] & np.repeat(fit_kn, 3)[None], joint[1], 0.0
                )
                @ RT.T
            )
            kn3 = np.repeat(kn, 3)
            F += np.where(kn3[:, None] & kn3[None], np.kron(np.ones((N, N)), Sc), 0.0)
            F += np.kron(np.diag(np.where(kn, 1e-4, tun.p0_unseen_feature_m**2)), np.eye(3))
            Wr = np.kron((wts / wts.sum())[None, :], np.eye(3))  # (3, 3N)
            sfe = lay.err("features")
            P[sfe, sfe] = F
            P[sr, sr] = R_LT @ Wr @ F @ Wr.T @ R_LT.T
            P[sr, sfe] = -R_LT @ Wr @ F
            P[sfe, sr] = P[sr, sfe].T
        if C6 is not None:
            sa = lay.err("attitude")
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
                P[si, si] = Sc + 1e-4 * np.eye(3)
            else:
                P[si, si] = tun.p0_unseen_feature_m**2 * np.eye(3)
        # The principal frame itself is uncertain (DPACF error, or unknown for the baseline):
        # a rotation u of the frame moves the attitude by u and rotates the rate and every
        # feature (frame_jacobian; unseen features are at 0). With the 'consider' frame
        # model the filter works in the front end's frame and adds this when it reports.
        if frame_in_P0:
            Ju = frame_jacobian(x0[b][None], lay)[0]
            P += Ju @ cov_frame @ Ju.T
        P0[b] = 0.5 * (P + P.T)
    return _Init(k0=k0, x0=x0, P0=P0)


def _R_LI_at(fe: stereo_points.PointsFrontEnd, b: int, k: int) -> Array:
    return fe.R_LI[b, k]


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


P_TURN_MIN = 1e-9  # half turns less likely than this are left out (= _hu_kernel.P_TURN_MIN)


def _turn_moments(x: Array, mu: Array, S: Array, lay: StateLayout) -> tuple[Array, Array]:
    """``E[D]`` (B, d) and ``E[D D^T]`` (B, d, d) of ``D(u) = turn(x, exp(u)) boxminus x =
    [u; R(u) w - w; 0; 0; 0; R(u) f_i - f_i]`` for ``u ~ N(mu, S)`` (mu (B, 3), S (B, 3, 3)),
    over the six sigma points ``mu +- sqrt(3) L e_i`` (``S = L L^T``; n = 3, kappa = 0: the
    Gaussian's moments to the fourth)."""
    B = x.shape[0]
    N = (lay.nominal_dim - lay.nom("features").start) // 3
    L = np.swapaxes(_chol3(np.nan_to_num(S)), -1, -2)
    U = mu[:, None, :] + np.sqrt(3.0) * np.concatenate([L, -L], 1)  # (B, 6, 3)
    R = rot.exp_map(U)  # (B, 6, 3, 3)
    D = np.zeros((B, 6, lay.dim))
    D[:, :, lay.err("attitude")] = U
    w = x[:, None, lay.nom("rate"), None]
    D[:, :, lay.err("rate")] = (R @ w)[..., 0] - w[..., 0]
    f = x[:, lay.nom("features")].reshape(B, 1, N, 3)
    D[:, :, lay.err("features")] = (f @ np.swapaxes(R, -1, -2) - f).reshape(B, 6, 3 * N)
    return D.mean(axis=1), np.swapaxes(D, -1, -2) @ D / 6.0


def frame_consider_cov(
    x: Array,
    P: Array,
    cov_frame: Array,
    lay: StateLayout,
    p_turn: Array | None = None,
    mu_turn: Array | None = None,
    S_turn: Array | None = None,
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
    (to first order ``Ju u``, :func:`frame_jacobian`), over six sigma points
    (:func:`_turn_moments`): at 1e-6 rad the features' shape is known to micrometres while
    the frame is known to a tenth of a degree, and the quadratic part of the turn,
    ``[u x]^2 f / 2``, is then many of the shape's sigmas. With ``p_turn`` (B, 3) and the
    frame error given each turn, ``mu_turn`` (B, 3, 3) and ``S_turn`` (B, 3, 3, 3), all three
    from ``frontends.inertia.branch_statistics``, the half turns of the frame are added,
    :func:`branch_mixture_cov`."""
    B = x.shape[0]
    C = np.nan_to_num(cov_frame)
    _, D2 = _turn_moments(x, np.zeros((B, 3)), C, lay)
    out = P + D2
    if p_turn is not None:
        out = branch_mixture_cov(x, P, out, p_turn, mu_turn, S_turn, lay)
    return out


def branch_mixture_cov(
    x: Array, P: Array, Pc: Array, p_turn: Array, mu_turn: Array, S_turn: Array, lay: StateLayout
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
    the non-attitude part), turns with ``p_a <= P_TURN_MIN`` left out."""
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
        m1, m2 = _turn_moments(xs, mu_turn[sel, a], S_turn[sel, a], lay)
        Jm = m1 * sg
        comp = (P[sel] + m2) * np.outer(sg, sg) + v[:, :, None] * v[:, None, :]
        comp += v[:, :, None] * Jm[:, None, :] + Jm[:, :, None] * v[:, None, :]
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
    J = np.tile(np.eye(lay.dim), (len(b), 1, 1))
    for name in ("attitude", "rate"):
        sl = lay.err(name)
        J[:, sl, sl] = F
    sf0 = lay.err("features").start
    for i in range(N):
        J[:, sf0 + 3 * i : sf0 + 3 * i + 3, sf0 + 3 * i : sf0 + 3 * i + 3] = F
    P[b] = J @ P[b] @ np.swapaxes(J, -1, -2)
    if f_first is not None:
        f_first[b] = f_first[b] @ np.swapaxes(F, -1, -2)


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


def run_filter(
    scenario: Any,
    meas_list: list,
    use_dpacf: bool,
    p_every: int = 1,
    engine: Literal["auto", "numpy", "compiled"] | None = None,
) -> dict[str, Any]:
    """Run the EKF on B runs at once. Returns the histories ``x`` (B, n, nom) and ``P``
    (B, ceil(n / p_every), d, d), the covariance of every ``p_every``-th epoch (campaigns need
    it only for the NEES, at about 1 Hz), the NIS and what each run skipped. It never
    sees the truth: errors are the evaluation's (:mod:`tumblenav.evaluation`).

    ``engine``: the compiled per-run loop (:mod:`tumblenav.estimators._hu_kernel`) or the
    batched numpy loop below; both give the same result (tests). ``auto`` takes the compiled
    one wherever it covers the tuning (eq. 31 attitude measurement, no innovation gate).
    ``None``: the module's ``ENGINE`` (benchmarks set it to time the numpy loop)."""
    scenario = context_from_scenario(scenario)  # never the target's truth
    engine = engine or ENGINE
    tun = parse_tuning(scenario.estimator.tuning, use_dpacf)
    consider = use_dpacf and tun.dpacf_frame_error == "consider"
    refine = tun.refine_start
    # iterated update: prior attitude variance (trace) above this (0: never)
    iter_var = 3.0 * tun.iterate_sigma_rad**2
    s_t2 = (
        tun.sigma_t2_m2_s4
        if tun.sigma_t2_m2_s4 is not None
        else scenario.process_noise.translational_m2_s4
    )
    s_r2 = (
        tun.sigma_r2_rad2_s4
        if tun.sigma_r2_rad2_s4 is not None
        else scenario.process_noise.rotational_rad2_s4
    )
    n_orbit = scenario.chaser.orbit.mean_motion_rad_s if scenario.chaser.orbit else 0.0
    covered = tun.dpacf_measurement == "attitude" and tun.gate_probability is None
    if engine == "compiled" and not covered:
        raise ValueError("the compiled engine covers dpacf_measurement 'attitude' without a gate")
    fe_all = frontend(meas_list, tun)
    fe = filter_view(fe_all, tun.max_dpacf_sigma_rad)
    B, n, N = fe.usable.shape
    lay = layout(N)
    init = _initial_state(fe, tun, use_dpacf, lay, n_orbit, frame_in_P0=not consider, refine=refine)
    p_turn = np.zeros((B, n, 3))
    mu_turn = np.zeros((B, n, 3, 3))
    S_turn = np.zeros((B, n, 3, 3, 3))
    if consider and tun.branch_mixture:
        # the front end re-solves its frame every ls_every epochs and holds it in between
        every = stereo_points.FrontEndSettings().ls_every
        stat = branch_statistics(fe.R_GT[:, ::every], fe.cov_frame[:, ::every])
        p_turn, mu_turn, S_turn = (np.repeat(a, every, axis=1)[:, :n] for a in stat)
    d = lay.dim
    gate = stats.chi2.ppf(tun.gate_probability, 3) if tun.gate_probability else np.inf
    if np.isfinite(gate) and tun.dpacf_measurement == "frame":
        raise InputError(
            "estimator.tuning: gate_probability works with dpacf_measurement 'attitude' only"
        )
    dt_nom = float(np.median(np.diff(fe.t)))
    att_inflation = max(1.0, tun.attitude_corr_time_s / (dt_nom * tun.attitude_meas_every))
    if consider:  # the attitude measurement's noise: its white (G attitude) part only
        att_inflation = 0.0
    t = fe.t
    out_x = np.full((B, n, lay.nominal_dim), np.nan)
    out_P = np.full((B, -(-n // p_every), d, d), np.nan)  # epochs 0, p_every, 2 p_every, ...
    nis = np.full((B, n), np.nan)
    nis_dof = np.zeros((B, n))
    rejected = np.zeros(B, dtype=np.int64)
    diverged = np.zeros(B, dtype=bool)
    flips = np.zeros(B, dtype=np.int64)

    def pack() -> dict[str, Any]:
        return {
            "t": t,
            "x": out_x,
            "P": out_P,
            "nis": nis,
            "nis_dof": nis_dof,
            "layout": lay,
            "frontend": fe,
            "k0": init.k0,
            "rejected": rejected,
            "diverged": diverged,
            "frame_flips": flips,
            "dpacf_q_TI": fe_all.q_TI,
        }

    uniform = bool(np.allclose(np.diff(t), dt_nom, rtol=1e-9, atol=0))
    compiled_ok = covered and uniform
    if engine == "compiled" and not uniform:
        raise ValueError("the compiled engine needs a uniform time grid")
    if engine != "numpy" and compiled_ok:
        from tumblenav.estimators import _hu_kernel

        diverged = np.zeros(B, dtype=np.bool_)
        R0 = np.nan_to_num(fe.cov_TI + (att_inflation - 1.0) * fe.cov_frame)
        Pht, Qt = _translation_discrete(n_orbit, s_t2, dt_nom)  # uniform grid: one dt

        # cov_L as it is (no NaN-free copy of the largest array): the kernel reads it only where
        # ``usable``, which the triangulation sets only for finite covariances
        _hu_kernel.run_filter_kernel(
            t, fe.p_L, np.ascontiguousarray(fe.cov_L), fe.usable, fe.known_at, fe.q_TI, R0, fe.R_LI,
            init.k0, init.x0, init.P0, use_dpacf, bool(tun.first_estimates_jacobian),
            tun.attitude_meas_every, tun.flip_epochs, CONSTRAIN_EVERY, tun.constraint_curvature,
            MAX_RATE_RAD_S,
            s_r2, Pht, Qt, tun.sigma_f2_m2_s * dt_nom,
            _FLIPS, rot.matrix_to_quat(_FLIPS), p_every, _neutral_state(lay), out_x, out_P,
            nis, nis_dof, diverged, flips, consider, fe.R_GT, np.nan_to_num(fe.cov_frame), p_turn, mu_turn,
            S_turn, refine, bool(tun.attitude_update), iter_var, tun.iterate_max,
        )  # fmt: skip
        return pack()
    # the reference engine: each run folded through Hu's steps (tumblenav.estimators.base.fold)
    for b in range(B):
        steps = HuSteps(
            fe=_run_view(fe, b),
            tun=tun,
            use_dpacf=use_dpacf,
            layout=lay,
            k0=int(init.k0[b]),
            x0=init.x0[b],
            P0=init.P0[b],
            n_orbit=n_orbit,
            s_r2=s_r2,
            s_t2=s_t2,
            consider=consider,
            refine=refine,
            iter_var=iter_var,
            gate=float(gate),
            att_inflation=att_inflation,
            p_turn=p_turn[b : b + 1],
            mu_turn=mu_turn[b : b + 1],
            S_turn=S_turn[b : b + 1],
        )
        r = fold(steps, t, p_every)
        out_x[b], out_P[b], nis[b], nis_dof[b] = r.x, r.P, r.nis, r.nis_dof
        rejected[b], diverged[b] = r.rejected, r.diverged
        flips[b] = r.memo.flips if r.memo is not None else 0
    return pack()


def _run_view(fe: stereo_points.PointsFrontEnd, b: int) -> stereo_points.PointsFrontEnd:
    """Run ``b`` of a batched front end, as a batch of one (the arrays keep their run axis)."""
    B = fe.usable.shape[0]
    upd = {}
    for f in dataclasses.fields(fe):
        v = getattr(fe, f.name)
        if f.name != "t" and isinstance(v, np.ndarray) and v.ndim and v.shape[0] == B:
            upd[f.name] = v[b : b + 1]
    upd["skipped"] = {k: np.asarray(v)[b : b + 1] for k, v in fe.skipped.items()}
    view = dataclasses.replace(fe, **upd)
    view.R_LI = fe.R_LI[b : b + 1]
    return view


@dataclass(frozen=True)
class HuMemo:
    """What Hu's filter carries from epoch to epoch besides x and P (one run): the
    consecutive DPACF measurements a half turn away and the half turns followed
    (:func:`_follow_dpacf_branch`), the features' first estimates (FEJ linearisation points,
    (N, 3), NaN before), and with the 'consider' frame model the front end's frame the state
    is in and the epoch it is from."""

    votes: int
    flips: int
    f_first: Array
    R_used: Array
    k_used: int


@dataclass(frozen=True)
class HuSteps:
    """Hu 2024's EKF (eq. 36-44) as stateless steps on one run's front-end output, folded by
    :func:`tumblenav.estimators.base.fold`: the reference engine of :func:`run_filter`. The
    compiled kernel (:mod:`._hu_kernel`) is the fast fold of the same steps (tested equal on
    runs drawn at random). The arrays are those of a batch of one (leading axis 1), so that
    the batched model pieces of this module serve both."""

    fe: stereo_points.PointsFrontEnd
    tun: HuTuning
    use_dpacf: bool
    layout: StateLayout
    k0: int
    x0: Array
    P0: Array
    n_orbit: float
    s_r2: float
    s_t2: float
    consider: bool
    refine: bool
    iter_var: float
    gate: float
    att_inflation: float
    p_turn: Array
    mu_turn: Array
    S_turn: Array

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        """The start prepared by :func:`_initial_state`, at its epoch ``k0``."""
        if k != self.k0:
            return None, StepInfo()
        N = self.fe.usable.shape[2]
        memo = HuMemo(0, 0, np.full((N, 3), np.nan), self.fe.R_GT[0, k].copy(), 0)
        t = float(self.fe.t[k])
        return Belief(t, self.x0.copy(), self.P0.copy(), self.layout, memo), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        """Hu 2024 eq. 36-39: F is block diagonal, rotation (9, state dependent) and
        translation (6, constant)."""
        lay, tun = self.layout, self.tun
        sq, sw, sp = lay.nom("attitude"), lay.nom("rate"), lay.nom("inertia")
        srv = slice(lay.nom("position").start, lay.nom("velocity").stop)
        dt = t - belief.t
        x, P = belief.x[None].copy(), belief.P[None].copy()
        F = core_F(x[:, sw], x[:, sp], self.n_orbit, rotation_only=True)
        Phr, Qr = discretise(F, core_Qc(x[:, sp], self.s_r2, self.s_t2)[:, :9, :9], dt)
        Pht, Qt = _translation_discrete(self.n_orbit, self.s_t2, dt)
        q_new, w_new = propagate_rotation(x[:, sq], x[:, sw], x[:, sp], dt)
        x[:, sq], x[:, sw] = q_new, w_new
        x[:, srv] = x[:, srv] @ Pht.T
        P[:, :9, :] = Phr @ P[:, :9, :]
        P[:, 9:15, :] = Pht @ P[:, 9:15, :]
        P[:, :, :9] = P[:, :, :9] @ np.swapaxes(Phr, -1, -2)
        P[:, :, 9:15] = P[:, :, 9:15] @ Pht.T
        P[:, :9, :9] += Qr
        P[:, 9:15, 9:15] += Qt
        if tun.sigma_f2_m2_s > 0:
            sf = lay.err("features")
            P[:, sf, sf] += tun.sigma_f2_m2_s * dt * np.eye(sf.stop - sf.start)
        return dataclasses.replace(belief, t=t, x=x[0], P=P[0])

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        """Epoch ``k``'s measurements: the frame change ('consider'), the DPACF branch, the
        feature (eq. 32-35) and attitude (eq. 31) updates, iterated where the prior attitude
        is poorly known, the inertia constraint; a blown-up state is reported diverged."""
        lay, tun, fe = self.layout, self.tun, self.fe
        m = belief.memo
        x, P = belief.x[None].copy(), belief.P[None].copy()
        f_first, R_used = m.f_first[None].copy(), m.R_used[None].copy()
        k_used = np.array([m.k_used])
        votes, flips = np.array([m.votes]), np.array([m.flips])
        active, start = np.array([True]), np.array([started])
        if self.consider:
            k_used[_reframe(x, P, fe.R_GT[:, k], R_used, active, lay, f_first)] = k
        if tun.dpacf_measurement == "frame":
            use_att = "frame" if self.use_dpacf and k % tun.frame_meas_every == 0 else False
        else:
            use_att = self.use_dpacf and tun.attitude_update and (k % tun.attitude_meas_every == 0)
        # a refined start has used its epoch's measurements already (refine_start_pose)
        upd = active & ~start if self.refine else active
        if self.use_dpacf and k % tun.attitude_meas_every == 0:
            x, P, votes = _follow_dpacf_branch(
                x, P, fe.q_TI[:, k], upd, lay, votes, tun.flip_epochs, flips, f_first
            )
        if np.isfinite(self.gate):
            x, P, nis_k, dof_k, rej = _update(
                x, P, fe, k, lay, use_att, self.gate, self.att_inflation, upd
            )
        else:
            if tun.first_estimates_jacobian:
                N = f_first.shape[1]
                fnow = x[:, lay.nom("features")].reshape(1, N, 3)
                fresh = (start[:, None] & fe.known_at[:, k]) | (
                    active[:, None] & fe.usable[:, k] & ~np.isfinite(f_first[..., 0])
                )
                f_first = np.where(fresh[..., None], fnow, f_first)
            f_l = f_first if tun.first_estimates_jacobian else None
            x_pr, P_pr = x, P
            x, P, nis_k, dof_k, rej = _update_sequential(
                x_pr, P_pr, fe, k, lay, use_att, self.att_inflation, upd, f_lin=f_l
            )
            # iterated update where the prior attitude is poorly known (after a gap)
            its = upd & (
                np.trace(P_pr[:, lay.err("attitude"), lay.err("attitude")], axis1=-2, axis2=-1)
                > self.iter_var
            )
            if self.iter_var > 0 and its.any():
                for _ in range(tun.iterate_max):
                    x2, P2, nis2, _dof2, _r = _update_sequential(
                        x_pr, P_pr, fe, k, lay, use_att, self.att_inflation, upd, f_lin=f_l,
                        x_lin=x,
                    )  # fmt: skip
                    x = np.where(its[:, None], x2, x)
                    P = np.where(its[:, None, None], P2, P)
                    nis_k = np.where(its, nis2, nis_k)
        if started or k % CONSTRAIN_EVERY == 0:
            x, P = constrain_inertia(x, P, lay, active, curvature=tun.constraint_curvature)
        memo = HuMemo(int(votes[0]), int(flips[0]), f_first[0], R_used[0], int(k_used[0]))
        out = dataclasses.replace(belief, x=x[0], P=P[0], memo=memo)
        if _diverged(x, P, lay)[0]:
            return out, StepInfo(diverged=True)
        return out, StepInfo(float(nis_k[0]), int(dof_k[0]), int(rej[0]))

    def report(self, belief: Belief, k: int) -> Array:
        """The covariance reported: with the 'consider' frame model it also holds the
        frame's own error and half turns (:func:`frame_consider_cov`)."""
        if not self.consider:
            return belief.P
        ku = (np.array([0]), np.array([belief.memo.k_used]))
        return frame_consider_cov(
            belief.x[None], belief.P[None], self.fe.cov_frame[ku], self.layout,
            self.p_turn[ku], self.mu_turn[ku], self.S_turn[ku],
        )[0]  # fmt: skip


_FLIPS = np.array(
    [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
)


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
):
    """Apply ``c(p) = 0`` as a (nearly) perfect scalar pseudo-measurement (Simon 2010, "estimate
    projection" by a Kalman update) and keep every ratio inside |p_i| < 1 (triangle inequality).
    Runs where ``active`` is False are left alone.

    With ``curvature`` (beyond Hu 2024), the variance along the constraint gradient is then
    set back to what the surface's curvature leaves (:func:`curvature_variance`): applied
    again and again as a perfect measurement it would shrink to ``r / n`` while the true
    error across the tangent plane is of the order of the tangent variance times the
    curvature (measured: z-scores of 500 along the gradient, docs/results/hu2024.md)."""
    sp = lay.nom("inertia")
    ep = lay.err("inertia")
    c, g = inertia_constraint(x[:, sp], jac=True)
    if active is not None:
        c = np.where(active, c, 0.0)
        g = g * active[:, None]
    PH = (P[:, :, ep] @ g[..., None])[..., 0]  # P H^T, H nonzero on the p block only
    s = np.sum(g * PH[:, ep], axis=1) + r
    K = PH / s[:, None]
    x = lay.boxplus(x, -K * c[:, None])
    P = P - K[:, :, None] * PH[:, None, :]
    clip = np.clip(x[:, sp], -0.999, 0.999)
    x[:, sp] = clip if active is None else np.where(active[:, None], clip, x[:, sp])
    if curvature:
        _, g1 = inertia_constraint(x[:, sp], jac=True)
        v = curvature_variance(x[:, sp], P[:, ep, ep])
        n = g1 / np.sum(g1 * g1, axis=1, keepdims=True)  # g1 . (v n n^T) . g1 = v
        add = v[:, None, None] * n[:, :, None] * n[:, None, :]
        if active is not None:
            add = add * active[:, None, None]
        P[:, ep, ep] += add
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


def _neutral_state(lay: StateLayout) -> Array:
    x = np.zeros(lay.nominal_dim)
    x[lay.nom("attitude")] = rot.IDENTITY
    return x


def _update(x, P, fe, k, lay, use_att, gate, att_inflation, active):
    """One batched measurement update at epoch k (Hu 2024 eq. 40-44).

    All visible feature blocks (eq. 32-35) and the DPACF attitude (eq. 31) are processed
    together; the sparsity of H is used so that the cost is O(d^2 m), not O(d^3).
    Covariance: the Joseph form of eq. 41, ``(I-KH)P(I-KH)^T + K R K^T``, equals
    ``P - (HP)^T S^-1 (HP)`` for the optimal gain of eq. 42 (expand it and use
    ``K S = P H^T``); that expression is evaluated (symmetrised), which avoids the two
    O(d^3) products. Rows of measurements that are missing (or runs not started) are
    zeroed, so they change nothing.
    """
    B, N = fe.usable.shape[0], fe.usable.shape[2]
    d = lay.dim
    m = 3 + 3 * N
    sa, sr = lay.err("attitude"), lay.err("position")
    sf0 = lay.err("features").start
    q = x[:, lay.nom("attitude")]
    f = x[:, lay.nom("features")].reshape(B, N, 3)
    R_LT = fe.R_LI[:, k] @ np.swapaxes(rot.quat_to_matrix(q), -1, -2)
    Hth = R_LT[:, None] @ rot.skew(f)  # (B,N,3,3): dy_i/dtheta = R_LT [f_i x]
    y_hat = x[:, None, lay.nom("position")] + f @ np.swapaxes(R_LT, -1, -2)
    u = fe.usable[:, k] & active[:, None]
    ok0 = np.all(np.isfinite(fe.q_TI[:, k]), axis=-1) & active & use_att
    rows = np.concatenate([np.repeat(ok0[:, None], 3, 1), np.repeat(u, 3, axis=1)], axis=1)
    # innovations
    nu = np.zeros((B, m))
    q_hat = x[:, lay.nom("attitude")]
    qm = np.where(ok0[:, None], fe.q_TI[:, k], q_hat)
    nu[:, :3] = rot.boxminus(qm, q_hat)
    nu[:, 3:] = (np.nan_to_num(fe.p_L[:, k]) - y_hat).reshape(B, -1)
    nu *= rows
    # H P, using the structure of H
    Pth = P[:, sa, :]
    HPf = Hth @ Pth[:, None] + P[:, None, sr, :] + R_LT[:, None] @ P[:, sf0:, :].reshape(B, N, 3, d)
    HP = np.concatenate([Pth, HPf.reshape(B, 3 * N, d)], axis=1) * rows[..., None]
    # S = H P H^T + R, again from the structure of H (columns: attitude, then features)
    HPth, HPr = HP[:, :, sa], HP[:, :, sr]
    S_f = HPth @ np.transpose(Hth, (0, 3, 1, 2)).reshape(B, 3, 3 * N)
    S_f += np.tile(HPr, (1, 1, N))
    S_f += _feature_cols(HP[:, :, sf0:], R_LT, B, m, N)
    S = np.concatenate([HPth, S_f], axis=2)
    Rm = np.zeros((B, m, m))
    if use_att:
        R0 = np.nan_to_num(fe.cov_TI[:, k] + (att_inflation - 1.0) * fe.cov_frame[:, k])
        Rm[:, :3, :3] = R0
    covL = np.nan_to_num(fe.cov_L[:, k])
    for i in range(N):
        Rm[:, 3 + 3 * i : 6 + 3 * i, 3 + 3 * i : 6 + 3 * i] = covL[:, i]
    both = rows[:, :, None] & rows[:, None, :]
    S = np.where(both, S + Rm, 0.0) + (~rows)[:, :, None] * np.eye(m)
    keep_blocks = rows[:, ::3].copy()
    rejected = np.zeros(B, dtype=np.int64)
    if np.isfinite(gate):  # per-block chi-square gate on the innovations (optional)
        Sb = np.stack([S[:, 3 * j : 3 * j + 3, 3 * j : 3 * j + 3] for j in range(N + 1)], 1)
        nb = nu.reshape(B, N + 1, 3)
        d2 = np.einsum("bji,bji->bj", nb, np.linalg.solve(Sb, nb[..., None])[..., 0])
        reject = keep_blocks & (d2 > gate)
        if reject.any():
            keep_blocks &= ~reject
            rejected = reject.sum(axis=1)
            rows = np.repeat(keep_blocks, 3, axis=1)
            both = rows[:, :, None] & rows[:, None, :]
            S = np.where(both, S, 0.0) + (~rows)[:, :, None] * np.eye(m)
            HP = HP * rows[..., None]
            nu = nu * rows
    sol = np.linalg.solve(S, np.concatenate([HP, nu[..., None]], axis=2))
    Kt, Sinv_nu = sol[..., :d], sol[..., d]  # S^-1 H P (= K^T) and S^-1 nu
    dx = (nu[:, None, :] @ Kt)[:, 0]  # K nu, eq. 40
    P_new = P - np.swapaxes(HP, -1, -2) @ Kt  # eq. 41 for the optimal gain (see above)
    P_new = 0.5 * (P_new + np.swapaxes(P_new, -1, -2))
    x_new = lay.boxplus(x, dx)  # eq. 43-44
    nis_k = np.sum(nu * Sinv_nu, axis=1)
    return x_new, P_new, nis_k, 3 * keep_blocks.sum(axis=1), rejected


def _inv3(S: Array) -> tuple[Array, Array]:
    """Inverse and determinant of stacks of 3x3 matrices by cofactors (vectorised, no LAPACK
    call per matrix: the batched solve dominated the update's cost)."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    d, e, f = S[..., 1, 0], S[..., 1, 1], S[..., 1, 2]
    g, h, i = S[..., 2, 0], S[..., 2, 1], S[..., 2, 2]
    A, B_, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B_ + c * C
    adj = np.stack(
        [
            np.stack([A, -(b * i - c * h), b * f - c * e], -1),
            np.stack([B_, a * i - c * g, -(a * f - c * d)], -1),
            np.stack([C, -(a * h - b * g), a * e - b * d], -1),
        ],
        -2,
    )
    return adj / det[..., None, None], det


def frame_measurement(f: Array, g: Array, use: NDArray[np.bool_], jac: bool = False):
    """The rotation ``R_TG`` between the filter's features in T and their template in G.

    ``f`` (B,N,3) features in T, ``g`` (B,N,3) template in G, ``use`` (B,N). Least-squares
    rigid alignment (Kabsch) of the centred sets. With ``jac``, also ``dphi/df_i`` (B,N,3,3)
    for the rotation error ``R_TG = Exp(dphi) R_TG_hat`` (in T): with ``b_i`` the centred
    template rotated into T and ``M = sum (|b_i|^2 I - b_i b_i^T)``,
    ``dphi/df_i = M^-1 [b_i x]`` (centring cancels because ``sum b_i = 0``).
    """
    w = use.astype(float)
    n = np.maximum(w.sum(axis=1), 1.0)[:, None]
    fc = np.nan_to_num(f) - (w[..., None] * np.nan_to_num(f)).sum(1)[:, None] / n[..., None]
    gc = np.nan_to_num(g) - (w[..., None] * np.nan_to_num(g)).sum(1)[:, None] / n[..., None]
    fc, gc = fc * w[..., None], gc * w[..., None]
    Hm = np.swapaxes(gc, -1, -2) @ fc  # sum g f^T
    U, _, Vt = np.linalg.svd(Hm)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros_like(Hm)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    R_TG = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    if not jac:
        return R_TG, None
    b = gc @ np.swapaxes(R_TG, -1, -2)
    M = np.sum(w * np.sum(b * b, -1), 1)[:, None, None] * np.eye(3) - np.swapaxes(b, -1, -2) @ b
    Minv, _ = _inv3(M)
    J = (Minv[:, None] @ rot.skew(b)) * w[..., None, None]
    return R_TG, J


def _update_sequential(x, P, fe, k, lay, use_att, att_inflation, active, f_lin=None, x_lin=None):
    """The update of :func:`_update` processed block by block (DPACF attitude, then each
    feature), all linearised at the prior, or at ``x_lin`` (an iterate of the iterated
    update: each innovation then adds ``H (x_lin boxminus x)``): for independent
    measurement blocks this equals the batch update exactly, and it needs only 3x3
    inverses."""
    B, N = fe.usable.shape[0], fe.usable.shape[2]
    sa, sr = lay.err("attitude"), lay.err("position")
    sf0 = lay.err("features").start
    xl = x if x_lin is None else x_lin
    q_hat = xl[:, lay.nom("attitude")]
    f = xl[:, lay.nom("features")].reshape(B, N, 3)
    R_LT = fe.R_LI[:, k] @ np.swapaxes(rot.quat_to_matrix(q_hat), -1, -2)
    R_TL = np.swapaxes(R_LT, -1, -2)
    # dy_i/dtheta = R_LT [f_i x]; optionally at the features' first estimates (FEJ)
    Hth = R_LT[:, None] @ rot.skew(f if f_lin is None else np.where(np.isfinite(f_lin), f_lin, f))
    HthT = np.swapaxes(Hth, -1, -2)
    y_hat = xl[:, None, lay.nom("position")] + f @ R_TL
    if x_lin is not None:  # + H delta, delta = x_lin boxminus x
        dl = lay.boxminus(x_lin, x)
        dlf = dl[:, sf0:].reshape(B, N, 3)
        y_hat = y_hat - (Hth @ dl[:, None, sa, None])[..., 0] - dl[:, None, sr] - dlf @ R_TL
    u = fe.usable[:, k] & active[:, None]
    nu_f = np.where(u[..., None], np.nan_to_num(fe.p_L[:, k]) - y_hat, 0.0)
    covL = np.nan_to_num(fe.cov_L[:, k])
    dx = np.zeros((B, lay.dim))
    nis = np.zeros(B)
    eye3 = np.eye(3)

    def absorb(HP, S, nu, ok):
        nonlocal P, dx, nis
        HP = HP * ok[:, None, None]
        S = np.where(ok[:, None, None], S, eye3)
        Sinv, _ = _inv3(S)
        Kt = Sinv @ HP  # (B,3,d) = K^T
        nu = nu * ok[:, None]
        dx += (nu[:, None, :] @ Kt)[:, 0]
        P = P - np.swapaxes(HP, -1, -2) @ Kt
        nis += np.sum(nu * (Sinv @ nu[..., None])[..., 0], axis=1)

    if use_att == "frame":  # DPACF frame R_TG against the filter's own features
        use = fe.known_at[:, k] & active[:, None]
        ok0 = np.all(np.isfinite(fe.R_GT[:, k]), axis=(-1, -2)) & (use.sum(1) >= 3) & active
        R_hat, J = frame_measurement(f, fe.template_at(k), use, jac=True)
        R_meas = np.swapaxes(np.where(ok0[:, None, None], fe.R_GT[:, k], np.eye(3)), -1, -2)
        nu0 = rot.log_map(R_meas @ np.swapaxes(R_hat, -1, -2))
        if x_lin is not None:  # + H delta (R_hat and J at x_lin's features)
            nu0 = nu0 + np.einsum("bnij,bnj->bi", J, dlf)
        HP = np.zeros((B, 3, lay.dim))
        Hdx = np.zeros((B, 3))
        for i in range(N):
            fi = slice(sf0 + 3 * i, sf0 + 3 * i + 3)
            HP += J[:, i] @ P[:, fi, :]
        S = np.zeros((B, 3, 3))
        for i in range(N):
            fi = slice(sf0 + 3 * i, sf0 + 3 * i + 3)
            S += HP[:, :, fi] @ np.swapaxes(J[:, i], -1, -2)
        R0 = np.nan_to_num(fe.cov_frame[:, k]) * att_inflation
        absorb(HP, S + R0, nu0 - Hdx, ok0)
    elif use_att:
        ok0 = np.all(np.isfinite(fe.q_TI[:, k]), axis=-1) & active
        qm = np.where(ok0[:, None], fe.q_TI[:, k], q_hat)
        R0 = np.nan_to_num(fe.cov_TI[:, k] + (att_inflation - 1.0) * fe.cov_frame[:, k])
        HP = P[:, sa, :]
        nu0 = rot.boxminus(qm, q_hat) + (0.0 if x_lin is None else dl[:, sa])
        absorb(HP, HP[:, :, sa] + R0, nu0 - dx[:, sa], ok0)
    else:
        ok0 = np.zeros(B, dtype=bool)
    for i in range(N):
        fi = slice(sf0 + 3 * i, sf0 + 3 * i + 3)
        HP = Hth[:, i] @ P[:, sa, :] + P[:, sr, :] + R_LT @ P[:, fi, :]
        S = HP[:, :, sa] @ HthT[:, i] + HP[:, :, sr] + HP[:, :, fi] @ R_TL + covL[:, i]
        Hdx = (Hth[:, i] @ dx[:, sa, None])[..., 0] + dx[:, sr] + (R_LT @ dx[:, fi, None])[..., 0]
        absorb(HP, S, nu_f[:, i] - Hdx, u[:, i])
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    dof = 3 * (ok0.astype(int) + u.sum(axis=1))
    return lay.boxplus(x, dx), P, nis, dof, np.zeros(B, dtype=np.int64)


def _feature_cols(HPf_cols: Array, R_LT: Array, B: int, m: int, N: int) -> Array:
    """``(HP)[:, :, f_j] R_LT^T`` for every feature j: (B, m, 3N)."""
    X = HPf_cols.reshape(B, m * N, 3) @ np.swapaxes(R_LT, -1, -2)
    return X.reshape(B, m, 3 * N)


def filter_view(
    fe: stereo_points.PointsFrontEnd, max_sigma_rad: float
) -> stereo_points.PointsFrontEnd:
    """The front end as the filter uses it: DPACF frames (attitude measurement, frame, moments)
    only where the frame's 1-sigma (largest axis) is below ``max_sigma_rad``. The front end
    itself reports them from ``dpacf_emit_sigma_rad`` on (Hu 2024 Fig. 5)."""
    # frames are re-solved every ls_every epochs and held in between: test the solved ones
    every = stereo_points.FrontEndSettings().ls_every
    n = fe.cov_frame.shape[1]
    C = np.nan_to_num(fe.cov_frame[:, ::every], nan=1e6)
    sig = np.repeat(np.sqrt(np.linalg.eigvalsh(C)[..., -1]), every, axis=1)[:, :n]
    keep = sig < max_sigma_rad
    view = dataclasses.replace(
        fe,
        q_TI=np.where(keep[..., None], fe.q_TI, np.nan),
        cov_TI=np.where(keep[..., None, None], fe.cov_TI, np.nan),
        cov_frame=np.where(keep[..., None, None], fe.cov_frame, np.nan),
        cov_ratios=np.where(keep[..., None, None], fe.cov_ratios, np.nan),
        R_GT=np.where(keep[..., None, None], fe.R_GT, np.nan),
        moments=np.where(keep[..., None], fe.moments, np.nan),
    )
    view.R_LI = fe.R_LI
    return view


def frontend(meas_list, tun: HuTuning) -> stereo_points.PointsFrontEnd:
    """The stereo-points front end on B runs, with the settings ``tun.frontend``."""
    fe = tun.frontend
    out = stereo_points.process(
        meas_list,
        stereo_points.FrontEndSettings(
            rate_half_window=fe.rate_half_window,
            min_ls_epochs=fe.min_ls_epochs,
            max_dpacf_sigma_rad=max(fe.dpacf_emit_sigma_rad, tun.max_dpacf_sigma_rad),
            g_fit=fe.g_attitude_fit,
            template_refine_s=tuple(np.atleast_1d(np.asarray(fe.template_refine_s, float))),
            unbiased_last=fe.ls_unbiased_rates,
        ),
    )
    out.R_LI = rot.quat_to_matrix(np.stack([m.q_LI for m in meas_list]))
    return out


ENGINE: Literal["auto", "numpy", "compiled"] = "auto"  # default of run_filter(engine=None)
# A rate estimate above one turn per second is a filter that blew up: ten times the fastest
# tumble reported for malfunctioning spacecraft (36 deg/s, Hu 2024 Sec. 5 citing [27]).
MAX_RATE_RAD_S = 2 * np.pi
CONSTRAIN_EVERY = 10  # epochs between projections onto the inertia constraint


class HuEKF:
    """Shared implementation of ekf-dpacf and ekf-baseline."""

    consumes = (STEREO_TRACKS,)  # the measurement types it runs on
    needs = "stereo feature tracks (stereo sensor)"
    compiled = True  # numba kernels: campaigns warm them up before forking their workers

    def __init__(self, use_dpacf: bool) -> None:
        self.use_dpacf = use_dpacf
        self.name = "ekf-dpacf" if use_dpacf else "ekf-baseline"
        self.description = (
            "Hu 2024: inertia least squares + unique principal frame (DPACF) + error-state EKF"
            if use_dpacf
            else "Hu 2024's EKF without DPACF (principal frame free, Aghili & Parsa 2009)"
        )

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        if scenario.sensor.kind != "stereo":
            raise InputError(
                f"{self.name} needs a stereo sensor; scenario {scenario.name} has "
                f"a {scenario.sensor.kind} sensor"
            )
        parse_tuning(scenario.estimator.tuning, self.use_dpacf)

    def run(self, scenario: Any, measurements: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        self.check(scenario)
        return histories(run_filter(scenario, [measurements], self.use_dpacf), scenario)[0]

    def run_batch(
        self, scenario: Any, measurements: list, rngs: list, p_every: int = 1
    ) -> list[EstimateHistory]:
        """Many runs at once (vectorised); the same histories as :meth:`run`, with the
        covariance reported every ``p_every`` epochs (NaN in between)."""
        scenario = context_from_scenario(scenario)  # never the target's truth
        self.check(scenario)
        res = run_filter(scenario, measurements, self.use_dpacf, p_every=p_every)
        return histories(res, scenario)


def histories(res: dict[str, Any], scenario: Any) -> list[EstimateHistory]:
    """One :class:`EstimateHistory` per run of a :func:`run_filter` result."""
    fe = res["frontend"]
    max_sigma = parse_tuning(scenario.estimator.tuning).max_dpacf_sigma_rad
    out = []
    for b in range(res["x"].shape[0]):
        skipped = {k: int(v[b]) for k, v in fe.skipped.items()}
        skipped["gated_out"] = int(res["rejected"][b])
        skipped["diverged"] = int(res["diverged"][b])
        skipped["frame_flips"] = int(res["frame_flips"][b])
        k0 = res["k0"][b]
        out.append(
            EstimateHistory(
                t=res["t"],
                x=res["x"][b],
                P=res["P"][b],
                P_every=-(-len(res["t"]) // res["P"].shape[1]),
                layout=res["layout"],
                nis=res["nis"][b],
                nis_dof=res["nis_dof"][b],
                skipped=skipped,
                info={
                    "convention": "hu2024",  # the run's DPACF frame: evaluation.alignment
                    "template_G": fe.template_G[b],
                    "known": fe.known[b],
                    "start_time_s": float(res["t"][k0]) if k0 >= 0 else None,
                    "dpacf_q_TI": res["dpacf_q_TI"][b],
                    "start_condition": (
                        "(the DPACF frame never reached a 1-sigma below max_dpacf_sigma_rad = "
                        f"{max_sigma} rad; epochs with >= 3 triangulated features: "
                        f"{int((fe.usable[b].sum(axis=1) >= 3).sum())} of {len(fe.t)})"
                    ),
                },
            )
        )
    return out


register("ekf-dpacf")(lambda: HuEKF(True))
register("ekf-baseline")(lambda: HuEKF(False))
