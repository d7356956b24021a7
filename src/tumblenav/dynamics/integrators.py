"""Fixed-step integration and discretisation used by the filters: the one RK4 and the one
truncated-series ``(Phi, Q_k)`` of tumblenav.

* :func:`rk4_step`: one classical Runge-Kutta step of ``dy/dt = f(y)`` for a state made of
  several arrays (e.g. a quaternion and a rate), vectorised over leading axes.
* :func:`discretise`: ``Phi = exp(F dt)`` by its series to ``dt^4`` (Hu 2024 eq. 38) and the
  discrete process noise ``Q_k`` of a continuous ``Q_c`` by Van Loan's series to ``dt^3``
  (Hu 2024 eq. 39).

The compiled twin of :func:`rk4_step` for the torque-free attitude lives in
:mod:`tumblenav.dynamics.compiled`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["discretise", "rk4_step"]


def rk4_step(
    f: Callable[..., tuple[Array, ...]], y: tuple[Array, ...], dt: float
) -> tuple[Array, ...]:
    """One classical fourth-order Runge-Kutta step of ``dy/dt = f(*y)``.

    Parameters
    ----------
    f : callable
        ``f(*y) -> dy/dt``, a tuple shaped like ``y`` (autonomous: no time argument).
    y : tuple of arrays
        The state at the start of the step, split into arrays (e.g. ``(q_TI, omega_TI_T)``);
        any leading axes are carried along.
    dt : float
        Step (s).

    Returns
    -------
    tuple of arrays
        The state after ``dt``: ``y + dt/6 (k1 + 2 k2 + 2 k3 + k4)``.  Nothing is
        normalised (a quaternion stays as RK4 leaves it; the caller decides).
    """
    h = 0.5 * dt
    k1 = f(*y)
    k2 = f(*(yi + h * ki for yi, ki in zip(y, k1, strict=True)))
    k3 = f(*(yi + h * ki for yi, ki in zip(y, k2, strict=True)))
    k4 = f(*(yi + dt * ki for yi, ki in zip(y, k3, strict=True)))
    s = dt / 6
    return tuple(
        yi + s * (a + 2 * b + 2 * c + d) for yi, a, b, c, d in zip(y, k1, k2, k3, k4, strict=True)
    )


def discretise(F: Array, Qc: Array, dt: float) -> tuple[Array, Array]:
    """Transition matrix and process noise of ``dx/dt = F x + w``, ``E[w w^T] = Qc delta``,
    over a step ``dt``, by truncated series.

    .. math::

        \\Phi = I + A + A^2/2 + A^3/6 + A^4/24, \\quad A = F\\,\\Delta t
        \\quad \\text{(Hu 2024 eq. 38)}

        Q_k = Q_c \\Delta t + (F Q_c + Q_c F^T) \\Delta t^2/2
              + (F^2 Q_c + 2 F Q_c F^T + Q_c F^{T2}) \\Delta t^3/6
        \\quad \\text{(Hu 2024 eq. 39, Van Loan's series)}

    Parameters
    ----------
    F : (..., n, n)
        Continuous system matrix (1/s).
    Qc : (..., n, n)
        Continuous process noise spectral density (state units^2 / s).
    dt : float
        Step (s).

    Returns
    -------
    Phi, Q_k : (..., n, n)
        ``Q_k`` symmetrised.
    """
    A = F * dt
    A2 = A @ A
    eye = np.eye(F.shape[-1])
    Phi = eye + A + A2 / 2 + A2 @ A / 6 + A2 @ A2 / 24
    FQ = F @ Qc
    FQF = FQ @ np.swapaxes(F, -1, -2)
    F2Q = F @ FQ
    Qk = Qc * dt + (FQ + np.swapaxes(FQ, -1, -2)) * dt**2 / 2
    Qk = Qk + (F2Q + 2 * FQF + np.swapaxes(F2Q, -1, -2)) * dt**3 / 6
    return Phi, 0.5 * (Qk + np.swapaxes(Qk, -1, -2))
