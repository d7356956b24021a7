"""Compiled (numba) twin of the filters' attitude propagation, for the compiled loops.

:func:`rk4_attitude` is :func:`tumblenav.dynamics.integrators.rk4_step` applied to the
torque-free attitude, the quaternion kinematics (:func:`tumblenav.rotations.quat_derivative`)
with Euler's equations in principal axes written with their coefficients
(:func:`tumblenav.dynamics.rigid_body.euler_rhs_coefficients`).  It is inlined into its caller
(``inline="always"``), so it runs under the caller's floating-point licence; tested against
the numpy reference in ``tests/test_dynamics.py``.  As for
:mod:`tumblenav.rotations_compiled`: after editing it, clear the callers' numba caches.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from tumblenav.rotations_compiled import quat_multiply

__all__ = ["rk4_attitude"]


@njit(cache=True, inline="always", error_model="numpy")
def rk4_attitude(q, w, c, dt, q_out, w_out):
    """One RK4 step of ``dq_TI/dt = -1/2 [w; 0] (x) q_TI`` and
    ``w' = c * [wy wz, wx wz, wx wy]`` (``c`` (3,): Hu 2024 eq. 21's ``p``, or
    ``((I2 - I3)/I1, (I3 - I1)/I2, (I1 - I2)/I3)``) over ``dt`` (s), into ``q_out`` (4,),
    ``w_out`` (3,) (they may be ``q``, ``w``).  The quaternion is not normalised."""
    q0 = q.copy()
    w0 = w.copy()
    kq = np.zeros((4, 4))
    kw = np.zeros((4, 3))
    qs = q0.copy()
    ws = w0.copy()
    w4 = np.zeros(4)
    dq = np.empty(4)
    for s in range(4):
        if s > 0:
            h = dt if s == 3 else 0.5 * dt
            for i in range(4):
                qs[i] = q0[i] + h * kq[s - 1, i]
            for i in range(3):
                ws[i] = w0[i] + h * kw[s - 1, i]
        w4[0], w4[1], w4[2] = ws[0], ws[1], ws[2]
        quat_multiply(w4, qs, dq)  # dq/dt = -1/2 [w; 0] (x) q
        for i in range(4):
            kq[s, i] = -0.5 * dq[i]
        kw[s, 0] = c[0] * ws[1] * ws[2]  # Euler, Hu 2024 eq. 21-22
        kw[s, 1] = c[1] * ws[0] * ws[2]
        kw[s, 2] = c[2] * ws[0] * ws[1]
    for i in range(4):
        q_out[i] = q0[i] + dt / 6 * (kq[0, i] + 2 * kq[1, i] + 2 * kq[2, i] + kq[3, i])
    for i in range(3):
        w_out[i] = w0[i] + dt / 6 * (kw[0, i] + 2 * kw[1, i] + 2 * kw[2, i] + kw[3, i])
