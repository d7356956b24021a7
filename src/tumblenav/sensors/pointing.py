"""Attitude of the stereo rig frame C relative to the chaser's LVLH frame L.

``R_LC`` maps rig coordinates into L (its columns are the C axes expressed in L), so a feature
at ``p_inL`` relative to the chaser is seen at ``p_inC = R_LC.T @ p_inL`` (taking the rig
origin at the chaser's centre of mass; add a lever arm upstream if needed).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

__all__ = ["fixed_R_LC", "target_pointing_R_LC"]

# Below this |sin(angle between boresight and hint)| the hint is treated as parallel.
_PARALLEL_TOL = 1e-6


def _unit(v: Array) -> Array:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def target_pointing_R_LC(r_target_L: ArrayLike, up_hint_L: ArrayLike = (0.0, 0.0, -1.0)) -> Array:
    """Rig attitude whose boresight (C's ``y`` axis) points at the target centre.

    An ideal target-tracking attitude (Chang 2021 Sec. 3 keeps the *left camera* on the
    target; for a convergent rig the rig ``y`` axis is not the left camera's boresight, which
    is toed in by ``alpha``).  ``y_C = r / |r|``; ``z_C`` is the unit vector perpendicular to
    ``y_C`` closest to ``up_hint_L`` (the normalised projection of the hint); ``x_C = y_C x z_C``
    completes the right-handed frame (then ``z_C = x_C x y_C`` as in :mod:`tumblenav.frames`).
    Where the boresight is (anti)parallel to the hint, the L axis least aligned with the hint
    is used as the hint instead (for the default hint: L's ``x``, along-track).

    Parameters
    ----------
    r_target_L : (..., 3) array
        Target centre relative to the chaser (rig origin), expressed in L (m); nonzero.
    up_hint_L : (3,) or (..., 3) array, optional
        Desired direction of C's ``z`` axis in L; default zenith ``-z_L`` (L's ``z`` is nadir).

    Returns
    -------
    (..., 3, 3) array
        ``R_LC`` with columns ``[x_C, y_C, z_C]`` expressed in L.
    """
    r = np.asarray(r_target_L, dtype=float)
    hint = np.asarray(up_hint_L, dtype=float)
    if np.any(np.linalg.norm(r, axis=-1) == 0.0):
        raise ValueError("r_target_L must be nonzero")
    if np.any(np.linalg.norm(hint, axis=-1) == 0.0):
        raise ValueError("up_hint_L must be nonzero")
    y = _unit(r)
    hint = _unit(np.broadcast_to(hint, np.broadcast_shapes(hint.shape, y.shape)))
    # Fallback hint: the L axis least aligned with the hint (perpendicular-ish to it, hence to
    # a boresight that is parallel to it).
    k = np.argmin(np.abs(hint), axis=-1)
    fallback = np.eye(3)[k]
    z = hint - np.sum(hint * y, axis=-1, keepdims=True) * y
    parallel = np.linalg.norm(z, axis=-1, keepdims=True) < _PARALLEL_TOL
    z_fb = fallback - np.sum(fallback * y, axis=-1, keepdims=True) * y
    z = _unit(np.where(parallel, z_fb, z))
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def fixed_R_LC(R_BC: ArrayLike, R_LB: ArrayLike | None = None) -> Array:
    """Rig attitude for a camera hard-mounted on the chaser body: ``R_LC = R_LB @ R_BC``.

    Parameters
    ----------
    R_BC : (..., 3, 3) array
        Mounting rotation, rig frame C into body frame B.
    R_LB : (..., 3, 3) array, optional
        Chaser body attitude relative to LVLH; default identity (an LVLH-pointing chaser,
        body axes = L axes).

    Returns
    -------
    (..., 3, 3) array
        ``R_LC``.
    """
    R_BC = np.asarray(R_BC, dtype=float)
    if R_LB is None:
        return R_BC.copy()
    return np.matmul(np.asarray(R_LB, dtype=float), R_BC)
