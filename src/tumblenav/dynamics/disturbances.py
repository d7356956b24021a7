"""The truth's random disturbances: a white random torque on the target and a white random
force on its mass centre, with the spectral densities of the scenario's ``process_noise``.

Why: a filter's process noise Q states the disturbances it expects. Against a torque-free,
force-free truth any Q > 0 makes the filter conservative by design (NEES/dof below 1), so NEES
cannot judge it. With these disturbances on, the truth has exactly the statistics the filter's
Q describes, and NEES inside its bounds means the covariance is right.

Definitions (the same ones the filters' Q use; docs/conventions.md):

- Rotational, ``q_r`` (``process_noise.rotational_rad2_s4``): the disturbance torque is white
  and isotropic in the body (the same spectral density about every axis, uncorrelated between
  axes), scaled so that the angular acceleration about the axis of the LARGEST principal moment
  ``I_max`` has spectral density ``q_r`` (rad^2/s^3). About a principal axis of moment ``I_i``
  the angular acceleration then has spectral density ``q_r (I_max / I_i)^2``: Hu 2024 eq. 22's
  ``J = diag(1, I_x/I_y, I_x/I_z)`` in the DPACF frame (``x`` = the largest moment, Hu 2024
  Sec. 3.2). For a non-diagonal inertia ``I_T`` the angular acceleration's spectral density in
  T is ``q_r I_max^2 I_T^-2``.
- Translational, ``q_t`` (``process_noise.translational_m2_s4``): a white acceleration of the
  target's mass centre with spectral density ``q_t`` (m^2/s^3) per axis of L, uncorrelated
  between axes: the CW white-acceleration model of the filters
  (:func:`tumblenav.dynamics.relative_orbit.cw_discrete`, Hu 2024 eq. 38-39).

Over a step ``dt`` the rate then random-walks with covariance ``q_r I_max^2 I_T^-2 dt`` and the
velocity with ``q_t dt I_3``, whatever the integration step (the white noise is realised as a
zero-order hold of variance ``S / h`` over sub-steps of ``h``).

The attitude is integrated by RK4 on sub-steps of at most ``max_rotation_rad`` of rotation
(written here, compiled with numba: scipy's adaptive integrators cannot take a piecewise-constant
random input without restarting at every sub-step). The translational disturbance enters
through the CW (Hill) model, linear in the disturbance: the truth's relative orbit is the
nonlinear force-free one plus the CW response to the random force, drawn exactly from the
discrete CW model (transition and covariance of :func:`cw_discrete`). The neglected coupling
(the disturbance's effect on the nonlinear terms) is of order ``|dr| |r| n^2 / R_orbit``:
micrometres over the scenarios' ranges.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from tumblenav.dynamics.relative_orbit import cw_discrete
from tumblenav.rotations_compiled import quat_multiply

Array = NDArray[np.float64]

__all__ = [
    "angular_acceleration_psd",
    "disturbed_attitude",
    "translational_disturbance",
]


def angular_acceleration_psd(inertia_T: ArrayLike, q_r: float) -> Array:
    """(3, 3) spectral density (rad^2/s^3) in T of the angular acceleration that the isotropic
    disturbance torque causes: ``q_r I_max^2 I_T^-2`` (module docstring)."""
    J = np.asarray(inertia_T, dtype=float)
    if J.shape == (3,):
        J = np.diag(J)
    i_max = float(np.linalg.eigvalsh(J).max())
    Jinv = np.linalg.inv(J)
    return float(q_r) * i_max**2 * (Jinv @ Jinv)


@njit(cache=True, error_model="numpy")
def _rk4_disturbed(q0, w0, J, Jinv, t, n_sub, accel):  # pragma: no cover - compiled
    """RK4 of ``dq_TI/dt = -1/2 [w; 0] (x) q_TI`` and ``J w' = -w x (J w) + J a`` with ``a``
    held constant over each sub-step; ``n_sub[k]`` sub-steps between ``t[k]`` and ``t[k+1]``,
    ``accel`` (sum(n_sub), 3) the held angular accelerations. Returns q (n, 4), w (n, 3)."""
    n = t.shape[0]
    q_out = np.empty((n, 4))
    w_out = np.empty((n, 3))
    q = q0.copy()
    w = w0.copy()
    q_out[0] = q
    w_out[0] = w
    kq = np.zeros((4, 4))
    kw = np.zeros((4, 3))
    qs = np.empty(4)
    ws = np.empty(3)
    w4 = np.zeros(4)
    dq = np.empty(4)
    Jw = np.empty(3)
    c = np.empty(3)
    j = 0
    for k in range(n - 1):
        h = (t[k + 1] - t[k]) / n_sub[k]
        for _ in range(n_sub[k]):
            a = accel[j]
            j += 1
            for s in range(4):
                if s == 0:
                    qs[:] = q
                    ws[:] = w
                else:
                    hs = h if s == 3 else 0.5 * h
                    for i in range(4):
                        qs[i] = q[i] + hs * kq[s - 1, i]
                    for i in range(3):
                        ws[i] = w[i] + hs * kw[s - 1, i]
                w4[0], w4[1], w4[2] = ws[0], ws[1], ws[2]
                quat_multiply(w4, qs, dq)
                for i in range(4):
                    kq[s, i] = -0.5 * dq[i]
                for i in range(3):
                    Jw[i] = J[i, 0] * ws[0] + J[i, 1] * ws[1] + J[i, 2] * ws[2]
                c[0] = -(ws[1] * Jw[2] - ws[2] * Jw[1])  # -w x (J w)
                c[1] = -(ws[2] * Jw[0] - ws[0] * Jw[2])
                c[2] = -(ws[0] * Jw[1] - ws[1] * Jw[0])
                for i in range(3):
                    kw[s, i] = Jinv[i, 0] * c[0] + Jinv[i, 1] * c[1] + Jinv[i, 2] * c[2] + a[i]
            for i in range(4):
                q[i] += h / 6 * (kq[0, i] + 2 * kq[1, i] + 2 * kq[2, i] + kq[3, i])
            for i in range(3):
                w[i] += h / 6 * (kw[0, i] + 2 * kw[1, i] + 2 * kw[2, i] + kw[3, i])
            nq = np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
            for i in range(4):
                q[i] /= nq
        q_out[k + 1] = q
        w_out[k + 1] = w
    return q_out, w_out


def disturbed_attitude(
    q_TI0: ArrayLike,
    omega0_T: ArrayLike,
    inertia_T: ArrayLike,
    t: ArrayLike,
    q_r: float,
    rng: np.random.Generator,
    max_rotation_rad: float = 2e-3,
) -> tuple[Array, Array]:
    """Attitude ``q_TI`` (n, 4) and rate ``omega_TI_T`` (n, 3) at ``t`` under the random
    disturbance torque of spectral density ``q_r`` (module docstring); ``q_r = 0`` gives the
    torque-free motion (RK4 on sub-steps of at most ``max_rotation_rad``: a relative error of
    ~1e-10 per radian turned). Deterministic for a given ``rng`` state."""
    J = np.asarray(inertia_T, dtype=float)
    if J.shape == (3,):
        J = np.diag(J)
    t = np.asarray(t, dtype=float)
    q0 = np.asarray(q_TI0, dtype=float)
    q0 = q0 / np.linalg.norm(q0)
    w0 = np.asarray(omega0_T, dtype=float)
    S = angular_acceleration_psd(J, q_r)
    # sub-steps: small rotations; the rate bound grows with the random walk (6 sigma margin)
    dt = np.diff(t)
    w_max = float(np.linalg.norm(w0)) + 6.0 * np.sqrt(np.trace(S) * max(t[-1] - t[0], 0.0))
    n_sub = np.maximum(1, np.ceil(dt * w_max / max_rotation_rad)).astype(np.int64)
    n_tot = int(n_sub.sum())
    h = np.repeat(dt / n_sub, n_sub)
    if q_r > 0.0:
        L = np.linalg.cholesky(S)
        # zero-order hold of white noise of density S: variance S / h over a sub-step h
        accel = (rng.standard_normal((n_tot, 3)) @ L.T) / np.sqrt(h)[:, None]
    else:
        accel = np.zeros((n_tot, 3))
    q, w = _rk4_disturbed(q0, w0, J, np.linalg.inv(J), t, n_sub, accel)
    return q, w


def translational_disturbance(
    n_orbit: float, t: ArrayLike, q_t: float, rng: np.random.Generator
) -> tuple[Array, Array]:
    """The CW response ``(dr_L, dv_L)`` (n, 3) each, zero at ``t[0]``, to a white random
    acceleration of spectral density ``q_t`` per axis of L, drawn exactly from the discrete
    model ``dx_{k+1} = Phi dx_k + w_k``, ``w_k ~ N(0, Q_d)`` (:func:`cw_discrete`).
    ``n_orbit = 0``: no orbit (a double integrator)."""
    t = np.asarray(t, dtype=float)
    x = np.zeros((len(t), 6))
    if q_t <= 0.0:
        return x[:, :3], x[:, 3:]
    cache: dict[float, tuple[Array, Array]] = {}
    for k in range(len(t) - 1):
        dt = round(float(t[k + 1] - t[k]), 12)
        if dt not in cache:
            Phi, Qd = cw_discrete(n_orbit, q_t, dt)
            cache[dt] = (Phi, np.asarray(np.linalg.cholesky(0.5 * (Qd + Qd.T)), dtype=float))
        Phi, L = cache[dt]
        x[k + 1] = Phi @ x[k] + L @ rng.standard_normal(6)
    return x[:, :3], x[:, 3:]
