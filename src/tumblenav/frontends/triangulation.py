"""Stereo triangulation of feature points in the rig frame C (Hu 2024 Sec. 2.1, eq. 1).

Frame and pixel conventions (see :mod:`tumblenav.frames`)
---------------------------------------------------------
The rig frame C is attached to the left camera's centre of projection, ``x`` points towards
the right camera, ``y`` along the optical axis and ``z = x cross y``.  Every camera ``C_k``
uses the same axis convention, and a point ``p_inCk = (x, y, z)`` in front of it (``y > 0``)
projects to the pixel ::

    u = cu + f x / y,        v = cv + f z / y        (f, cu, cv in pixels)

Corrections to Hu 2024 eq. 1
----------------------------
The extracted eq. 1 reads ``m = [z u_l/f, z v_l/f, f b/(u_l - u_r)]``, i.e. it puts the
depth on ``z`` although the text of Sec. 2.1 puts the optical axis on ``y``.  With the
optical axis on ``y`` the depth is the *y* component::

    y = f b / (u_l - u_r),   x = y (u_l - cu) / f,   z = y (v_l - cv) / f

and pixel coordinates are measured from the principal point ``(cu, cv)`` (eq. 1 silently
assumes ``cu = cv = 0``).  Both corrections are applied in :func:`triangulate_parallel`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

__all__ = [
    "triangulate_parallel",
    "triangulate_two_ray",
    "triangulation_covariance",
    "triangulation_jacobian",
]


def triangulate_parallel(
    uv_left: ArrayLike,
    uv_right: ArrayLike,
    focal_px: ArrayLike,
    baseline_m: ArrayLike,
    principal_point_px: ArrayLike,
) -> Array:
    """Point in the rig frame C from a rectified, parallel stereo pair (Hu 2024 eq. 1, corrected).

    Parameters
    ----------
    uv_left, uv_right : array_like, shape (..., 2)
        Pixel coordinates ``(u, v)`` of the same feature in the left and right image (px).
        ``v_right`` is not used (eq. 1 takes the height from the left image only).
    focal_px : float or array_like broadcastable to (...)
        Focal length in pixels (the same for both cameras).
    baseline_m : float or array_like broadcastable to (...)
        Distance between the two centres of projection (m); the right camera sits at
        ``(b, 0, 0)`` in C.
    principal_point_px : array_like, shape (..., 2)
        Principal point ``(cu, cv)`` (px), the same for both cameras.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        ``p_inC = (x, y, z)`` in metres.  Rows whose disparity ``u_l - u_r`` is not strictly
        positive (point at or beyond infinity, or behind the rig), or whose input contains a
        NaN, are all-NaN; the function never returns ``inf`` and never raises on such data.
    """
    uv_l = np.asarray(uv_left, dtype=float)
    uv_r = np.asarray(uv_right, dtype=float)
    f = np.asarray(focal_px, dtype=float)
    b = np.asarray(baseline_m, dtype=float)
    pp = np.asarray(principal_point_px, dtype=float)

    disparity = uv_l[..., 0] - uv_r[..., 0]
    good = np.isfinite(disparity) & (disparity > 0.0) & np.isfinite(uv_l[..., 1])
    safe_d = np.where(good, disparity, 1.0)
    # Hu 2024 eq. 1, depth on the optical axis y (the extracted text divides by z instead).
    y = f * b / safe_d
    x = y * (uv_l[..., 0] - pp[..., 0]) / f
    z = y * (uv_l[..., 1] - pp[..., 1]) / f
    p = np.stack(np.broadcast_arrays(x, y, z), axis=-1)
    good = np.broadcast_to(good, p.shape[:-1]) & np.all(np.isfinite(p), axis=-1)
    return np.where(good[..., None], p, np.nan)


def _per_camera(value: ArrayLike, scalar_ndim: int) -> tuple[Array, Array]:
    """Split a per-camera parameter: a single value (ndim == scalar_ndim) or a left/right pair."""
    a = np.asarray(value, dtype=float)
    if a.ndim == scalar_ndim:
        return a, a
    if a.ndim == scalar_ndim + 1 and a.shape[0] == 2:
        return a[0], a[1]
    raise ValueError(
        f"expected one value of ndim {scalar_ndim} or a (left, right) pair, got shape {a.shape}"
    )


def _ray_in_rig(uv: Array, f: Array, pp: Array, R_CkC: Array) -> Array:
    """Direction (rig coordinates) of the viewing ray through pixel ``uv``; its Ck-y part is 1."""
    d_Ck = np.stack(
        np.broadcast_arrays((uv[..., 0] - pp[..., 0]) / f, 1.0, (uv[..., 1] - pp[..., 1]) / f),
        axis=-1,
    )
    # d_C = R_CkC^T d_Ck  (R_CkC maps rig coordinates into camera coordinates).
    return np.einsum("...ji,...j->...i", R_CkC, d_Ck)


def triangulate_two_ray(
    uv_left: ArrayLike,
    uv_right: ArrayLike,
    focal_px: ArrayLike,
    principal_point_px: ArrayLike,
    R_ClC: ArrayLike,
    p_ClinC: ArrayLike,
    R_CrC: ArrayLike,
    p_CrinC: ArrayLike,
) -> Array:
    """General two-ray triangulation for a convergent (or any calibrated) stereo rig.

    Each camera ``Ck`` (k = l, r) has the attitude ``R_CkC`` (maps rig coordinates into camera
    coordinates) and the centre of projection ``p_CkinC`` (rig frame, m).  The viewing ray of
    camera k is ``p_CkinC + s_k d_k`` with ``d_k = R_CkC^T [(u-cu)/f, 1, (v-cv)/f]``, so that
    ``s_k`` is the depth of the point along camera k's optical axis.  The result is the
    midpoint of the common perpendicular of the two rays (the classical "midpoint method"):
    with ``w0 = p_l - p_r``, ``a = d_l.d_l``, ``b = d_l.d_r``, ``c = d_r.d_r``,
    ``d = d_l.w0``, ``e = d_r.w0``::

        s_l = (b e - c d) / (a c - b^2),   s_r = (a e - b d) / (a c - b^2)
        p = ((p_l + s_l d_l) + (p_r + s_r d_r)) / 2

    For a parallel rig (``R_ClC = R_CrC = I``, ``p_r = (b, 0, 0)``) and ``v_l = v_r`` the rays
    intersect and the result equals :func:`triangulate_parallel`.

    Parameters
    ----------
    uv_left, uv_right : array_like, shape (..., 2)
        Pixel coordinates (px) of the feature in the left and right image.
    focal_px : float or (f_left, f_right)
        Focal length(s) in pixels.
    principal_point_px : (cu, cv) or ((cu_l, cv_l), (cu_r, cv_r))
        Principal point(s) in pixels.
    R_ClC, R_CrC : array_like, shape (3, 3) or (..., 3, 3)
        Rig-to-camera rotations of the left and right camera.
    p_ClinC, p_CrinC : array_like, shape (3,) or (..., 3)
        Centres of projection in the rig frame (m).  ``p_ClinC`` is usually zero (C is
        attached to the left camera) but any value is accepted.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        ``p_inC`` (m).  NaN where the rays are (numerically) parallel
        (``a c - b^2 <= 1e-12 a c``), where the point lies behind either camera
        (``s_l <= 0`` or ``s_r <= 0``), or where any input is NaN.
    """
    uv_l = np.asarray(uv_left, dtype=float)
    uv_r = np.asarray(uv_right, dtype=float)
    f_l, f_r = _per_camera(focal_px, 0)
    pp_l, pp_r = _per_camera(principal_point_px, 1)
    R_l = np.asarray(R_ClC, dtype=float)
    R_r = np.asarray(R_CrC, dtype=float)
    o_l = np.asarray(p_ClinC, dtype=float)
    o_r = np.asarray(p_CrinC, dtype=float)

    with np.errstate(invalid="ignore", divide="ignore"):
        d_l = _ray_in_rig(uv_l, f_l, pp_l, R_l)
        d_r = _ray_in_rig(uv_r, f_r, pp_r, R_r)
        w0 = o_l - o_r
        a = np.sum(d_l * d_l, axis=-1)
        b = np.sum(d_l * d_r, axis=-1)
        c = np.sum(d_r * d_r, axis=-1)
        d = np.sum(d_l * w0, axis=-1)
        e = np.sum(d_r * w0, axis=-1)
        den = a * c - b * b
        ok = np.isfinite(den) & (den > 1e-12 * a * c)
        den = np.where(ok, den, 1.0)
        s_l = (b * e - c * d) / den
        s_r = (a * e - b * d) / den
        ok &= (s_l > 0.0) & (s_r > 0.0)
        p = 0.5 * ((o_l + s_l[..., None] * d_l) + (o_r + s_r[..., None] * d_r))
    ok = ok & np.all(np.isfinite(p), axis=-1)
    return np.where(ok[..., None], p, np.nan)


def triangulation_jacobian(p_inC: ArrayLike, focal_px: ArrayLike, baseline_m: ArrayLike) -> Array:
    """Jacobian of eq. 1 (corrected) w.r.t. the pixels ``(u_l, v_l, u_r, v_r)``, at ``p_inC``.

    With ``d = u_l - u_r = f b / y`` (all in px, m)::

        dx/du_l = y/f - x y/(f b)   dx/du_r =  x y/(f b)
        dy/du_l =   - y^2/(f b)     dy/du_r =  y^2/(f b)
        dz/du_l =   - z y/(f b)     dz/du_r =  z y/(f b)     dz/dv_l = y/f

    and all other entries are zero (``v_r`` is not used by eq. 1).

    Parameters
    ----------
    p_inC : array_like, shape (..., 3)
        Triangulated point in the rig frame (m), ``y > 0``.
    focal_px, baseline_m : float or array_like broadcastable to (...)
        Focal length (px) and baseline (m) of the parallel rig.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 4)
        ``d p_inC / d (u_l, v_l, u_r, v_r)`` in m/px.
    """
    p = np.asarray(p_inC, dtype=float)
    f = np.asarray(focal_px, dtype=float)
    b = np.asarray(baseline_m, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    k = y / (f * b)  # = 1/d  (px^-1 times m/m)
    shape = np.broadcast_shapes(x.shape, k.shape)
    J = np.zeros(shape + (3, 4))
    J[..., 0, 0] = y / f - x * k
    J[..., 0, 2] = x * k
    J[..., 1, 0] = -y * k
    J[..., 1, 2] = y * k
    J[..., 2, 0] = -z * k
    J[..., 2, 1] = y / f
    J[..., 2, 2] = z * k
    return J


def triangulation_covariance(
    p_inC: ArrayLike, sigma_px: ArrayLike, focal_px: ArrayLike, baseline_m: ArrayLike
) -> Array:
    """First-order covariance of a parallel-rig triangulated point (Jacobian of eq. 1).

    ``Sigma_p = J diag(sigma^2) J^T`` with ``J`` from :func:`triangulation_jacobian` and
    independent, zero-mean pixel noise of standard deviation ``sigma_px`` on each of
    ``u_l, v_l, u_r, v_r``.  (Hu 2024 specifies the noise as an angular resolution
    ``sigma_rad``; the pixel equivalent is ``sigma_px = f * sigma_rad``.)  Depth noise grows
    as ``y^2``: ``sigma_y = sqrt(2) y^2 sigma_px / (f b)``.

    Parameters
    ----------
    p_inC : array_like, shape (..., 3)
        Point in the rig frame (m).
    sigma_px : float or array_like broadcastable to (...)
        Standard deviation of each pixel coordinate (px).
    focal_px, baseline_m : float or array_like broadcastable to (...)
        Focal length (px) and baseline (m).

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Covariance of ``p_inC`` (m^2).
    """
    J = triangulation_jacobian(p_inC, focal_px, baseline_m)
    s2 = np.asarray(sigma_px, dtype=float) ** 2
    return s2[..., None, None] * np.einsum("...ik,...jk->...ij", J, J)
