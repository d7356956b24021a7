"""Kabir 2025's UKF on stereo projections and optical flow (``ukf``), and a multiplicative
(USQUE-style) variant of it (``ukf-mult``).

Kabir & Bai, Sensors 2025, 25, 647, Sec. 2.1-2.2 and 3.2.  Known (Sec. 2.1): the target's mass
centre ``rho0`` relative to the chaser, and the chaser's (fixed) attitude; the chaser does not
rotate and L = I (``chaser.orbit: null``).

State (Kabir 2025 eq. 5), in tumblenav's names and order::

    x = [omega_TI_T (3), q_TI (4, [x,y,z,w]), k1, k2, p_1..p_N in T (3N)]

Kabir's B is our T and his ``q`` (scalar first, ``nu_B = C(q) nu_I``) is our ``q_TI``.
Inertia (Kabir 2025 eq. 6-8): the paper defines ``k1 = log(I1/I2)``, ``k2 = log(I2/I3)``
(eq. 6) but then writes ``I = diag(exp k1, 1, exp k2)`` (eq. 7) and builds the Euler equations
(eq. 8) on it; the two disagree on ``k2``.  We implement eq. 7, i.e. ``k2 = log(I3/I2)``:
``I / I2 = diag(e^k1, 1, e^k2)`` and, from ``I w' = -w x (I w)``::

    wx' = e^-k1 (1 - e^k2) wy wz,   wy' = (e^k2 - e^k1) wx wz,   wz' = e^-k2 (e^k1 - 1) wx wy

(the extracted eq. 8 lost the minus signs in the exponents).  Kinematics ``dq_TI/dt`` by
:func:`tumblenav.rotations.quat_derivative`; ``k`` and ``p`` constant (eq. 11-12); RK4 over
each step (eq. 13).

Measurements (eq. 16-25): per feature ``[u_R, v_R, u_L, v_L, u_L - u_R, du_R, dv_R, du_L,
dv_L]`` (rad, rad/s) from :mod:`tumblenav.frontends.projections` with the flow taken by finite
differences of the measured projections (eq. 27).  Features in C: ``rho_i = rho0_C + R_CI
R_IT p_i``; the flow is that of a rigid rotation about ``rho0`` with ``omega_C = R_CI R_IT
omega_TI_T``.  ``R`` is diagonal (``sigma_p``, ``sigma_d``, ``sigma_o``).  Beyond the paper
(tuning ``flow_edges``, default ``drop``): no flow where eq. 27 falls back to its first- and
second-order formulas, i.e. two samples at each end of every run of measurements; their
truncation error is 30 (0.075 Hz) to 180 (0.025 Hz) times the paper's ``sigma_o`` and its last
sample before an occlusion otherwise throws ``k`` off just before the filter must coast.

Filters
-------
* ``ukf`` (the paper's): additive UKF on the 24-dim state with the 4-component quaternion
  (normalised after every predict and update), scaled unscented transform (Sec. 3.2:
  alpha = 0.1, beta = 2, kappa = 0), diagonal P0 and Q with the quaternion's variances on its
  four components.  Its history reports the 23-dim error-state covariance: the quaternion
  block is mapped by ``dtheta = 2 vec(dq (x) conj(q_hat))`` (the first-order form of
  :func:`tumblenav.rotations.boxminus`, which also drops the quaternion's norm direction).
* ``ukf-mult``: sigma points on the 23-dim error state with the attitude as a rotation vector,
  ``q = exp(dtheta) (x) q_hat`` (tumblenav's boxplus), the quaternion kept unit, the mean
  attitude as the weighted mean of the sigma points' errors about the propagated centre point
  (USQUE-like, Crassidis & Markley 2003, in the left/global error of
  :mod:`tumblenav.rotations`).  The quaternion variances of P0 and Q map to ``4 x`` those
  values in rad^2 (``dtheta = 2 dq_vec``).  After each update the covariance is moved to the
  new nominal attitude (error reset ``G = I + 1/2 [dtheta x]``, from the BCH formula); without
  it the large early corrections from the paper's initial guess sent the filter to wrong
  solutions (70 deg off at 1000 s on three seeds of four).  Once the attitude is lost (sigma > 180 deg, long
  occlusions) its rotation-vector sigma points wrap and the run diverges; it is then stopped.

Both filters propagate the sigma points (RK4) and redraw them from the predicted covariance
for the update.  A run is stopped and counted in ``skipped['diverged']`` once its state or
covariance stops being finite or becomes absurd (see ``_MAX_STATE``); later epochs are NaN.

Behaviour worth knowing: the measurements are very precise (1e-5 rad) and the body frame is
fixed only through the Euler dynamics, so from the paper's initial guess (27.8 deg, omega x
1.75) the filters claim sub-degree attitude within a few steps while still ~28 deg off (NEES
in the thousands) and converge only as the process noise lets them, over a few polhode
periods (kabir2025 at 0.075 Hz, four seeds, after 1000 s: 0.6-0.7 deg for ``ukf``, 0.9-2.1
deg for ``ukf-mult``).  From 10 % of those initial errors both are consistent (NEES/dof
~0.8) and reach ~0.3 deg in 400 s (tests/test_ukf.py).

Entry points: :func:`run_ukf` runs either filter on prepared measurements ``z`` (n, N, 9) and
variances (n, N, 9) (NaN = not available), so that pseudo-measurements (the GP predictions of
``ukf-gp``) with their own variances can be fed; :func:`stereo_measurements` builds ``z`` and
``R`` from a :class:`~tumblenav.measurements.StereoMeasurements`; :func:`paper_tuning` gives the
paper's per-frequency Q and flow noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
)
from scipy import stats

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import rk4_step
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
from tumblenav.frontends import projections as proj
from tumblenav.measurements import STEREO_TRACKS

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]

__all__ = [
    "KabirGeometry",
    "KabirTuning",
    "KabirUKF",
    "euler_rhs_k",
    "geometry",
    "initial_state",
    "layout",
    "measurement_model",
    "paper_tuning",
    "parse_tuning",
    "projection_sigmas",
    "propagate_rotation",
    "run_ukf",
    "stereo_measurements",
]

# Kabir 2025 Sec. 3.2, per tumbling frequency f_T (Hz): Q of omega (rad^2/s^2), Q of each
# quaternion component, and sigma_o of the optical flow (rad/s).
_PAPER_PER_FREQUENCY = {
    0.025: (2.5e-9, 4e-10, 1e-5),
    0.075: (2.5e-7, 4e-8, 5e-4),
    0.125: (2.5e-5, 4e-6, 5e-4),
    0.175: (2.5e-5, 4e-6, 1e-3),
}


def layout(n_features: int) -> StateLayout:
    """Kabir 2025 eq. 5 in tumblenav's block names: nominal 9 + 3N, error 8 + 3N."""
    return StateLayout(
        (
            Block("rate", "vector", 3),
            Block("attitude", "quat", 3),
            Block("inertia", "vector", 2),
            Block("features", "vector", 3 * n_features),
        )
    )


# --- tuning --------------------------------------------------------------------------------


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
    init: Literal["triangulated", "given"] = Field(
        "triangulated",
        description="'triangulated': from the first epochs' measurements alone (q = identity, "
        "features triangulated, omega from the optical flow, k = 0); 'given': init_omega_rad_s, "
        "init_q_TI, init_features_m (the kabir2025 recipe gives Kabir 2025 Sec. 3.2's "
        "truth-based guess this way: tumblenav.papers.kabir2025.paper_start)",
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
    q_omega_var: float = Field(2.5e-9, ge=0, description="rad^2/s^2 per step")
    q_quat_var: float = Field(4e-10, ge=0, description="per quaternion component per step")
    q_k_var: float = Field(3.6e-5, ge=0, description="per step")
    q_feature_var: float = Field(1e-6, ge=0, description="m^2 per step")
    sigma_p_rad: float | Literal["sensor"] = Field(
        "sensor",
        description="projection noise sigma_p (rad, Kabir 2025 eq. 24); 'sensor': the "
        "measurements' noise_px / focal_px (left camera)",
    )
    sigma_d_rad: float | Literal["sigma_p"] = Field(
        "sigma_p", description="disparity noise (rad); 'sigma_p': the same as sigma_p_rad"
    )
    sigma_flow_rad_s: float = Field(
        1e-5,
        gt=0,
        description="optical flow noise sigma_o; note that eq. 27's truncation error at 1 Hz "
        "is ~3e-3 to 6e-3 rad/s at Kabir's tumbling rates, far above the paper's sigma_o "
        "(docs/results/kabir2025.md)",
    )
    flow_edges: Literal["drop", "paper"] = Field(
        "drop",
        description="'drop': no flow where Kabir 2025 eq. 27 falls back to its first- and "
        "second-order differences (two samples at each end of every run of measurements: their "
        "truncation error is tens to hundreds of sigma_o at the paper's tuning); 'paper': use "
        "eq. 27 everywhere",
    )
    gate_probability: float | None = Field(
        None, gt=0, lt=1, description="per-feature chi-square innovation gate; default: none"
    )

    @field_validator("sigma_p_rad", "sigma_d_rad", mode="before")
    @classmethod
    def _number_or_rule(cls, v: Any, info: ValidationInfo) -> Any:
        """A positive number, or the rule named by the default (``null``, the former default,
        means the rule too)."""
        rule = cls.model_fields[info.field_name].default
        if v is None or v == rule:
            return rule
        try:
            number = float("nan") if isinstance(v, bool) else float(v)
        except (TypeError, ValueError):
            number = float("nan")
        if not number > 0:
            raise ValueError(f"a positive number or '{rule}', got {v!r}")
        return number


def parse_tuning(raw: dict[str, Any] | None, model: type[KabirTuning] = KabirTuning) -> KabirTuning:
    """Validate ``estimator.tuning``; InputError naming the key on unknown keys / bad values."""
    return base_parse_tuning(raw, model)


def paper_tuning(f_T_hz: float) -> dict[str, float]:
    """Kabir 2025 Sec. 3.2's per-frequency tuning: ``q_omega_var``, ``q_quat_var``,
    ``sigma_flow_rad_s`` for f_T in 0.025, 0.075, 0.125, 0.175 Hz."""
    for f, (qw, qq, so) in _PAPER_PER_FREQUENCY.items():
        if abs(f_T_hz - f) < 1e-6:
            return {"q_omega_var": qw, "q_quat_var": qq, "sigma_flow_rad_s": so}
    raise InputError(
        f"Kabir 2025 tunes only f_T = {', '.join(map(str, _PAPER_PER_FREQUENCY))} Hz; "
        f"got {f_T_hz:g} Hz"
    )


# --- the model -----------------------------------------------------------------------------


def _euler_coefficients(k: Array) -> Array:
    """``[e^-k1 (1 - e^k2), e^k2 - e^k1, e^-k2 (e^k1 - 1)]`` of :func:`euler_rhs_k`: the
    coefficients ``c`` of :func:`tumblenav.dynamics.rigid_body.euler_rhs_coefficients` for
    ``I / I2 = diag(e^k1, 1, e^k2)``."""
    e1, e2 = np.exp(k[..., 0]), np.exp(k[..., 1])
    return np.stack([(1.0 - e2) / e1, e2 - e1, (e1 - 1.0) / e2], axis=-1)


def euler_rhs_k(omega_T: Array, k: Array) -> Array:
    """Torque-free Euler equations with ``I / I2 = diag(e^k1, 1, e^k2)``, (..., 3) rad/s^2.

    Kabir 2025 eq. 6-8: eq. 7's ``I = diag(exp k1, 1, exp k2)`` is used, i.e.
    ``k1 = log(I1/I2)``, ``k2 = log(I3/I2)`` (eq. 6 prints ``log(I2/I3)``, inconsistent with
    eq. 7-8), and eq. 8 with the minus signs in its exponents restored::

        wx' = e^-k1 (1 - e^k2) wy wz,  wy' = (e^k2 - e^k1) wx wz,  wz' = e^-k2 (e^k1 - 1) wx wy
    """
    return euler_rhs_coefficients(omega_T, _euler_coefficients(np.asarray(k, dtype=float)))


def propagate_rotation(omega_T: Array, q_TI: Array, k: Array, dt: float) -> tuple[Array, Array]:
    """RK4 of Kabir 2025 eq. 8-10 (Euler in k1, k2 form + quaternion kinematics
    ``dq_TI/dt = -1/2 [omega; 0] (x) q_TI``) over ``dt``; stacks (...).

    The quaternion is not normalised here (the additive UKF propagates non-unit sigma points;
    the kinematics are linear in ``q``).
    """
    c = _euler_coefficients(k)

    def f(w, q):
        return euler_rhs_coefficients(w, c), rot.quat_derivative_fast(q, w)

    w_new, q_new = rk4_step(f, (omega_T, q_TI), dt)
    return w_new, q_new


@dataclass(frozen=True)
class KabirGeometry:
    """What Kabir 2025 Sec. 2.1 takes as known.

    R_CI : (3, 3) rig attitude (constant: rotationally fixed chaser, L = I).
    rho0_C, rho0_dot_C : (n, 3) target mass centre in C (m) and its velocity (m/s).
    centres_x : (2,) ``(x_left, x_right)`` of the camera centres in C (m).
    """

    R_CI: Array
    rho0_C: Array
    rho0_dot_C: Array
    centres_x: Array


def _mass_centre(scenario: Any) -> tuple[Array, Array] | None:
    """The settings' known mass centre ``(r0_L (3,), v_L (3,))``, or None if not given (read
    from the raw settings: ukf-gp's extend ukf's, see :class:`KabirTuning`)."""
    raw = scenario.estimator.tuning or {}
    if raw.get("mass_centre_L_m") is None:
        return None
    fields = KabirTuning.model_fields
    r0 = raw["mass_centre_L_m"]
    v = raw.get("mass_centre_velocity_L_m_s", fields["mass_centre_velocity_L_m_s"].default)
    try:
        r0_L, v_L = np.asarray(r0, float).reshape(3), np.asarray(v, float).reshape(3)
    except (TypeError, ValueError):
        raise InputError(
            "estimator.tuning.mass_centre_L_m / mass_centre_velocity_L_m_s: three numbers each"
        ) from None
    return r0_L, v_L


def check_scenario(scenario: Any) -> None:
    """What Kabir 2025's filters need (Sec. 2.1), checked before anything else is read."""
    scenario = context_from_scenario(scenario)  # never the target's truth
    if scenario.sensor.kind != "stereo":
        raise InputError(
            f"Kabir 2025's UKF needs a stereo rig; scenario {scenario.name} has a "
            f"{scenario.sensor.kind} sensor"
        )
    if scenario.chaser.orbit is not None:
        raise InputError(
            "Kabir 2025's UKF assumes an inertially fixed chaser (Sec. 2.1): set chaser.orbit: "
            f"null (scenario {scenario.name} has an orbit)"
        )
    if _mass_centre(scenario) is None:
        raise InputError(
            "Kabir 2025's UKF assumes the target's mass-centre position known (Sec. 2.1): give "
            "it as estimator.tuning.mass_centre_L_m (m, in L at t = 0) and, if it moves, "
            "mass_centre_velocity_L_m_s"
        )
    if scenario.sensor.rig != "parallel":
        raise InputError(
            "Kabir 2025's observation model (eq. 16-27) needs a parallel stereo rig; scenario "
            f"{scenario.name} has a {scenario.sensor.rig} rig"
        )


def geometry(scenario: Any, t: Array, meas: Any = None) -> KabirGeometry:
    """The known geometry at times ``t``: the mass centre from the settings
    (``mass_centre_L_m + t mass_centre_velocity_L_m_s``, L = I since the chaser has no orbit:
    Kabir 2025's assumption, stated by the user), the rig attitude from the
    measurements' ``q_CL``/``q_LI`` (else from the scenario's camera mount), the rig from the
    measurements (else from the scenario's sensor)."""
    scenario = context_from_scenario(scenario)  # never the target's truth
    from tumblenav import sensors

    check_scenario(scenario)
    t = np.asarray(t, dtype=float)
    r0_L, v_L = _mass_centre(scenario)
    r_L = r0_L + np.outer(t, v_L)
    if meas is not None:
        R_CI = rot.quat_to_matrix(rot.quat_multiply(meas.q_CL, meas.q_LI))
        rig = meas.rig
    else:
        if scenario.chaser.attitude == "target-pointing":
            R_LC = sensors.target_pointing_R_LC(r_L)
        else:
            R_LC = np.broadcast_to(scenario.chaser.R_LC_fixed, (len(t), 3, 3))
        R_CI = np.swapaxes(R_LC, -1, -2)
        rig = sensors.make_rig(scenario.sensor)
    R_CI = np.asarray(R_CI).reshape(-1, 3, 3)
    if np.abs(R_CI - R_CI[0]).max() > 1e-9:
        raise InputError(
            "Kabir 2025's optical-flow model needs a rotationally fixed rig (Sec. 2.1); the "
            "rig attitude changes during the run"
        )
    R = R_CI[0]
    return KabirGeometry(
        R_CI=R,
        rho0_C=r_L @ R.T,
        rho0_dot_C=np.broadcast_to(R @ v_L, (len(t), 3)).copy(),
        centres_x=proj.parallel_centres_x(rig),
    )


def measurement_model(
    x: Array, R_CI: Array, rho0_C: Array, rho0_dot_C: Array, centres_x: Array
) -> Array:
    """Kabir 2025 eq. 22-23 for states ``x`` (..., nominal): (..., N, 9).

    ``rho_i = rho0_C + R_CI R_IT p_i`` (eq. 4 in C), ``omega_C = R_CI R_IT omega_TI_T``; the
    quaternion need not be unit (it is normalised in the rotation matrix).
    """
    R_CT = R_CI @ np.swapaxes(rot.quat_to_matrix_fast(x[..., 3:7]), -1, -2)
    p = x[..., 9:].reshape(x.shape[:-1] + (-1, 3))
    rho = rho0_C[..., None, :] + p @ np.swapaxes(R_CT, -1, -2)
    omega_C = (R_CT @ x[..., 0:3, None])[..., 0]
    return proj.kabir_h(rho, rho0_C, omega_C, centres_x, rho0_dot_C)


def projection_sigmas(tun: KabirTuning, meas: Any) -> tuple[float, float]:
    """``(sigma_p, sigma_d)`` (rad) of Kabir 2025 eq. 24: as given in the tuning, or by its
    rules (``'sensor'``: the measurements' ``noise_px / focal_px``; ``'sigma_p'``)."""
    sp = tun.sigma_p_rad
    if sp == "sensor":
        sp = float(meas.noise_px) / float(meas.rig.left.focal_px)
        if not sp > 0:
            raise InputError(
                "the sensor noise is zero or unknown: set estimator.tuning.sigma_p_rad"
            )
    sd = sp if tun.sigma_d_rad == "sigma_p" else tun.sigma_d_rad
    return sp, sd


def stereo_measurements(meas: Any, tuning: KabirTuning | None = None) -> tuple[Array, Array]:
    """``z`` (n, N, 9) and its variances (n, N, 9) from pixel measurements.

    ``z_i = [u_R, v_R, u_L, v_L, u_L - u_R, du_R, dv_R, du_L, dv_L]`` from
    :func:`~tumblenav.frontends.projections.normalised` and the flow by
    :func:`~tumblenav.frontends.projections.finite_difference_rate` (Kabir 2025 eq. 27) of the
    measured projections (by default only where eq. 27 is fourth order, see ``flow_edges``);
    NaN where not available.  Variances: ``sigma_p^2``, ``sigma_d^2``
    (:func:`projection_sigmas`) and ``sigma_flow^2`` (Kabir 2025 eq. 24-25, diagonal).
    """
    tun = tuning or KabirTuning()
    t = np.asarray(meas.t, dtype=float)
    dts = np.diff(t)
    if len(t) < 2 or np.ptp(dts) > 1e-9 * max(1.0, float(np.abs(dts).max())):
        raise InputError("Kabir 2025's finite differences need uniformly sampled measurements")
    w, _ = proj.normalised(meas)
    flow = proj.finite_difference_rate(w, float(dts[0]))
    if tun.flow_edges == "drop":
        flow = np.where(proj.finite_difference_order(w) == 4, flow, np.nan)
    z = np.concatenate([w, w[..., 2:3] - w[..., 0:1], flow], axis=-1)
    sp, sd = projection_sigmas(tun, meas)
    var = np.array([sp**2] * 4 + [sd**2] + [tun.sigma_flow_rad_s**2] * 4)
    return z, np.broadcast_to(var, z.shape).copy()


# --- initial state -------------------------------------------------------------------------


def initial_state(
    scenario: Any, t: Array, z: Array, geom: KabirGeometry, tun: KabirTuning, variant: Variant
) -> tuple[Array, Array]:
    """``x0`` (nominal) and ``P0`` (24x24 for ``additive``, 23x23 for ``mult``) at ``t[0]``.

    ``init: triangulated`` uses the measurements ``z`` (n, N, 9) of the first epochs only;
    ``init: given`` the settings' ``init_omega_rad_s``, ``init_q_TI``, ``init_features_m``
    (``k = 0``), e.g. Kabir 2025 Sec. 3.2's truth-based guess made by the kabir2025 recipe.
    """
    N = z.shape[1]
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
    else:
        x[0:3], x[3:7], x[9:] = _triangulated_start(t, z, geom)
    if variant == "additive":
        var = [tun.p0_omega_var] * 3 + [tun.p0_quat_var] * 4
    else:  # dtheta = 2 dq_vec
        var = [tun.p0_omega_var] * 3 + [4.0 * tun.p0_quat_var] * 3
    var += [tun.p0_k_var] * 2 + [tun.p0_feature_var] * (3 * N)
    return x, np.diag(var)


def _triangulated_start(t: Array, z: Array, geom: KabirGeometry) -> tuple[Array, Array, Array]:
    """At ``t[0]``: q_TI = identity (T := I); features triangulated in C; omega_C by least
    squares on ``w_dot = A omega`` (Kabir 2025 eq. 18-19) with the flow from the one-sided
    second-order difference of the first three epochs' projections (else ``z[0]``'s flow)."""
    z0 = z[0]
    cl, cr = geom.centres_x
    ok = np.all(np.isfinite(z0[:, [0, 1, 2, 4]]), axis=1)
    if ok.sum() < 2:
        raise InputError("estimator.tuning.init: 'triangulated' needs >= 2 stereo features at t0")
    y = (cr - cl) / z0[:, 4]  # disparity u_L - u_R = b / y
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


# --- the filter ----------------------------------------------------------------------------


@dataclass(frozen=True)
class _Unscented:
    """Scaled unscented transform (Julier 2002; Kabir 2025 Sec. 3.2 alpha, beta, kappa)."""

    Wm: Array  # (2n+1,)
    Wc: Array
    c: float  # sqrt(n + lambda)

    @classmethod
    def make(cls, n: int, alpha: float, beta: float, kappa: float) -> _Unscented:
        lam = alpha**2 * (n + kappa) - n
        if not n + lam > 0:
            raise InputError("estimator.tuning: alpha^2 (n + kappa) must be positive")
        Wm = np.full(2 * n + 1, 0.5 / (n + lam))
        Wm[0] = lam / (n + lam)
        Wc = Wm.copy()
        Wc[0] += 1.0 - alpha**2 + beta
        return cls(Wm=Wm, Wc=Wc, c=float(np.sqrt(n + lam)))

    def offsets(self, P: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Sigma-point offsets (B, 2n+1, n): 0, +c columns of sqrt(P), -c columns; and the
        runs whose covariance needed a repair (see :func:`_sqrt_psd`)."""
        L, repaired = _sqrt_psd(P)
        Lt = self.c * np.swapaxes(L, -1, -2)
        return np.concatenate([np.zeros_like(Lt[:, :1]), Lt, -Lt], axis=1), repaired

    def cov(self, A: Array, B_: Array) -> Array:
        """``sum_i Wc_i A_i B_i^T`` for (B, S, a), (B, S, b) -> (B, a, b)."""
        return np.swapaxes(A * self.Wc[:, None], -1, -2) @ B_


def _sqrt_psd(P: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Square roots ``L L^T = P`` of (B, n, n): Cholesky, or for a run where that fails the
    symmetric square root with eigenvalues clipped at 1e-15 of the largest (the negative
    zeroth weight of the scaled transform can leave a slightly indefinite covariance); NaN for
    a run whose P is not finite.  Returns also which runs were repaired."""
    try:
        return np.linalg.cholesky(P), np.zeros(P.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    L = np.full_like(P, np.nan)
    repaired = np.zeros(P.shape[0], dtype=bool)
    for b in range(P.shape[0]):
        if not np.all(np.isfinite(P[b])):
            continue
        try:
            L[b] = np.linalg.cholesky(P[b])
        except np.linalg.LinAlgError:
            lam, V = np.linalg.eigh(0.5 * (P[b] + P[b].T))
            lam = np.maximum(lam, 1e-15 * np.abs(lam).max())
            L[b] = V * np.sqrt(lam)
            repaired[b] = True
    return L, repaired


def _boxplus(x: Array, dx: Array) -> Array:
    """``x [+] dx`` for this layout (rate, attitude, inertia, features): the attitude by
    :func:`tumblenav.rotations.boxplus`, the rest by addition; broadcasts."""
    q = rot.boxplus_fast(x[..., 3:7], dx[..., 3:6])
    v = x[..., 0:3] + dx[..., 0:3]
    if q.shape[:-1] != v.shape[:-1]:
        q = np.broadcast_to(q, v.shape[:-1] + (4,))
    return np.concatenate([v, q, x[..., 7:] + dx[..., 6:]], axis=-1)


def quat_cov_map(q_hat: Array) -> Array:
    """(..., 3, 4) ``d dtheta / d q`` at ``q_hat`` for ``dtheta = 2 vec(q (x) conj(q_hat))``,
    the first-order form of :func:`tumblenav.rotations.boxminus` (its null space is the
    quaternion's norm direction)."""
    qh = q_hat / np.linalg.norm(q_hat, axis=-1, keepdims=True)
    E = rot.quat_multiply_fast(np.eye(4), rot.quat_conjugate(qh)[..., None, :])  # (..., 4 j, 4)
    return 2.0 * np.swapaxes(E[..., :3], -1, -2)


def additive_to_error_cov(x: Array, P: Array) -> Array:
    """24x24 covariance of the additive state -> 23x23 error-state covariance (...)."""
    n = P.shape[-1]
    T = np.zeros(P.shape[:-2] + (n - 1, n))
    T[..., 0:3, 0:3] = np.eye(3)
    T[..., 3:6, 3:7] = quat_cov_map(x[..., 3:7])
    T[..., 6:, 7:] = np.eye(n - 7)
    return T @ P @ np.swapaxes(T, -1, -2)


def _process_noise(tun: KabirTuning, N: int, variant: Variant) -> Array:
    """Diagonal Q per step (Kabir 2025 eq. 14-15, Sec. 3.2)."""
    if variant == "additive":
        v = [tun.q_omega_var] * 3 + [tun.q_quat_var] * 4
    else:
        v = [tun.q_omega_var] * 3 + [4.0 * tun.q_quat_var] * 3
    return np.diag(v + [tun.q_k_var] * 2 + [tun.q_feature_var] * (3 * N))


@dataclass(frozen=True)
class _UKFModel:
    """What the UKF's predict and update share, for one run or a batch: the unscented
    transform, Q, the gate, the known geometry, the tuning and the variant."""

    ut: _Unscented
    Q: Array
    gate: Array | None
    geom: KabirGeometry
    tun: KabirTuning
    variant: Variant
    N: int

    @classmethod
    def make(cls, d: int, N: int, geom: KabirGeometry, tun: KabirTuning, variant: Variant):
        gate = None
        if tun.gate_probability is not None:
            gate = stats.chi2.ppf(tun.gate_probability, np.arange(10))  # by dof 0..9
        ut = _Unscented.make(d, tun.alpha, tun.beta, tun.kappa)
        return cls(ut, _process_noise(tun, N, variant), gate, geom, tun, variant, N)

    @property
    def additive(self) -> bool:
        return self.variant == "additive"

    def sigma(self, x: Array, P: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Sigma points (B, 2d+1, nom), their offsets, and the runs whose P needed a repair."""
        off, rep = self.ut.offsets(P)
        X = x[:, None, :] + off if self.additive else _boxplus(x[:, None, :], off)
        return X, off, rep

    def predict(self, x: Array, P: Array, dt: float) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Kabir 2025 eq. 13-15 for B runs over ``dt``; also the runs repaired."""
        Wm = self.ut.Wm
        X, _, rep = self.sigma(x, P)
        w, q = propagate_rotation(X[..., 0:3], X[..., 3:7], X[..., 7:9], dt)
        if self.additive:
            X = np.concatenate([w, q, X[..., 7:]], axis=-1)
            x = Wm @ X
            D = X - x[:, None, :]
            x[:, 3:7] /= np.linalg.norm(x[:, 3:7], axis=-1, keepdims=True)
        else:
            q = q / np.linalg.norm(q, axis=-1, keepdims=True)
            X = np.concatenate([w, q, X[..., 7:]], axis=-1)
            x = Wm @ X
            # mean attitude: the weighted mean e_bar of the sigma points' errors e_i about the
            # propagated centre point, and their deviations e_i - e_bar (BCH: exact to
            # O(|e_i| |e_bar|), e_bar being second order in the spread)
            qc = q[:, 0]
            e = rot.boxminus_fast(q, qc[:, None, :])
            e_bar = Wm @ e
            x[:, 3:7] = rot.boxplus_fast(qc, e_bar)
            D = np.concatenate(
                [w - x[:, None, 0:3], e - e_bar[:, None, :], X[..., 7:] - x[:, None, 7:]],
                axis=-1,
            )
        return x, self.ut.cov(D, D) + self.Q, rep

    def update(
        self, x: Array, P: Array, k: int, zk: Array, Rk: Array, rows: NDArray[np.bool_]
    ) -> tuple[Array, Array, Array, Array, Array, NDArray[np.bool_]]:
        """Kabir 2025 eq. 22-25 for B runs with epoch ``k``'s measurements ``zk``, variances
        ``Rk`` (B, 9N) where ``rows``; returns x, P, NIS and its dof (B,), the rejected
        features (B,) and the runs repaired."""
        ut, geom, N = self.ut, self.geom, self.N
        B, M, d = x.shape[0], 9 * N, P.shape[-1]
        diag = np.arange(M)
        X, off, rep = self.sigma(x, P)
        Z = measurement_model(
            X, geom.R_CI, geom.rho0_C[k], geom.rho0_dot_C[k], geom.centres_x
        ).reshape(B, -1, M)
        zh = ut.Wm @ Z
        dZ = Z - zh[:, None, :]
        S0 = ut.cov(dZ, dZ)
        S0[:, diag, diag] += np.where(rows, Rk, 0.0)
        Pxz = ut.cov(off, dZ)
        nu = np.where(rows, zk - zh, 0.0)
        rejected = np.zeros(B, dtype=np.int64)
        if self.gate is not None:
            rows, rejected = _gate(S0, nu, rows, self.gate, N)
            nu = np.where(rows, nu, 0.0)
        both = rows[:, :, None] & rows[:, None, :]
        S = np.where(both, S0, 0.0)
        S[:, diag, diag] += ~rows
        Pxz = Pxz * rows[:, None, :]
        sol = np.linalg.solve(S, np.concatenate([np.swapaxes(Pxz, 1, 2), nu[..., None]], 2))
        Kt, Sinv_nu = sol[..., :d], sol[..., d]
        dx = (Pxz @ Sinv_nu[..., None])[..., 0]
        P = P - Pxz @ Kt
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        if self.additive:
            x = x + dx
            x[:, 3:7] /= np.linalg.norm(x[:, 3:7], axis=-1, keepdims=True)
        else:
            x = _boxplus(x, dx)
            # reset of the error to the new nominal: theta' = theta - dtheta +
            # 1/2 [dtheta x] theta (BCH), so P <- G P G^T, G = I + 1/2 [dtheta x]
            G = np.broadcast_to(np.eye(d), P.shape).copy()
            G[:, 3:6, 3:6] += 0.5 * rot.skew(dx[:, 3:6])
            P = G @ P @ np.swapaxes(G, -1, -2)
        nis = np.where(rows.any(1), np.sum(nu * Sinv_nu, axis=1), np.nan)
        return x, P, nis, rows.sum(1), rejected, rep


def _filter(
    t: Array,
    z: Array,
    Rv: Array,
    x0: Array,
    P0: Array,
    geom: KabirGeometry,
    tun: KabirTuning,
    variant: Variant,
) -> dict[str, Any]:
    """The batched engine: B filters at once, z, Rv (B, n, N, 9); x0 (B, nom); P0 (B, d, d);
    the same predict and update as :class:`UKFSteps` (tested equal to its fold).

    Returns x (B, n, nom), P (B, n, d, d) of the filter's own state, nis, nis_dof,
    rejected (B,), diverged_at (B,) epoch or -1, repairs (B,).
    """
    B, n, N, _ = z.shape
    M = 9 * N
    nom = 9 + 3 * N
    d = P0.shape[-1]
    m = _UKFModel.make(d, N, geom, tun, variant)
    z = z.reshape(B, n, M)
    Rv = Rv.reshape(B, n, M)
    usable = np.isfinite(z) & np.isfinite(Rv)
    x = np.array(x0, dtype=float)
    P = np.array(P0, dtype=float)
    xs = np.full((B, n, nom), np.nan)
    Ps = np.full((B, n, d, d), np.nan)
    nis = np.full((B, n), np.nan)
    nis_dof = np.zeros((B, n), dtype=np.int64)
    rejected = np.zeros(B, dtype=np.int64)
    repairs = np.zeros(B, dtype=np.int64)
    diverged_at = np.full(B, -1, dtype=np.int64)
    alive = np.ones(B, dtype=bool)

    # a diverging run overflows before it is caught (and stopped) by the finite check
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for k in range(n):
            x_prev, P_prev = x, P
            try:
                if k > 0:
                    x, P, rep = m.predict(x, P, t[k] - t[k - 1])
                    repairs[rep & alive] += 1
                rows = usable[:, k] & alive[:, None]
                if rows.any():
                    x, P, nis_k, dof_k, rej, rep = m.update(x, P, k, z[:, k], Rv[:, k], rows)
                    repairs[rep & alive] += 1
                    rejected += rej
                    nis[:, k] = nis_k
                    nis_dof[:, k] = dof_k
                ok = _sane(x, P)
            except np.linalg.LinAlgError:
                ok = np.zeros(B, dtype=bool)
                x, P = x_prev, P_prev
            if not ok.all():
                bad = alive & ~ok
                diverged_at[bad] = k
                alive &= ok
                x = np.where(ok[:, None], x, x_prev)
                P = np.where(ok[:, None, None], P, P_prev)
                if not alive.any():
                    break
            xs[:, k] = np.where(alive[:, None], x, np.nan)
            Ps[:, k] = np.where(alive[:, None, None], P, np.nan)
    nis[~np.isfinite(xs[..., 0])] = np.nan
    return {
        "x": xs,
        "P": Ps,
        "nis": nis,
        "nis_dof": nis_dof,
        "rejected": rejected,
        "diverged_at": diverged_at,
        "repairs": repairs,
        "usable": usable.reshape(B, n, N, 9),
    }


def _filter_layout(n_features: int, variant: Variant) -> StateLayout:
    """The layout the filter itself works in: :func:`layout` for ``mult``; for the additive
    UKF the quaternion is an additive 4-vector (24-dim covariance, turned into the 23-dim
    error-state covariance for the history: :func:`additive_to_error_cov`)."""
    if variant == "mult":
        return layout(n_features)
    return StateLayout(
        (
            Block("rate", "vector", 3),
            Block("attitude_additive", "vector", 4),
            Block("inertia", "vector", 2),
            Block("features", "vector", 3 * n_features),
        )
    )


@dataclass(frozen=True)
class UKFSteps:
    """Kabir 2025's UKF as stateless steps on one run's prepared measurements, folded by
    :func:`tumblenav.estimators.base.fold` (the reference engine of :func:`run_ukf`; the
    batched :func:`_filter` is the fast one for campaigns, tested equal). The filter starts
    at the first epoch from ``x0``, ``P0``; a state or covariance that is no longer finite or
    absurd stops the run (counted as diverged, Kabir 2025 Sec. 3.2)."""

    model: _UKFModel
    t: Array
    z: Array  # (n, 9N)
    Rv: Array  # (n, 9N)
    x0: Array
    P0: Array
    layout: StateLayout

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        if k != 0:
            return None, StepInfo()
        return Belief(float(self.t[0]), self.x0.copy(), self.P0.copy(), self.layout), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            try:
                x, P, rep = self.model.predict(belief.x[None], belief.P[None], t - belief.t)
            except np.linalg.LinAlgError:  # update() sees a non-finite state: diverged
                x, P, rep = np.full((1,) + belief.x.shape, np.nan), belief.P[None], [False]
        return Belief(t, x[0], P[0], self.layout, memo=int(rep[0]))

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        repairs = belief.memo or 0
        rows = (np.isfinite(self.z[k]) & np.isfinite(self.Rv[k]))[None]
        x, P = belief.x[None], belief.P[None]
        nis, dof, rej = float("nan"), 0, 0
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            try:
                if rows.any():
                    x, P, nis_k, dof_k, rej_k, rep = self.model.update(
                        x, P, k, self.z[k][None], self.Rv[k][None], rows
                    )
                    nis, dof, rej = float(nis_k[0]), int(dof_k[0]), int(rej_k[0])
                    repairs += int(rep[0])
                ok = bool(_sane(x, P)[0])
            except np.linalg.LinAlgError:
                ok = False
        skipped = {"covariance_repairs": repairs}
        out = Belief(belief.t, x[0], P[0], self.layout)
        if not ok:
            return belief, StepInfo(diverged=True, skipped=skipped)
        return out, StepInfo(nis=nis, dof=dof, rejected=rej, skipped=skipped)

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P


# A run is stopped (counted as diverged) once its state or covariance is no longer finite or
# is absurd: any state component beyond 1e6 (rad/s, log inertia ratio, m) or variance beyond
# 1e12.  Kabir 2025 Sec. 3.2 stops its UKF the same way when the covariance of omega "reaches
# virtually infinity" during occlusion.
_MAX_STATE, _MAX_VARIANCE = 1e6, 1e12


def _sane(x: Array, P: Array) -> NDArray[np.bool_]:
    var = np.diagonal(P, axis1=1, axis2=2)
    return (
        np.all(np.abs(x) < _MAX_STATE, axis=1)
        & np.all(var < _MAX_VARIANCE, axis=1)
        & np.all(np.isfinite(P), axis=(1, 2))
    )


def _gate(
    S: Array, nu: Array, rows: NDArray[np.bool_], gate: Array, N: int
) -> tuple[NDArray[np.bool_], Array]:
    """Per-feature chi-square gate on the 9 (or fewer available) components of each feature."""
    B = S.shape[0]
    r = rows.reshape(B, N, 9)
    Sb = np.stack([S[:, 9 * i : 9 * i + 9, 9 * i : 9 * i + 9] for i in range(N)], axis=1)
    both = r[..., :, None] & r[..., None, :]
    Sb = np.where(both, Sb, 0.0) + (~r)[..., None] * np.eye(9)
    nb = np.where(r, nu.reshape(B, N, 9), 0.0)
    d2 = np.sum(nb * np.linalg.solve(Sb, nb[..., None])[..., 0], axis=-1)
    dof = r.sum(-1)
    reject = (dof > 0) & (d2 > gate[dof])
    return (r & ~reject[..., None]).reshape(B, -1), reject.sum(axis=1)


# --- entry points --------------------------------------------------------------------------


def run_ukf(
    scenario: Any,
    t: Array,
    z: Array,
    R_diag: Array,
    variant: Variant = "additive",
    tuning: KabirTuning | None = None,
    geom: KabirGeometry | None = None,
    x0: Array | None = None,
    P0: Array | None = None,
) -> EstimateHistory:
    """Kabir 2025's UKF (``variant='additive'``) or its multiplicative variant (``'mult'``)
    on prepared measurements.

    Parameters
    ----------
    scenario : Scenario
        For the known geometry (the mass centre from the settings, the rig).
    t : (n,) s
        Epochs; the filter starts at ``t[0]`` (update with ``z[0]``), then predicts and
        updates at every epoch.
    z : (n, N, 9) array
        Per feature ``[u_R, v_R, u_L, v_L, u_L - u_R, du_R, dv_R, du_L, dv_L]`` (rad, rad/s),
        NaN where not available (that component is not used; an epoch with none is a
        prediction only).
    R_diag : (n, N, 9) array
        Variance of each component of ``z`` (rad^2, rad^2/s^2); NaN = not available.
    variant : 'additive' or 'mult'
    tuning : KabirTuning, optional
        Default: ``parse_tuning(scenario.estimator.tuning)``.
    geom : KabirGeometry, optional
        Default: :func:`geometry` ``(scenario, t)``.
    x0, P0 : arrays, optional
        Initial state and covariance (24x24 additive, 23x23 mult); default
        :func:`initial_state`.

    Returns
    -------
    EstimateHistory
        Layout :func:`layout`; ``P`` is the 23-dim error-state covariance for both variants.
    """
    scenario = context_from_scenario(scenario)  # never the target's truth
    if variant not in ("additive", "mult"):
        raise ValueError(f"variant must be 'additive' or 'mult', got {variant!r}")
    tun = tuning if tuning is not None else parse_tuning(scenario.estimator.tuning)
    t = np.asarray(t, dtype=float)
    z = np.asarray(z, dtype=float)
    R_diag = np.asarray(R_diag, dtype=float)
    N = z.shape[1] if z.ndim == 3 else 0
    if z.shape != (len(t), N, 9) or R_diag.shape != z.shape:
        raise ValueError(f"z and R_diag must have shape (n, N, 9) = ({len(t)}, N, 9)")
    geom = geom if geom is not None else geometry(scenario, t)
    if x0 is None or P0 is None:
        x0_, P0_ = initial_state(scenario, t, z, geom, tun, variant)
        x0 = x0_ if x0 is None else x0
        P0 = P0_ if P0 is None else P0
    n = len(t)
    steps = UKFSteps(
        model=_UKFModel.make(np.asarray(P0).shape[-1], N, geom, tun, variant),
        t=t,
        z=z.reshape(n, 9 * N),
        Rv=R_diag.reshape(n, 9 * N),
        x0=np.asarray(x0, dtype=float),
        P0=np.asarray(P0, dtype=float),
        layout=_filter_layout(N, variant),
    )
    r = fold(steps, t)
    stopped = np.flatnonzero(np.isfinite(r.x[:-1, 0]) & ~np.isfinite(r.x[1:, 0])) + 1
    usable = np.isfinite(z) & np.isfinite(R_diag)
    res = {
        "x": r.x[None],
        "P": r.P[None],
        "nis": r.nis[None],
        "nis_dof": r.nis_dof[None].astype(np.int64),
        "rejected": np.array([r.rejected]),
        "diverged_at": np.array([(int(stopped[0]) if len(stopped) else 0) if r.diverged else -1]),
        "repairs": np.array([r.skipped.get("covariance_repairs", 0)]),
        "usable": usable[None],
    }
    return _history(t, res, 0, variant, tun, np.asarray(x0))


def _history(
    t: Array, res: dict[str, Any], b: int, variant: Variant, tun: KabirTuning, x0: Array
) -> EstimateHistory:
    """Run ``b`` of a :func:`_filter` result as an :class:`EstimateHistory` (the covariance
    as the 23-dim error-state covariance for both variants)."""
    x, P = res["x"][b], res["P"][b]
    if variant == "additive":
        P = additive_to_error_cov(x, P)
    div = int(res["diverged_at"][b])
    return EstimateHistory(
        t=t,
        x=x,
        P=P,
        layout=layout((x.shape[-1] - 9) // 3),
        nis=res["nis"][b],
        nis_dof=res["nis_dof"][b],
        skipped=_skipped(res["usable"][b], res, b),
        info={
            "convention": "kabir2025",  # [omega_TI_T, q_TI, k1, k2, p_T]: evaluation.alignment
            "variant": variant,
            "diverged_at_s": float(t[div]) if div >= 0 else None,
            "tuning": tun.model_dump(),
            "x0": x0,
        },
    )


def _skipped(usable: NDArray[np.bool_], res: dict, b: int) -> dict[str, int]:
    any_f = usable.any(axis=-1)  # (n, N)
    return {
        "no_measurement_epochs": int((~any_f.any(axis=-1)).sum()),
        "unobserved_feature_epochs": int((~any_f).sum()),
        "gated_out": int(res["rejected"][b]),
        "diverged": int(res["diverged_at"][b] >= 0),
        "covariance_repairs": int(res["repairs"][b]),
    }


class KabirUKF:
    """``ukf`` (Kabir 2025's additive UKF) and ``ukf-mult`` (USQUE-style variant)."""

    consumes = (STEREO_TRACKS,)  # the measurement types it runs on
    needs = (
        "stereo feature tracks from a parallel rig, an inertially fixed chaser and the target's "
        "mass-centre position, known (Kabir 2025 Sec. 2.1): estimator.tuning.mass_centre_L_m"
    )

    def __init__(self, variant: Variant) -> None:
        self.variant = variant
        self.name = "ukf" if variant == "additive" else "ukf-mult"
        self.description = (
            "Kabir 2025: UKF on stereo projections, disparity and optical flow (quaternion in "
            "the state, additive)"
            if variant == "additive"
            else "Kabir 2025's UKF with a multiplicative attitude error (USQUE-style, 23-dim)"
        )

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        check_scenario(scenario)
        parse_tuning(scenario.estimator.tuning)

    def run(self, scenario: Any, measurements: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        check_scenario(scenario)
        tun = parse_tuning(scenario.estimator.tuning)
        geom = geometry(scenario, measurements.t, measurements)
        z, R = stereo_measurements(measurements, tun)
        return run_ukf(scenario, measurements.t, z, R, self.variant, tun, geom)

    def run_batch(
        self, scenario: Any, measurements: list, rngs: list, p_every: int = 1
    ) -> list[EstimateHistory]:
        """Many runs at once (vectorised over runs): the same histories as :meth:`run`
        (``p_every`` is accepted for the campaign runner; every covariance is kept)."""
        scenario = context_from_scenario(scenario)  # never the target's truth
        check_scenario(scenario)
        tun = parse_tuning(scenario.estimator.tuning)
        t = measurements[0].t
        geoms = [geometry(scenario, m.t, m) for m in measurements]
        g0 = geoms[0]
        same = all(
            np.array_equal(m.t, t)
            and np.allclose(g.R_CI, g0.R_CI)
            and np.allclose(g.rho0_C, g0.rho0_C)
            and np.allclose(g.centres_x, g0.centres_x)
            for m, g in zip(measurements, geoms, strict=True)
        )
        if not same:
            raise ValueError("run_batch needs runs with the same epochs and geometry")
        zs, Rs, x0s, P0s = [], [], [], []
        for m in measurements:
            z, R = stereo_measurements(m, tun)
            x0, P0 = initial_state(scenario, t, z, g0, tun, self.variant)
            zs.append(z)
            Rs.append(R)
            x0s.append(x0)
            P0s.append(P0)
        res = _filter(
            t, np.stack(zs), np.stack(Rs), np.stack(x0s), np.stack(P0s), g0, tun, self.variant
        )
        return [_history(t, res, b, self.variant, tun, x0s[b]) for b in range(len(measurements))]


register("ukf")(lambda: KabirUKF("additive"))
register("ukf-mult")(lambda: KabirUKF("mult"))
