"""Kabir 2025 UKF settings (:class:`KabirTuning`) and the paper's per-frequency tuning (Sec. 3.2)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from tumblenav.errors import InputError
from tumblenav.estimators.base import nest_front_end_keys
from tumblenav.estimators.base import parse_tuning as base_parse_tuning
from tumblenav.frontends import projections as proj
from tumblenav.frontends.projections import ProjectionsTuning
from tumblenav.settings_rules import positive_or_rule

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


# Kabir 2025 Sec. 3.2, per tumbling frequency f_T (Hz): Q of omega (rad^2/s^2), Q of each
# quaternion component, and sigma_o of the optical flow (rad/s).
_PAPER_PER_FREQUENCY = {
    0.025: (2.5e-9, 4e-10, 1e-5),
    0.075: (2.5e-7, 4e-8, 5e-4),
    0.125: (2.5e-5, 4e-6, 5e-4),
    0.175: (2.5e-5, 4e-6, 1e-3),
}


class KabirTuning(BaseModel):
    """``estimator.tuning`` keys of ukf / ukf-mult (defaults: Kabir 2025 Sec. 3.2 for
    f_T = 0.025 Hz; use :func:`paper_tuning` for the other frequencies). The known mass
    centre, ``mass_centre_L_m``, is required: Kabir 2025 assumes it."""

    model_config = ConfigDict(extra="forbid")
    mass_centre_L_m: list[float] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="the target's mass-centre position at t = 0 in L (= I), m: Kabir 2025 "
        "Sec. 2.1 assumes it known; required (the estimator never reads the target's truth)",
    )
    mass_centre_velocity_L_m_s: list[float] = Field(
        [0.0, 0.0, 0.0],
        min_length=3,
        max_length=3,
        description="its constant velocity in L, m/s (Kabir 2025: an inertially fixed CM)",
    )
    init: Literal["identified", "triangulated", "given"] = Field(
        "identified",
        description="'identified' (tumblenav default): from the measurements alone -- the "
        "feature set's attitude by Kabsch on triangulated points, its rate, the inertia and "
        "principal frame by Hu 2024 eq. 13's least squares over a window grown until the frame "
        "is known to init_frame_sigma_rad; the filter starts at the end of that window with "
        "the identification's own covariance; 'triangulated': at t0 with q = identity, features "
        "triangulated, omega from the optical flow, k = 0 (the frame is unknown: "
        "init_attitude_sigma_rad); 'given': init_omega_rad_s, init_q_TI, init_features_m "
        "(the kabir2025 recipe gives Kabir 2025 Sec. 3.2's truth-based guess this way: "
        "tumblenav.papers.kabir2025.paper_start)",
    )
    init_frame_sigma_rad: float = Field(
        0.05,
        gt=0,
        description="'identified' start: the window grows until the principal frame's 1-sigma "
        "(largest axis) is below this (rad)",
    )
    init_max_window_s: float | None = Field(
        None,
        gt=0,
        description="'identified' start: the longest window (s); default: the first run of "
        "observations",
    )
    init_rate_lag: int | None = Field(
        None,
        ge=1,
        le=50,
        description="'identified' start: the rates of the feature set are central differences "
        "of its attitudes over +- this many epochs; default (null): the fewest that bring the "
        "rate's noise (from the attitudes' scatter about the rigid template) below 1 % of the "
        "rate, at most 0.8 rad of tumble per epoch of half-width (1 on every built-in and table "
        "scenario; 2 at 30 m, 3 at ten times the paper's pixel noise)",
    )
    init_attitude_sigma_rad: float = Field(
        1.0,
        gt=0,
        description="'triangulated' start: 1-sigma of the attitude (per axis, rad): q = "
        "identity knows nothing of the principal frame (the features' covariance follows it)",
    )
    init_omega_rad_s: list[float] = Field(
        [0.0, 0.0, 0.0], min_length=3, max_length=3, description="given init: omega_TI_T"
    )
    init_q_TI: list[float] = Field(
        [0.0, 0.0, 0.0, 1.0], min_length=4, max_length=4, description="given init: [x,y,z,w]"
    )
    init_features_m: list[list[float]] = Field(
        [], description="given init: each feature's position in T, m (one [x, y, z] each)"
    )
    alpha: float = Field(0.1, gt=0, le=1, description="unscented spread (Sec. 3.2)")
    beta: float = Field(2.0, ge=0, description="unscented transform (Sec. 3.2)")
    kappa: float = Field(0.0, description="unscented transform (Sec. 3.2)")
    p0_omega_var: float = Field(0.1225, gt=0, description="rad^2/s^2")
    p0_quat_var: float = Field(0.04, gt=0, description="per quaternion component")
    p0_k_var: float = Field(0.01, gt=0, description="initial variance of each log-ratio k")
    p0_feature_var: float = Field(2.25, gt=0, description="m^2")
    q_omega_var: float | list[float] | None = Field(
        None,
        description="rad^2/s^2 per step: one number for every axis (Kabir 2025 Sec. 3.2), or "
        "three, one per principal axis of T (x, y, z); default (null): derived per axis from "
        "the scenario's process_noise.rotational_rad2_s4, the estimated inertia ratios and "
        "the sample interval (derive_tuning: q_r (I_max/I_i)^2 dt, the isotropic torque's "
        "rate walk about each axis)",
    )
    q_quat_var: float | None = Field(
        None,
        ge=0,
        description="per quaternion component per step; default (null): derived (derive_tuning)",
    )
    q_k_var: float | None = Field(
        None,
        ge=0,
        description="per step; default (null): derived, 0 (the inertia of a rigid body is "
        "constant; Kabir 2025 Sec. 3.2 tunes 3.6e-5: paper_tuning)",
    )
    q_feature_var: float | None = Field(
        None,
        ge=0,
        description="m^2 per step; default (null): derived, 0 (the features of a rigid body "
        "do not move in T; Kabir 2025 Sec. 3.2 tunes 1e-6: paper_tuning)",
    )
    flow_model: Literal["stencil", "instantaneous"] = Field(
        "stencil",
        description="what the filter predicts for a measured flow: 'stencil' (tumblenav "
        "default) eq. 27's five-point stencil of the projections predicted at t +- dt, "
        "+- 2 dt by the torque-free model, so that eq. 27's truncation error is modelled; "
        "'instantaneous' (Kabir 2025 eq. 22-23) the flow A omega at t, eq. 27's truncation "
        "error then counted in sigma_o",
    )
    use_disparity: bool = Field(
        False,
        description="update with the disparity u_L - u_R (Kabir 2025 eq. 22) as a fifth "
        "independent component; default False (tumblenav): it is the difference of the two "
        "measured projections already used, so counting it as independent noise "
        "over-weights the depth (paper_tuning sets True)",
    )
    sigma_p_rad: float | Literal["sensor"] = Field(
        "sensor",
        description="projection noise sigma_p (rad, Kabir 2025 eq. 24); 'sensor': the "
        "measurements' noise_px / focal_px (left camera)",
    )
    sigma_d_rad: float | Literal["sigma_p"] = Field(
        "sigma_p", description="disparity noise (rad); 'sigma_p': the same as sigma_p_rad"
    )
    sigma_flow_rad_s: float | None = Field(
        None,
        gt=0,
        description="optical flow noise sigma_o (rad/s); default (null): derived from the "
        "sensor noise through eq. 27 and eq. 27's truncation error at the estimator's own "
        "initial rate and geometry (derive_tuning); the paper's per-frequency values: "
        "paper_tuning",
    )
    frontend: ProjectionsTuning = Field(
        default_factory=ProjectionsTuning,
        description="the projections front end's settings (ProjectionsTuning)",
    )
    gate_probability: float | None = Field(
        None, gt=0, lt=1, description="per-feature chi-square innovation gate; default: none"
    )
    coast_covariance: Literal["cubature", "linearised"] = Field(
        "cubature",
        description="the covariance while no feature is measured (a coast): 'cubature', "
        "the third-degree spherical-radial rule's points (Arasaratnam & Haykin 2009: +- "
        "sqrt(d) columns of sqrt(P), equal weights) propagated about the propagated centre "
        "point, which follows the spread of the polhode phase a long coast builds "
        "(tumblenav, issue 18: ukf in kabir_paper's 1500-s loss NEES/dof 4.3 -> 1.0 over 4 "
        "runs); 'linearised': the unscented points at alpha's spread, i.e. the linearised "
        "propagation (the former default). Either way the rigid parameters get no process "
        "noise in a coast (nothing updates them)",
    )

    update_chart: Literal["world", "body"] = Field(
        "world",
        description="the chart of the measurement update: 'world' (tumblenav default, issue "
        "18) the rate and features turned into I for the update, where the projections do "
        "not depend on the attitude, so that the principal frame against the feature set is "
        "learnt from the Euler dynamics only; 'body' (Kabir 2025) the filter's own chart, "
        "rate and features in T",
    )
    relabel_axes: bool = Field(
        True,
        description="after each update, relabel the principal axes whose estimated moments "
        "are confidently (3 sigma) not ascending (filter.canonical_axes; tumblenav default, "
        "issue 18: one labelling, so that the evaluation compares every run in one frame). "
        "False: Kabir 2025's filter, which keeps the start's labelling (reproduce): from the "
        "paper's k = 0 start at 0.025 Hz the moments cross while k is learnt, and each "
        "relabelling is a jump between symmetric frames within a run (benchmark, 20 runs: "
        "attitude RMSE 59.6 deg with it, 13.7 deg without, as before issue 18)",
    )
    covariance_report: Literal["actual", "filter"] = Field(
        "actual",
        description="ukf / ukf-mult: the covariance the history reports; the estimate is the "
        "same either way. 'actual' (tumblenav default, issue 18): the UKF's covariance mapped "
        "(T P T^T, positive definite; in a coast the rigid block only) onto the actual "
        "error's covariance under the filter's gains, from a covariance analysis of the "
        "mismatched filter (Gelb 1974 Sec. 7.2; kabir2025.mismatch.actual_covariance): the "
        "features' and k's Q floor is a random "
        "walk the rigid truth lacks (the filter's own covariance of the features is about "
        "twice their error's), eq. 27's flow reuses the projections' noise, and the stencil "
        "sees the truth's torque over +- 2 dt as a rate error common to every feature. "
        "'filter': the UKF's own covariance. Measured, 20 runs each, 'filter' -> 'actual' "
        "(python benchmarks/consistency.py -o OUT --workers 1 --only kabir_geometry_ukf,"
        "kabir_paper_ukf,kabir_rate005_ukf,kabir_inertia_ukf and the _mult cases): NEES/dof "
        "kabir_geometry_observed 0.705 -> 1.02 [0.893, 1.11] (ukf and ukf-mult), "
        "kabir_rate005_observed 0.939 -> 1.04, kabir_inertia_observed 0.968 -> 0.996, "
        "kabir_paper_observed 1.07 -> 1.15 [0.875, 1.13] (its rate and attitude are "
        "over-confident, 1.7 and 2.2, which the features' 0.79 hid; the analysis does not "
        "explain it); NIS and RMSE unchanged; in the loss of every feature (kabir_*_occl_ukf) "
        "geometry 0.716 -> 1.02, rate005 0.773 -> 0.997, inertia 0.687 -> 0.851, paper "
        "1.18 -> 1.34. Per block on kabir_geometry_observed (python "
        "benchmarks/block_nees.py SCENARIO ukf --seeds 0,...,19): features 0.58 -> 1.01, "
        "inertia 0.62 -> 1.14, rate 1.17 -> 1.12, attitude 1.12 -> 1.15 ('filter' on seeds "
        "0-9). With 'actual' the NIS too is against the innovations' actual covariance from "
        "the same analysis (twenty-fourth session: the flows reuse projections the "
        "prediction has seen, so the filter's own NIS/dof is expected at ~0.91; the 14 "
        "observed rows 0.90-0.98 -> 0.999-1.00), the filter's own in the history's "
        "info['nis_filter']. ukf-gp reports its own (ukf_gp.rigid_floor_correction) and the "
        "filter's NIS",
    )

    @field_validator("q_omega_var")
    @classmethod
    def _per_axis(cls, v: float | list[float] | None) -> float | list[float] | None:
        """A non-negative number, or three (one per axis)."""
        if v is None:
            return v
        vals = [v] if isinstance(v, (int, float)) else list(v)
        if not (len(vals) in (1, 3) and all(np.isfinite(x) and x >= 0 for x in vals)):
            raise ValueError("must be a non-negative number or a list of three (x, y, z)")
        return v

    @field_validator("sigma_p_rad", "sigma_d_rad", mode="before")
    @classmethod
    def _number_or_rule(cls, v: Any, info: ValidationInfo) -> Any:
        """A positive number, or the rule named by the default (``null``, the former default,
        means the rule too)."""
        assert info.field_name is not None  # a field validator's info names its field
        return positive_or_rule(v, cls.model_fields[info.field_name].default)

    @model_validator(mode="before")
    @classmethod
    def _front_end_keys(cls, raw: Any) -> Any:
        """Front-end keys given at the top level (as before they moved) go to ``frontend``."""
        return nest_front_end_keys(raw, ProjectionsTuning)


def parse_tuning(raw: dict[str, Any] | None, model: type[KabirTuning] = KabirTuning) -> KabirTuning:
    """Validate ``estimator.tuning``; InputError naming the key on unknown keys / bad values."""
    return base_parse_tuning(raw, model)


# Kabir 2025 Sec. 3.2, every frequency: Q of each log-ratio k and of each feature coordinate
_PAPER_Q_K, _PAPER_Q_FEATURE = 3.6e-5, 1e-6


def paper_tuning(f_T_hz: float) -> dict[str, Any]:
    """Kabir 2025 Sec. 3.2's per-frequency tuning: ``q_omega_var``, ``q_quat_var``,
    ``sigma_flow_rad_s`` for f_T in 0.025, 0.075, 0.125, 0.175 Hz, with the paper's
    ``q_k_var``, ``q_feature_var`` and its observation model (the instantaneous flow, the
    disparity as a fifth component, the update in the filter's own body chart, the start's
    labelling of the principal axes kept)."""
    for f, (qw, qq, so) in _PAPER_PER_FREQUENCY.items():
        if abs(f_T_hz - f) < 1e-6:
            return {
                "q_omega_var": qw,
                "q_quat_var": qq,
                "sigma_flow_rad_s": so,
                "q_k_var": _PAPER_Q_K,
                "q_feature_var": _PAPER_Q_FEATURE,
                "flow_model": "instantaneous",
                "use_disparity": True,
                "update_chart": "body",
                "relabel_axes": False,
            }
    raise InputError(
        f"Kabir 2025 tunes only f_T = {', '.join(map(str, _PAPER_PER_FREQUENCY))} Hz; "
        f"got {f_T_hz:g} Hz"
    )


# --- tuning that follows the scenario (tumblenav default; issue 18) -------------------------

# Kabir 2025 eq. 27's five-point stencil applied to independent samples of noise sigma_p:
# var = sigma_p^2 (1 + 64 + 64 + 1) / (144 dt^2).
_STENCIL_NOISE_GAIN = np.sqrt(130.0 / 144.0)
# The features' (and k's) process-noise floor: a tenth of the sensor's resolution per step.
_FLOOR_FRACTION = 0.1
# An explicit setting further than this factor from the derived value draws a warning.
_FAR = 10.0


def flow_truncation_rms(
    omega_C: Array, rho_C: Array, rho0_C: Array, centres_x: Array, dt: float, phases: int = 24
) -> float:
    """RMS truncation error (rad/s) of Kabir 2025 eq. 27's fourth-order stencil on the
    projections of features ``rho_C`` (N, 3) of a body turning at the constant ``omega_C``
    about ``rho0_C`` (tumblenav default: how the flow's ``sigma_o`` follows the scenario when
    the filter predicts the instantaneous flow, ``flow_model: instantaneous``).

    Each feature is turned about ``omega_C`` through ``phases`` phases of one turn; at each the
    stencil ``(-w(t+2dt) + 8 w(t+dt) - 8 w(t-dt) + w(t-2dt)) / (12 dt)`` of the exact
    projections is compared with the exact flow ``A omega`` (eq. 18-21): the error is
    ``w^(5) dt^4 / 30 + ...``, i.e. for a projection swinging with amplitude ``a`` at the
    angular rate ``|omega|``, ``a |omega| g(|omega| dt)`` with
    ``g(x) = 1 - (8 sin x - sin 2x) / (6 x) ~ x^4 / 30``; computed here exactly, with the
    perspective and the rig, rather than by that one-harmonic estimate.
    """
    return _flow_phases(omega_C, rho_C, rho0_C, centres_x, dt, phases)[0]


def _flow_phases(
    omega_C: Array, rho_C: Array, rho0_C: Array, centres_x: Array, dt: float, phases: int = 24
) -> tuple[float, float]:
    """:func:`flow_truncation_rms` and the RMS norm (rad/s per rad/s) of the rows of the flow
    matrices ``A`` (:func:`~tumblenav.frontends.projections.flow_matrices`) over the same
    phases: how much one component of the flow moves per unit change of the rate."""
    omega_C = np.asarray(omega_C, dtype=float)
    rho = np.asarray(rho_C, dtype=float)
    rho0 = np.asarray(rho0_C, dtype=float)
    wn = float(np.linalg.norm(omega_C))
    if not wn > 0 or len(rho) == 0:
        return 0.0, 0.0
    from tumblenav import rotations as rot

    period = 2.0 * np.pi / wn
    s = np.arange(phases) * period / phases  # (P,)
    j = np.arange(-2, 3) * dt  # (5,)
    ang = (s[:, None] + j[None, :])[..., None] * omega_C  # (P, 5, 3)
    R = rot.exp_map(ang)  # (P, 5, 3, 3)
    r = np.einsum("pjab,nb->pjna", R, rho - rho0)  # (P, 5, N, 3)
    h = proj.kabir_h(r + rho0, rho0, omega_C, centres_x)  # (P, 5, N, 9)
    w = h[..., 0:4]
    stencil = (-w[:, 4] + 8.0 * w[:, 3] - 8.0 * w[:, 1] + w[:, 0]) / (12.0 * dt)
    err = stencil - h[:, 2, :, 5:9]
    A_R, A_L = proj.flow_matrices(r[:, 2] + rho0, rho0, centres_x)  # (P, N, 2, 3) each
    a2 = float(np.mean(np.concatenate([np.sum(A_R**2, -1), np.sum(A_L**2, -1)], axis=-1)))
    return float(np.sqrt(np.mean(err**2))), float(np.sqrt(a2))


# The stencil of eq. 27 applied to the attitude of a body whose rate random-walks (white
# angular acceleration of PSD q) from the epoch t outwards: the forward and the backward
# halves are independent, each ``var(8 theta(dt) - theta(2 dt)) = (64/3 - 80/6 + 16/6) q dt^3``
# (integrated Wiener process, ``cov(theta(s), theta(t)) = q s^2 (3t - s) / 6``), so the
# stencil's rate differs from the rate at t by a variance ``_STENCIL_WALK q dt``.
_STENCIL_WALK = 2.0 * (64.0 / 3.0 - 80.0 / 6.0 + 16.0 / 6.0) / 144.0


def rk4_attitude_error(omega_norm: float, dt: float) -> float:
    """Attitude error (rad) per step of RK4 on the quaternion kinematics at the rate
    ``|omega|`` (the phase error of the fourth-order Taylor polynomial of ``exp(i x)``,
    ``x = |omega| dt / 2``, doubled): ``~ (|omega| dt)^5 / 1920``."""
    x = 0.5 * omega_norm * dt
    return float(2.0 * abs(x - np.arctan2(x - x**3 / 6.0, 1.0 - x**2 / 2.0 + x**4 / 24.0)))


def derive_tuning(
    omega_T: Array,
    k: Array,
    omega_C: Array,
    rho_C: Array,
    rho0_C: Array,
    centres_x: Array,
    dt: float,
    sigma_p: float,
    rotational_psd: float,
    flow_model: str = "stencil",
) -> dict[str, Any]:
    """Q and ``sigma_o`` from what the estimator knows (tumblenav default, issue 18).

    Parameters: its initial rate ``omega_T`` (rad/s, in T) and log-ratios ``k``, the same rate
    in C and the features' positions in C (m) with the known mass centre ``rho0_C``, the
    rig, the sample interval ``dt`` (s), the projection noise ``sigma_p`` (rad) and the
    scenario's ``process_noise.rotational_rad2_s4`` (q_r, rad^2/s^3: white angular
    acceleration about the first principal axis, isotropic torque).

    * ``q_omega_var = q_r (I_max/I_i)^2 dt`` about each principal axis ``i`` of T (three
      values: the isotropic torque's random walk of the rate over one step, the ratios from
      ``k``; :mod:`tumblenav.dynamics.disturbances`). Until session 26 this was one value,
      ``q_r (I_1/I_i)^2 dt`` maximised over ``i`` with ``I_1`` the moment of T's x axis: where
      that axis is the smallest (kabir2025) every axis got ``q_r dt``, 1.55-3.45x too little
      about the smaller moments.
    * ``q_quat_var``: the attitude's share of the same random walk over one step,
      ``q_r dt^3 / 3`` rad^2 (mean over the three axes: one value per quaternion component
      keeps the trace), plus the RK4 propagation's own error squared
      (:func:`rk4_attitude_error` after the substeps of ``propagate_rotation``), mapped to
      one quaternion component (``dq = dtheta / 2``: a quarter).
    * ``q_k_var``, ``q_feature_var``: a floor only. The body is rigid (constant inertia,
      fixed features; the scenario's process noise is a torque and a force), but with no
      process noise at all the UKF's linearisation errors over thousands of updates shrink
      the covariance below the error (measured, kabir_paper_observed, 8 runs: NEES/dof 52
      with 0, 4.8 with 1e-12, 0.95 with 1e-10 m^2 per step at 10 m). The floor lets each
      feature move by a tenth of the sensor's resolution per step,
      ``(0.1 sigma_p |rho0|)^2`` m^2 (``|rho0|`` the range), and ``k`` by that over the
      features' RMS distance from the mass centre (tumblenav default).
    * ``sigma_flow_rad_s``: in quadrature, the sensor noise through eq. 27's stencil,
      ``sigma_p sqrt(130/144) / dt``; the process noise over the stencil's +- 2 dt (the
      rate's random walk seen through the stencil, ``_STENCIL_WALK q dt`` times the flow's
      sensitivity to the rate, :func:`_flow_phases`); and, for ``flow_model:
      instantaneous`` only, eq. 27's truncation error (:func:`flow_truncation_rms`) at the
      initial rate and geometry (the ``stencil`` model predicts it).
    """
    m = np.exp(np.array([k[0], 0.0, k[1]], dtype=float))
    ratio2_axes = (np.max(m) / m) ** 2  # (I_max / I_i)^2
    ratio2 = float(np.mean(ratio2_axes))
    q_omega = rotational_psd * ratio2_axes * dt
    wn = float(np.linalg.norm(omega_T))
    from tumblenav.estimators.kabir2025.model import rk4_substeps

    n_sub = rk4_substeps(wn, dt)
    rk4 = n_sub * rk4_attitude_error(wn, dt / n_sub)
    q_att = rotational_psd * ratio2 * dt**3 / 3.0 + rk4**2
    trunc, a_rms = _flow_phases(omega_C, rho_C, rho0_C, centres_x, dt)
    noise = _STENCIL_NOISE_GAIN * sigma_p / dt
    walk = a_rms * float(np.sqrt(_STENCIL_WALK * rotational_psd * ratio2 * dt))
    modelled = flow_model == "stencil"
    rng = float(np.linalg.norm(rho0_C))
    lever = float(np.sqrt(np.mean(np.sum((np.asarray(rho_C) - rho0_C) ** 2, axis=-1))))
    s_feat = _FLOOR_FRACTION * sigma_p * rng
    sigma_o = np.sqrt(noise**2 + walk**2 + (0.0 if modelled else trunc**2))
    return {
        "q_omega_var": [float(v) for v in q_omega],
        "q_quat_var": float(q_att / 4.0),
        "q_k_var": float((s_feat / lever) ** 2) if lever > 0 else 0.0,
        "q_feature_var": float(s_feat**2),
        "sigma_flow_rad_s": float(sigma_o),
        "flow_noise_rad_s": float(noise),
        "flow_truncation_rad_s": float(trunc),
        "flow_process_noise_rad_s": float(walk),
    }


def _shown(v: float | list[float]) -> str:
    """A tuning value as a warning prints it."""
    if isinstance(v, (int, float)):
        return f"{v:.3g}"
    return "[" + ", ".join(f"{x:.3g}" for x in v) + "]"


def rate_q(q_omega_var: float | list[float] | None) -> Array:
    """``q_omega_var`` as three per-axis values (rad^2/s^2 per step; null: zeros)."""
    return np.broadcast_to(np.asarray(q_omega_var or 0.0, dtype=float), (3,)).copy()


def resolve_tuning(tun: KabirTuning, derived: dict[str, Any]) -> tuple[KabirTuning, list[str]]:
    """``tun`` with every unset (null) Q / sigma_o key replaced by its derived value, and a
    warning for each explicit one more than 10x from what the scenario implies."""
    keys = ("q_omega_var", "q_quat_var", "sigma_flow_rad_s")
    warnings_: list[str] = []
    update: dict[str, Any] = {}
    for key in ("q_k_var", "q_feature_var"):  # the paper's small floors: no warning
        if getattr(tun, key) is None:
            update[key] = derived.get(key, 0.0)
    for key in keys:
        given = getattr(tun, key)
        want = derived[key]
        if given is None:
            update[key] = want
            continue
        per_axis = key == "q_omega_var"
        g = rate_q(given) if per_axis else np.array([float(given)])
        w = rate_q(want) if per_axis else np.array([float(want)])
        shown_g, shown_w = _shown(given), _shown(want)
        both = (w > 0) & (g > 0)
        r = np.where(both, g / np.where(w > 0, w, 1.0), 1.0)
        worst = int(np.argmax(np.abs(np.log(r))))
        axis = f" (axis {'xyz'[worst]})" if per_axis and len(set(r.tolist())) > 1 else ""
        if r[worst] > _FAR or r[worst] < 1.0 / _FAR:
            warnings_.append(
                f"estimator.tuning.{key} = {shown_g} is {r[worst]:.3g}x what the scenario "
                f"implies{axis} ({shown_w}: derived from the initial rate, dt, process_noise "
                "and eq. 27's truncation error); leave it unset to use the derived value"
            )
        elif np.any((w > 0) & (g == 0)) or (
            np.any((g > 0) & (w == 0)) and key != "sigma_flow_rad_s"
        ):
            warnings_.append(
                f"estimator.tuning.{key} = {shown_g} where the scenario implies {shown_w}"
            )
    return tun.model_copy(update=update), warnings_
