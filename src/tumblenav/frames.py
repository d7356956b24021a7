"""Reference frames of tumblenav and the maps between them.

Frames
------
I   inertial (Earth-centred, equatorial axes).
L   the chaser's LVLH / Hill frame: origin at the chaser's centre of mass,
    ``x`` along-track, ``y = -orbit normal``, ``z = nadir`` (towards the Earth's centre).
    In this frame the Clohessy-Wiltshire (Hill) matrices of Hu 2024 eq. 4-5 and
    Yu 2019 eq. 26-27 hold exactly as printed.
B   chaser body frame (its attitude ``q_BI`` is known to the chaser's own ADCS).
C   stereo rig / sensor frame, attached to the left camera's centre of projection:
    ``x`` towards the right camera (baseline), ``y`` along the optical axis (boresight),
    ``z = x cross y`` (Hu 2024 Sec. 2.1; Kabir 2025 eq. 16-17 also put the optical axis on y).
    Each camera k of the rig has its own frame ``C_k`` with the same axis convention.
T   target principal-axis body frame, origin at the target's mass centre.
G   photogrammetric frame of Hu 2024 eq. 6-7, fixed to the target, built from three features.

Naming: ``R_AB`` maps coordinates in B into A (``v_A = R_AB @ v_B``), ``q_AB`` is its
quaternion (see :mod:`tumblenav.rotations`), ``p_XinA`` the position of X expressed in A,
``omega_AB_C`` the angular velocity of A relative to B expressed in C.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

MU_EARTH_M3_S2 = 3.986004418e14  # EGM96 / WGS-84 gravitational parameter
R_EARTH_M = 6378137.0  # WGS-84 equatorial radius
J2_EARTH = 1.08262668e-3


def lvlh_axes(r_I: ArrayLike, v_I: ArrayLike) -> Array:
    """``R_IL``: columns are the L axes (x along-track, y = -orbit normal, z = nadir) in I.

    Accepts stacks (..., 3); returns (..., 3, 3).
    """
    r = np.asarray(r_I, dtype=float)
    v = np.asarray(v_I, dtype=float)
    z = -r / np.linalg.norm(r, axis=-1, keepdims=True)
    h = np.cross(r, v)
    y = -h / np.linalg.norm(h, axis=-1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def lvlh_rate(r_I: ArrayLike, v_I: ArrayLike) -> Array:
    """``omega_LI_L``: angular velocity of L relative to I, expressed in L (rad/s).

    For a Keplerian orbit, L rotates about its ``y`` axis (the negative orbit normal) at
    ``-|h|/|r|^2``: ``omega_LI_L = [0, -|h|/|r|^2, 0]``.
    """
    r = np.asarray(r_I, dtype=float)
    v = np.asarray(v_I, dtype=float)
    h = np.linalg.norm(np.cross(r, v), axis=-1)
    rn2 = np.sum(r * r, axis=-1)
    out = np.zeros(np.broadcast_shapes(r.shape, v.shape))
    out[..., 1] = -h / rn2
    return out


def inertial_to_lvlh(
    r_chaser_I: ArrayLike, v_chaser_I: ArrayLike, r_target_I: ArrayLike, v_target_I: ArrayLike
) -> tuple[Array, Array]:
    """Relative position and velocity of the target in L (velocity as seen from rotating L)."""
    R_IL = lvlh_axes(r_chaser_I, v_chaser_I)
    w_L = lvlh_rate(r_chaser_I, v_chaser_I)
    dr_I = np.asarray(r_target_I, float) - np.asarray(r_chaser_I, float)
    dv_I = np.asarray(v_target_I, float) - np.asarray(v_chaser_I, float)
    r_L = np.einsum("...ji,...j->...i", R_IL, dr_I)
    v_L = np.einsum("...ji,...j->...i", R_IL, dv_I) - np.cross(w_L, r_L)
    return r_L, v_L


def lvlh_to_inertial(
    r_chaser_I: ArrayLike, v_chaser_I: ArrayLike, r_L: ArrayLike, v_L: ArrayLike
) -> tuple[Array, Array]:
    """Inverse of :func:`inertial_to_lvlh`: the target's inertial position and velocity."""
    R_IL = lvlh_axes(r_chaser_I, v_chaser_I)
    w_L = lvlh_rate(r_chaser_I, v_chaser_I)
    r_L = np.asarray(r_L, float)
    v_L = np.asarray(v_L, float)
    r_I = np.asarray(r_chaser_I, float) + np.einsum("...ij,...j->...i", R_IL, r_L)
    v_I = np.asarray(v_chaser_I, float) + np.einsum(
        "...ij,...j->...i", R_IL, v_L + np.cross(w_L, r_L)
    )
    return r_I, v_I
