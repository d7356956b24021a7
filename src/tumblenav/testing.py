"""Helpers for the test suite: numerical Jacobians through boxplus/boxminus.

Every analytic Jacobian in tumblenav (Hu 2024 eq. 29-35, ...) is checked against
:func:`numerical_jacobian` on hypothesis-drawn states (``../shared/style.md``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

__all__ = ["KABIR_TORQUE_FREE", "numerical_jacobian"]

# The process noise the Kabir 2025 tests were written against (a scenario update): a torque-free
# truth and Hu 2024's default densities, as the built-in kabir2025 had before it got its quiet
# disturbance (issue 18). The tests check behaviours measured on that setting.
KABIR_TORQUE_FREE = {
    "process_noise.rotational_rad2_s4": 2.5e-5,
    "process_noise.translational_m2_s4": 2e-6,
    "process_noise.disturb_truth": False,
}


def numerical_jacobian(
    f: Callable[[Array], Any],
    x: ArrayLike,
    boxplus: Callable[[Array, Array], Array] | None = None,
    boxminus: Callable[[Any, Any], ArrayLike] | None = None,
    eps: float = 1e-6,
    dim: int | None = None,
) -> Array:
    r"""Central-difference Jacobian of ``f`` at ``x``, taken through boxplus and boxminus.

    Column ``j`` is

    .. math::

        J_{:,j} = \frac{(f(x \boxplus \epsilon e_j) \boxminus f(x))
                       - (f(x \boxplus (-\epsilon e_j)) \boxminus f(x))}{2 \epsilon},

    the derivative of the output error with respect to the input error, so that
    ``f(x [+] dx) [-] f(x) ~ J dx``.  Both differences are taken against ``f(x)`` (not
    against each other), which keeps manifold outputs (quaternions) on the chart of ``f(x)``.

    Parameters
    ----------
    f : callable
        Function of the (nominal) input; returns an array of any shape.
    x : array_like
        Point of linearisation (nominal representation, e.g. with quaternions).
    boxplus : callable, optional
        ``boxplus(x, dx) -> x'`` on the input; ``dx`` has shape ``(dim,)``.  Default:
        ``x + dx`` (``x`` flattened for the perturbation, then reshaped).
    boxminus : callable, optional
        ``boxminus(y, y0) -> dy`` on the output.  Default: ``y - y0``.  The result is flattened.
    eps : float
        Step of the central difference, in the units of the input error.  The default
        ``1e-6`` balances truncation (``eps^2``) and round-off (``1e-16 / eps``) for inputs
        and outputs of order one.
    dim : int, optional
        Size of the input error.  Default: ``x.size``; required when ``boxplus`` is given
        (the error of a manifold input is smaller than its nominal representation).

    Returns
    -------
    numpy.ndarray, shape (m, dim)
        ``m`` is the size of the flattened output error.
    """
    x = np.asarray(x, dtype=float)
    if boxplus is None:

        def boxplus(a: Array, d: Array) -> Array:
            return a + d.reshape(a.shape)

        n = x.size if dim is None else dim
    elif dim is None:
        raise ValueError("dim (the size of the input error) is required with a boxplus")
    else:
        n = dim
    if boxminus is None:

        def boxminus(a: Any, b: Any) -> Array:
            return np.asarray(a, dtype=float) - np.asarray(b, dtype=float)

    y0 = f(x)
    cols = []
    for j in range(n):
        e = np.zeros(n)
        e[j] = eps
        d_plus = np.ravel(boxminus(f(boxplus(x, e)), y0))
        d_minus = np.ravel(boxminus(f(boxplus(x, -e)), y0))
        cols.append((d_plus - d_minus) / (2.0 * eps))
    return np.stack(cols, axis=-1)
