"""Kabir 2025's filter model: state layout (eq. 5), torque-free dynamics with the log inertia
ratios (eq. 6-8), propagation (eq. 13-15), the known geometry (Sec. 2.1) and the process
noise; the additive/multiplicative error-state algebra."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import rk4_step
from tumblenav.dynamics.rigid_body import euler_rhs_coefficients
from tumblenav.errors import InputError
from tumblenav.estimators.base import (
    Block,
    StateLayout,
)
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.kabir2025 import kernels
from tumblenav.estimators.kabir2025.tuning import KabirTuning, rate_q
from tumblenav.frontends import projections as proj

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


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


# RK4's attitude error per step grows as (|omega| dt)^5 / 1920 (tuning.rk4_attitude_error):
# 4e-4 rad at |omega| dt = 1.1 (Kabir's 0.175 Hz at 1 Hz). Steps are split so that
# |omega| dt <= _MAX_TURN_PER_STEP (tumblenav default; <= 5e-7 rad per substep).
_MAX_TURN_PER_STEP = 0.25


def rk4_substeps(omega_norm: float, dt: float) -> int:
    """RK4 substeps of one step ``dt`` at the rate ``|omega|`` (tumblenav default)."""
    return max(1, int(np.ceil(abs(omega_norm * dt) / _MAX_TURN_PER_STEP - 1e-12)))


def propagate_rotation(omega_T: Array, q_TI: Array, k: Array, dt: float) -> tuple[Array, Array]:
    """RK4 of Kabir 2025 eq. 8-10 (Euler in k1, k2 form + quaternion kinematics
    ``dq_TI/dt = -1/2 [omega; 0] (x) q_TI``) over ``dt``; stacks (...).

    The step is split into :func:`rk4_substeps` equal RK4 steps for the fastest rate of the
    stack (one step at Kabir's 0.025 Hz at 1 Hz; tumblenav default beyond the paper's eq. 13).
    The quaternion is not normalised here (the additive UKF propagates non-unit sigma points;
    the kinematics are linear in ``q``).
    """
    c = _euler_coefficients(k)

    def f(w, q):
        return euler_rhs_coefficients(w, c), rot.quat_derivative_fast(q, w)

    wmax = np.nanmax(np.linalg.norm(omega_T, axis=-1)) if np.size(omega_T) else 0.0
    n = rk4_substeps(float(wmax) if np.isfinite(wmax) else 0.0, dt)
    n = min(n, 64)
    w_new, q_new = omega_T, q_TI
    for _ in range(n):
        w_new, q_new = rk4_step(f, (w_new, q_new), dt / n)
    return w_new, q_new


def propagate_rotation_compiled(
    omega_T: Array, q_TI: Array, k: Array, dt: float
) -> tuple[Array, Array]:
    """:func:`propagate_rotation` of stacks (..., 3), (..., 4), (..., 2) by the compiled loop
    (:func:`tumblenav.estimators.kabir2025.kernels.propagate_stack`): the same substeps and
    RK4, equal to rounding; for the filter's sigma points."""
    lead = np.shape(omega_T)[:-1]
    W, Q = kernels.propagate_stack(
        np.ascontiguousarray(omega_T, dtype=float).reshape(-1, 3),
        np.ascontiguousarray(q_TI, dtype=float).reshape(-1, 4),
        np.ascontiguousarray(k, dtype=float).reshape(-1, 2),
        float(dt),
        _MAX_TURN_PER_STEP,
        64,
    )
    return W.reshape(lead + (3,)), Q.reshape(lead + (4,))


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
    mass_centre = _mass_centre(scenario)
    assert mass_centre is not None  # check_scenario refuses a scenario without it
    r0_L, v_L = mass_centre
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


def _boxplus(x: Array, dx: Array) -> Array:
    """``x [+] dx`` for this layout (rate, attitude, inertia, features): the attitude by
    :func:`tumblenav.rotations.boxplus`, the rest by addition; broadcasts."""
    q = rot.boxplus_fast(x[..., 3:7], dx[..., 3:6])
    v = x[..., 0:3] + dx[..., 0:3]
    if q.shape[:-1] != v.shape[:-1]:
        q = np.broadcast_to(q, v.shape[:-1] + (4,))
    return np.concatenate([v, q, x[..., 7:] + dx[..., 6:]], axis=-1)


def world_chart_points(X: Array, runs: NDArray[np.bool_], to_world: bool) -> Array:
    """States (B, S, nom) of ``runs`` between the body chart (the filter's: rate and features
    in T) and the world chart (the rate and the features' offsets in I: ``R_IT omega``,
    ``R_IT p_i``; attitude and inertia ratios as they are). The projections and their flow
    depend on the state only through the world chart's rate and features (Kabir 2025 eq. 4,
    18-23), so in it a turn of the body frame alone -- the principal frame against the
    feature set, which only the Euler dynamics fix -- is the attitude block alone, and an
    update cannot learn it from the measurements (tumblenav, issue 18: in the body chart the
    filter's linearisation at moving estimates gave it information on that turn that the
    data do not hold, NEES 1e5 at 1e-6 rad of projection noise)."""
    R = rot.quat_to_matrix_fast(X[..., 3:7])  # R_TI (normalised)
    if to_world:
        R = np.swapaxes(R, -1, -2)  # R_IT
    Y = X.copy()
    Y[..., 0:3] = (R @ X[..., 0:3, None])[..., 0]
    p = X[..., 9:].reshape(X.shape[:-1] + (-1, 3))
    Y[..., 9:] = (p @ np.swapaxes(R, -1, -2)).reshape(X.shape[:-1] + (-1,))
    return np.where(runs[:, None, None], Y, X)


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
    qw, qq = tun.q_omega_var, tun.q_quat_var
    if qw is None or qq is None:
        raise ValueError("Q not resolved: call tuning.resolve_tuning first")
    qw3 = rate_q(qw).tolist()  # per principal axis of T (derive_tuning)
    if variant == "additive":
        v = qw3 + [qq] * 4
    else:
        v = qw3 + [4.0 * qq] * 3
    qk, qf = tun.q_k_var or 0.0, tun.q_feature_var or 0.0  # null: derived, 0 (rigid body)
    return np.diag(v + [qk] * 2 + [qf] * (3 * N))


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
