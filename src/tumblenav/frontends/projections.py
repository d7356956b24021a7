"""Normalised stereo projections, their finite-difference rates and Kabir 2025's observation
model (Sec. 2.2.2, eq. 16-25, Appendix A).

Notation
--------
Kabir & Bai (Sensors 2025) write the projections in rad (focal length ``f = 1``, principal
point removed), per feature in the order ``[u_R, v_R, u_L, v_L]``.  Kabir's R camera is our
RIGHT camera (rig index 1) and Kabir's L camera our LEFT camera (rig index 0): Kabir puts the
right camera at his origin and writes ``u_L = f (x + b)/y`` (eq. 17), which is only consistent
with the left camera at ``[-b, 0, 0]`` (see :mod:`tumblenav.sensors.stereo`).  In our rig frame
C (left camera at the origin, right camera at ``[b, 0, 0]``)::

    u_L = x / y,   u_R = (x - b) / y,   v_L = v_R = z / y,   u_L - u_R = b / y > 0.

The functions below take the camera centres' ``x`` coordinates in C in the rig's camera order
``centres_x = (x_left, x_right)`` (``(0, b)`` for :func:`tumblenav.sensors.parallel_rig`), so
the same code serves any parallel rig.

Optical flow (Kabir 2025 eq. 18-21, Appendix A): a point ``rho`` (in C) of a body rotating
rigidly with angular velocity ``omega`` (in C) about its mass centre ``rho0`` moves with
``rho_dot = omega x (rho - rho0) (+ rho0_dot)``, and with ``J = d(u, v)/d rho`` of one camera::

    w_dot = J rho_dot = A omega (+ J rho0_dot),    A = J [(rho0 - rho) x].

The extracted text of eq. 20-21 / A7-A8 has lost all its minus signs; derived here:

    A_R = [[ x(z-z0)/y^2,            (z-z0)/y,   -(y-y0)/y - x(x-x0)/y^2 ],
           [ (y-y0)/y + z(z-z0)/y^2, -(x-x0)/y,  -z(x-x0)/y^2            ]]

with ``x`` measured from the camera's centre (Kabir's R camera at his origin); A_L is the
same with ``x -> x + b`` and ``x0 -> x0 + b`` in Kabir's frame, i.e. ``x`` measured from the
left camera centre in ours.  The tests check both against finite differences of the
projections along a simulated trajectory.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from tumblenav import rotations as rot
from tumblenav.errors import InputError

if TYPE_CHECKING:
    from tumblenav.measurements import StereoMeasurements
    from tumblenav.sensors.stereo import StereoRig

Array = NDArray[np.float64]

__all__ = [
    "KABIR_H_NAMES",
    "finite_difference_order",
    "finite_difference_rate",
    "flow_matrices",
    "kabir_h",
    "normalised",
    "parallel_centres_x",
    "projection_jacobian",
    "projection_model",
]

# Kabir 2025 eq. 23: the nine components of h_i, in order.
KABIR_H_NAMES = ("u_R", "v_R", "u_L", "v_L", "disparity", "du_R", "dv_R", "du_L", "dv_L")


def parallel_centres_x(rig: StereoRig) -> Array:
    """``(x_left, x_right)`` (m) of a parallel rig's centres in C; InputError otherwise.

    Kabir 2025's model (eq. 16-17) needs both cameras aligned with C (optical axis ``y``) and
    their centres on C's ``x`` axis.
    """
    R = rig.R_CkC
    c = rig.centres_inC
    if not np.allclose(R, np.eye(3), atol=1e-12) or not np.allclose(c[:, 1:], 0.0, atol=1e-12):
        raise InputError(
            "Kabir 2025's observation model needs a parallel stereo rig (cameras aligned with "
            f"the rig frame, centres on its x axis); got a {rig.kind} rig"
        )
    return np.array(c[:, 0], dtype=float)


def normalised(meas: StereoMeasurements) -> tuple[Array, NDArray[np.bool_]]:
    """Pixel measurements -> Kabir 2025's normalised projections (rad, ``f = 1``).

    Parameters
    ----------
    meas : StereoMeasurements
        ``uv`` (n, 2, N, 2) px, camera 0 = left, 1 = right; a parallel rig.

    Returns
    -------
    w : (n, N, 4) array
        ``[u_R, v_R, u_L, v_L]`` (rad) per feature (Kabir 2025 eq. 16-17: R = our right
        camera, L = our left camera); NaN where that camera did not observe the feature.
    observed : (n, N) bool array
        True where both cameras observed the feature (a stereo pair).
    """
    parallel_centres_x(meas.rig)
    cams = meas.rig.cameras
    f = np.array([c.focal_px for c in cams])[:, None, None]  # (2, 1, 1)
    pp = np.array([c.principal_point_px for c in cams])[:, None, :]  # (2, 1, 2)
    obs = np.asarray(meas.observed, dtype=bool)
    x = (np.asarray(meas.uv, dtype=float) - pp) / f  # (n, 2, N, 2)
    x = np.where(obs[..., None], x, np.nan)
    w = np.concatenate([x[:, 1], x[:, 0]], axis=-1)  # right (Kabir R), then left (Kabir L)
    return w, np.all(obs, axis=1)


def finite_difference_rate(w: ArrayLike, dt: float) -> Array:
    """Time derivative along axis 0 by Kabir 2025 eq. 27, on every run of finite samples.

    On each contiguous run of finite samples (a NaN splits the series): first-order forward
    difference at the run's first sample, second-order central at its second and
    next-to-last, first-order backward at its last, fourth-order central elsewhere,
    ``(-w[k+2] + 8 w[k+1] - 8 w[k-1] + w[k-2]) / (12 dt)`` (the extracted eq. 27 lost its
    minus signs).  A run of one sample has no rate (NaN).

    Parameters
    ----------
    w : (n, ...) array
        Samples at a uniform step; any trailing shape, each element its own series.
    dt : float
        Sample step (s).

    Returns
    -------
    (n, ...) array
        Rate (units of ``w`` per second); NaN where ``w`` is NaN or a run has one sample.
    """
    w = np.asarray(w, dtype=float)
    n = w.shape[0]
    ok = np.isfinite(w)
    a, b = _run_position(ok)
    pad = np.full((2,) + w.shape[1:], np.nan)
    wp = np.concatenate([pad, w, pad], axis=0)
    m2, m1, p1, p2 = wp[0:n], wp[1 : n + 1], wp[3 : n + 3], wp[4 : n + 4]
    # Kabir 2025 eq. 27 (with its minus signs restored)
    return np.select(
        [~ok | ((a == 0) & (b == 0)), a == 0, b == 0, (a == 1) | (b == 1)],
        [
            np.nan,
            (p1 - w) / dt,
            (w - m1) / dt,
            (p1 - m1) / (2.0 * dt),
        ],
        default=(-p2 + 8.0 * p1 - 8.0 * m1 + m2) / (12.0 * dt),
    )


def _run_position(ok: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Finite samples before (a) and after (b) each sample within its run, along axis 0."""
    n = ok.shape[0]
    idx = np.arange(n).reshape((n,) + (1,) * (ok.ndim - 1))
    a = idx - np.maximum.accumulate(np.where(ok, -1, idx), axis=0) - 1
    after = np.flip(np.minimum.accumulate(np.flip(np.where(ok, n, idx), 0), axis=0), 0)
    return a, after - idx - 1


def finite_difference_order(w: ArrayLike) -> NDArray[np.int64]:
    """Order of accuracy of :func:`finite_difference_rate` at each sample (n, ...): 4 inside
    a run, 2 at its second and next-to-last samples, 1 at its ends, 0 where there is no rate."""
    ok = np.isfinite(np.asarray(w, dtype=float))
    a, b = _run_position(ok)
    m = np.minimum(a, b)
    order = np.select([m >= 2, m == 1], [4, 2], default=1)
    return np.where(ok & ((a > 0) | (b > 0)), order, 0)


def projection_model(rho_C: ArrayLike, centres_x: ArrayLike) -> Array:
    """Normalised projections of points in C into both cameras (Kabir 2025 eq. 16-17).

    Parameters
    ----------
    rho_C : (..., 3) array
        Points in the rig frame C (m), in front of the rig (``y > 0``).
    centres_x : (2,) array
        ``(x_left, x_right)`` of the camera centres in C (m).

    Returns
    -------
    (..., 2, 2) array
        ``[[u, v] of the left camera, [u, v] of the right camera]`` (rad), in the rig's
        camera order (0 = left = Kabir's L, 1 = right = Kabir's R).
    """
    rho = np.asarray(rho_C, dtype=float)
    cx = np.asarray(centres_x, dtype=float)
    y = rho[..., 1:2]
    u = (rho[..., :1] - cx) / y  # (..., 2)
    v = np.broadcast_to(rho[..., 2:3] / y, u.shape)
    return np.stack([u, v], axis=-1)


def projection_jacobian(rho_C: ArrayLike, centres_x: ArrayLike) -> Array:
    """``d(u, v)/d rho`` of each camera, (..., 2 cameras, 2, 3) (rig camera order).

    ``du/drho = [1/y, -(x - c)/y^2, 0]``, ``dv/drho = [0, -z/y^2, 1/y]`` (Kabir 2025 eq. A1-A2).
    """
    rho = np.asarray(rho_C, dtype=float)
    cx = np.asarray(centres_x, dtype=float)
    x, y, z = rho[..., 0:1], rho[..., 1:2], rho[..., 2:3]
    iy = 1.0 / y
    zero = np.zeros(x.shape[:-1] + (2,))
    du = np.stack([np.broadcast_to(iy, zero.shape), -(x - cx) * iy**2, zero], -1)
    dv = np.stack(
        [zero, np.broadcast_to(-z * iy**2, zero.shape), np.broadcast_to(iy, zero.shape)], -1
    )
    return np.stack([du, dv], axis=-2)


def flow_matrices(rho_C: ArrayLike, rho0_C: ArrayLike, centres_x: ArrayLike) -> tuple[Array, Array]:
    """Kabir 2025 eq. 18-21 (Appendix A): ``w_dot_R = A_R omega``, ``w_dot_L = A_L omega``.

    Kabir 2025 eq. 20-21, corrected: the extracted matrices lost their minus signs; derived
    as ``A = J [(rho0 - rho) x]`` (module notes), valid for any parallel rig.

    Parameters
    ----------
    rho_C : (..., 3) array
        Feature position in C (m).
    rho0_C : (..., 3) array
        The target's mass centre in C (m), the centre of the rotation.
    centres_x : (2,) array
        ``(x_left, x_right)`` of the camera centres in C (m).

    Returns
    -------
    A_R, A_L : (..., 2, 3) arrays
        Flow of ``[u, v]`` (rad/s) of Kabir's R (our right) and L (our left) camera per unit
        angular velocity of the target expressed in C (rad/s).
    """
    rho = np.asarray(rho_C, dtype=float)
    J = projection_jacobian(rho, centres_x)  # (..., 2, 2, 3)
    A = J @ rot.skew(np.asarray(rho0_C, dtype=float) - rho)[..., None, :, :]
    return A[..., 1, :, :], A[..., 0, :, :]


def kabir_h(
    rho_C: ArrayLike,
    rho0_C: ArrayLike,
    omega_C: ArrayLike,
    centres_x: ArrayLike,
    rho0_dot_C: ArrayLike | None = None,
) -> Array:
    """Kabir 2025 eq. 22-23: ``h_i = [u_R, v_R, u_L, v_L, u_L - u_R, du_R, dv_R, du_L, dv_L]``.

    The flow is ``A omega`` of :func:`flow_matrices` (plus ``J rho0_dot`` when the mass centre
    moves), evaluated without forming ``A``: ``rho_dot = omega x (rho - rho0) + rho0_dot`` and
    ``du = (x_dot - u y_dot)/y``, ``dv = (z_dot - v y_dot)/y``.  Vectorised over all leading
    axes (sigma points, runs, time).

    Parameters
    ----------
    rho_C : (..., N, 3) array
        Feature positions in C (m).
    rho0_C : (..., 3) array
        Mass centre in C (m).
    omega_C : (..., 3) array
        Angular velocity of the target w.r.t. the (inertially fixed) rig, in C (rad/s).
    centres_x : (2,) array
        ``(x_left, x_right)`` (m).
    rho0_dot_C : (..., 3) array, optional
        Velocity of the mass centre in C (m/s); Kabir 2025 Sec. 2.1 has it zero.

    Returns
    -------
    (..., N, 9) array
        rad and rad/s.
    """
    rho = np.asarray(rho_C, dtype=float)
    r0 = np.asarray(rho0_C, dtype=float)[..., None, :]
    om = np.asarray(omega_C, dtype=float)[..., None, :]
    cl, cr = (float(c) for c in np.asarray(centres_x, dtype=float))
    x, y, z = rho[..., 0], rho[..., 1], rho[..., 2]
    iy = 1.0 / y
    u_L, u_R, v = (x - cl) * iy, (x - cr) * iy, z * iy
    r = rho - r0  # rho_dot = omega x r (+ rho0_dot), written out (np.cross is slow on stacks)
    ox, oy, oz = om[..., 0], om[..., 1], om[..., 2]
    xd = oy * r[..., 2] - oz * r[..., 1]
    yd = oz * r[..., 0] - ox * r[..., 2]
    zd = ox * r[..., 1] - oy * r[..., 0]
    if rho0_dot_C is not None:
        v0 = np.asarray(rho0_dot_C, dtype=float)[..., None, :]
        xd, yd, zd = xd + v0[..., 0], yd + v0[..., 1], zd + v0[..., 2]
    du_L, du_R, dv = (xd - u_L * yd) * iy, (xd - u_R * yd) * iy, (zd - v * yd) * iy
    return np.stack([u_R, v, u_L, v, u_L - u_R, du_R, dv, du_L, dv], axis=-1)


class ProjectionsTuning(BaseModel):
    """Settings of the projections front end (Kabir 2025 eq. 16-27), under
    ``estimator.tuning.frontend`` of ukf, ukf-mult and ukf-gp (the same keys at the top of
    ``estimator.tuning`` are still read, as before)."""

    model_config = ConfigDict(extra="forbid")
    flow_edges: Literal["drop", "paper"] = Field(
        "drop",
        description="'drop': no flow where Kabir 2025 eq. 27 falls back to its first- and "
        "second-order differences (two samples at each end of every run of measurements: their "
        "truncation error is tens to hundreds of sigma_o at the paper's tuning); 'paper': use "
        "eq. 27 everywhere",
    )
