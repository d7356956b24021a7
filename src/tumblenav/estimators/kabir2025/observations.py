"""Kabir 2025's observations: the stereo projection, disparity and optical-flow model (eq. 16-27)
and the measurements and their variances prepared from stereo tracks."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.estimators.kabir2025 import kernels
from tumblenav.estimators.kabir2025.tuning import KabirTuning
from tumblenav.frontends import projections as proj

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


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


# Kabir 2025 eq. 27's five-point stencil: offsets (in dt) and weights (over 12 dt)
_STENCIL = ((-2, 1.0), (-1, -8.0), (1, 8.0), (2, -1.0))


def stencil_measurement_model(
    x: Array, R_CI: Array, rho0_C: Array, rho0_dot_C: Array, centres_x: Array, dt: float
) -> Array:
    """:func:`measurement_model` with the flow replaced by what eq. 27 makes of the predicted
    projections (tumblenav default ``flow_model: stencil``): each state ``x`` (..., nominal)
    is propagated by the torque-free model (:func:`~.model.propagate_rotation`, the inertia
    and features fixed) to ``t +- dt``, ``t +- 2 dt``, its projections there (the mass centre
    moving at ``rho0_dot_C``) go through the stencil
    ``(-w(t+2dt) + 8 w(t+dt) - 8 w(t-dt) + w(t-2dt)) / (12 dt)``, exactly as the measured
    flow does, so that eq. 27's truncation error is part of the model rather than of the
    noise."""
    from tumblenav.estimators.kabir2025.model import propagate_rotation

    h = measurement_model(x, R_CI, rho0_C, rho0_dot_C, centres_x)
    flow = np.zeros(h.shape[:-1] + (4,))
    for side in (1, -1):
        xs = x.copy()
        for step in (1, 2):
            w, q = propagate_rotation(xs[..., 0:3], xs[..., 3:7], xs[..., 7:9], side * dt)
            xs = np.concatenate([w, q, xs[..., 7:]], axis=-1)
            r0 = rho0_C + side * step * dt * rho0_dot_C
            wj = measurement_model(xs, R_CI, r0, rho0_dot_C, centres_x)[..., 0:4]
            weight = dict(_STENCIL)[side * step]
            flow += weight * wj
    h[..., 5:9] = flow / (12.0 * dt)
    return h


def stencil_measurement_model_compiled(
    x: Array, R_CI: Array, rho0_C: Array, rho0_dot_C: Array, centres_x: Array, dt: float
) -> Array:
    """:func:`stencil_measurement_model` of states ``x`` (..., nominal) at one epoch (``rho0_C``,
    ``rho0_dot_C`` (3,)) by the compiled loop
    (:func:`tumblenav.estimators.kabir2025.kernels.stencil_h`): equal to rounding; for the
    filter's sigma points. Returns (..., N, 9)."""
    from tumblenav.estimators.kabir2025.model import _MAX_TURN_PER_STEP

    nom = x.shape[-1]
    h = kernels.stencil_h(
        np.ascontiguousarray(x, dtype=float).reshape(-1, nom),
        np.ascontiguousarray(R_CI, dtype=float),
        np.ascontiguousarray(rho0_C, dtype=float),
        np.ascontiguousarray(rho0_dot_C, dtype=float),
        np.ascontiguousarray(centres_x, dtype=float),
        float(dt),
        _MAX_TURN_PER_STEP,
        64,
    )
    return h.reshape(x.shape[:-1] + h.shape[1:])


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
    if tun.frontend.flow_edges == "drop":
        flow = np.where(proj.finite_difference_order(w) == 4, flow, np.nan)
    disparity = w[..., 2:3] - w[..., 0:1]
    if not tun.use_disparity:  # u_L - u_R of the projections already in z: no information
        disparity = np.full_like(disparity, np.nan)
    z = np.concatenate([w, disparity, flow], axis=-1)
    sp, sd = projection_sigmas(tun, meas)
    so = tun.sigma_flow_rad_s
    if so is None:  # derived later (filter.prepare); meanwhile the sensor noise through eq. 27
        so = float(np.sqrt(130.0 / 144.0)) * sp / float(dts[0])
    var = np.array([sp**2] * 4 + [sd**2] + [so**2] * 4)
    return z, np.broadcast_to(var, z.shape).copy()
