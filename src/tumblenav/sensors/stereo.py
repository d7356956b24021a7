"""Pinhole stereo rig: geometry, projection of feature points and noisy pixel measurements.

Frames and conventions (see :mod:`tumblenav.frames`)
----------------------------------------------------
* ``C`` is the rig frame, attached to the left camera's centre of projection: ``x`` towards
  the right camera (baseline), ``y`` along the optical axis (boresight), ``z = x cross y``
  (Hu 2024 Sec. 2.1).
* Every camera ``k`` has its own frame ``C_k`` with the same axis convention (``x`` right,
  ``y`` optical axis, ``z = x cross y``).  ``R_CkC`` maps rig coordinates into ``C_k`` and
  ``p_CkinC`` is the camera's centre of projection in ``C``, so a point ``p`` in C has
  ``p_Ck = R_CkC (p - p_CkinC)``.
* Pinhole projection with ``y`` as the depth axis::

      u = cu + f x / y,     v = cv + f z / y          (pixels)

  This is the projection behind Hu 2024 eq. 1 and Kabir 2025 eq. 16-17 (both put the optical
  axis on ``y``).  Note that ``v`` grows along ``+z`` of the camera frame.
* Shapes: points ``(..., N, 3)``; pixel coordinates ``(..., 2, N, 2)`` with the camera index
  (0 = left, 1 = right) before the feature index and ``(u, v)`` last; masks ``(..., 2, N)``.
  Leading axes ``...`` are typically time.

Paper notes
-----------
* Hu 2024 eq. 1 is printed as ``m = [z u_l/f, z v_l/f, f b/(u_l - u_r)]``: it divides by ``z``
  although the text makes ``y`` the optical axis, and it omits the principal point.  The
  consistent form (implemented by :func:`project` and inverted in the tests) is
  ``y = f b / (u_l - u_r)``, ``x = y (u_l - cu)/f``, ``z = y (v_l - cv)/f``.
* Kabir 2025 eq. 16-17 put the right camera at the origin and write the left projection as
  ``u_L = f (x + b)/y`` while the text places the left camera at ``[b, 0, 0]``; the equations
  are only consistent with the left camera at ``[-b, 0, 0]`` (then ``u_L - u_R = f b / y``,
  as here with the left camera at the origin and the right one at ``[b, 0, 0]``).
* Chang 2021 (Table 1, Sec. 3.2): see :func:`chang2021_rig`.  Chang 2021 eq. 31 (convergent
  triangulation, depth ``Z`` along the left optical axis, ``alpha`` = toe-in per camera) is
  printed with ``... cos(alpha) + sin(alpha)`` in the numerator; for inward-tilted cameras
  the right centre lies ``b sin(alpha)`` *in front of* the left camera and the correct term
  is ``cos(alpha) - sin(alpha)``, i.e.
  ``Z = f b (T cos a - sin a) / (T (u_l - u_l0) - f)``,
  ``T = tan(2a + atan((u_r0 - u_r)/f) - pi/2)``
  (the printed ``arctan^{-1}`` is a plain ``arctan``).  The tests check this corrected form
  against :func:`project`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "Camera",
    "StereoMeasurement",
    "StereoRig",
    "angular_noise_to_px",
    "chang2021_rig",
    "chang2021_text_rig",
    "convergent_rig",
    "disparity",
    "measure",
    "parallel_rig",
    "project",
]

_RIG_KINDS = ("parallel", "convergent")


def _frozen_array(a: ArrayLike, shape: tuple[int, ...], name: str) -> Array:
    out = np.array(a, dtype=float)
    if out.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {out.shape}")
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Camera:
    """One pinhole camera of a stereo rig (no distortion).

    Parameters
    ----------
    focal_px : float
        Focal length in pixels (px).
    principal_point_px : tuple of float
        Principal point ``(cu, cv)`` (px).
    resolution_px : tuple of int
        Image size ``(width, height)`` (px); the image spans ``[0, width] x [0, height]``.
    R_CkC : (3, 3) array
        Rotation mapping rig-frame ``C`` coordinates into this camera's frame ``C_k``.
    p_CkinC : (3,) array
        Centre of projection of this camera, expressed in ``C`` (m).
    """

    focal_px: float
    principal_point_px: tuple[float, float]
    resolution_px: tuple[int, int]
    R_CkC: Array = field(default_factory=lambda: np.eye(3))
    p_CkinC: Array = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if not self.focal_px > 0.0:
            raise ValueError(f"focal_px must be positive, got {self.focal_px}")
        cu, cv = (float(c) for c in self.principal_point_px)
        w, h = (int(r) for r in self.resolution_px)
        if w <= 0 or h <= 0:
            raise ValueError(f"resolution_px must be positive, got {self.resolution_px}")
        R = _frozen_array(self.R_CkC, (3, 3), "R_CkC")
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0.0):
            raise ValueError("R_CkC must be a proper rotation matrix")
        object.__setattr__(self, "focal_px", float(self.focal_px))
        object.__setattr__(self, "principal_point_px", (cu, cv))
        object.__setattr__(self, "resolution_px", (w, h))
        object.__setattr__(self, "R_CkC", R)
        object.__setattr__(self, "p_CkinC", _frozen_array(self.p_CkinC, (3,), "p_CkinC"))

    @property
    def fov_rad(self) -> tuple[float, float]:
        """Full field of view ``(horizontal, vertical)`` (rad) of the image rectangle.

        ``atan(cu/f) + atan((W - cu)/f)``, i.e. ``2 atan(W / 2f)`` for a centred principal point.
        """
        f = self.focal_px
        cu, cv = self.principal_point_px
        w, h = self.resolution_px
        return (
            float(np.arctan(cu / f) + np.arctan((w - cu) / f)),
            float(np.arctan(cv / f) + np.arctan((h - cv) / f)),
        )

    @property
    def boresight_inC(self) -> Array:
        """Unit optical axis (the ``C_k`` ``y`` axis) expressed in the rig frame ``C``."""
        return np.array(self.R_CkC[1, :])


@dataclass(frozen=True, eq=False)
class StereoRig:
    """Two cameras expressed in the rig frame ``C`` (attached to the left camera).

    Parameters
    ----------
    left, right : Camera
        Camera 0 (left, centre at the origin of ``C``) and camera 1 (right).
    kind : str
        ``'parallel'`` (both optical axes along ``y``) or ``'convergent'`` (toed in).
    """

    left: Camera
    right: Camera
    kind: str = "parallel"

    def __post_init__(self) -> None:
        if self.kind not in _RIG_KINDS:
            raise ValueError(f"kind must be one of {_RIG_KINDS}, got {self.kind!r}")

    @property
    def cameras(self) -> tuple[Camera, Camera]:
        """``(left, right)``, in the order of the camera axis of :func:`project`."""
        return (self.left, self.right)

    @property
    def baseline_m(self) -> float:
        """Distance between the two centres of projection (m)."""
        return float(np.linalg.norm(self.right.p_CkinC - self.left.p_CkinC))

    @property
    def centres_inC(self) -> Array:
        """Centres of projection of (left, right), shape (2, 3), in ``C`` (m)."""
        return np.stack([self.left.p_CkinC, self.right.p_CkinC])

    @property
    def R_CkC(self) -> Array:
        """Stacked rotations ``R_CkC`` of (left, right), shape (2, 3, 3)."""
        return np.stack([self.left.R_CkC, self.right.R_CkC])


def _default_pp(
    resolution_px: tuple[int, int], pp: tuple[float, float] | None
) -> tuple[float, float]:
    if pp is None:
        return (0.5 * resolution_px[0], 0.5 * resolution_px[1])
    return pp


def _rot_z(angle_rad: float) -> Array:
    """Active rotation by ``angle_rad`` about ``z``: ``[[c, -s, 0], [s, c, 0], [0, 0, 1]]``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def parallel_rig(
    focal_px: float,
    baseline_m: float,
    resolution_px: tuple[int, int],
    principal_point_px: tuple[float, float] | None = None,
) -> StereoRig:
    """Rig with parallel optical axes (Hu 2024 Sec. 2.1, Kabir 2025 Fig. 2).

    Parameters
    ----------
    focal_px : float
        Focal length of both cameras (px).
    baseline_m : float
        Baseline (m); the right camera sits at ``[b, 0, 0]`` in ``C``.
    resolution_px : tuple of int
        ``(width, height)`` (px).
    principal_point_px : tuple of float, optional
        ``(cu, cv)`` (px); default the image centre.
    """
    if not baseline_m > 0.0:
        raise ValueError(f"baseline_m must be positive, got {baseline_m}")
    pp = _default_pp(resolution_px, principal_point_px)
    left = Camera(focal_px, pp, resolution_px, np.eye(3), np.zeros(3))
    right = Camera(focal_px, pp, resolution_px, np.eye(3), np.array([baseline_m, 0.0, 0.0]))
    return StereoRig(left, right, "parallel")


def convergent_rig(
    focal_px: float,
    baseline_m: float,
    toe_in_rad: float,
    resolution_px: tuple[int, int],
    principal_point_px: tuple[float, float] | None = None,
) -> StereoRig:
    """Convergent (toed-in) rig, as used by Chang 2021 (Sec. 2.3, Fig. 4).

    Same centres as :func:`parallel_rig`; each camera is turned about the rig ``z`` axis so
    that the optical axes turn towards each other by ``toe_in_rad``: the left boresight
    becomes ``[sin a, cos a, 0]`` and the right one ``[-sin a, cos a, 0]`` (in ``C``).  They
    cross at ``[b/2, (b/2)/tan a, 0]``.  Note the rig frame ``C`` stays aligned with the
    *un-toed* left camera, so the left camera frame ``C_0`` is not ``C`` here.

    Parameters
    ----------
    focal_px : float
        Focal length of both cameras (px).
    baseline_m : float
        Baseline (m).
    toe_in_rad : float
        Inward rotation of each camera (rad), in ``[0, pi/2)``.
    resolution_px : tuple of int
        ``(width, height)`` (px).
    principal_point_px : tuple of float, optional
        ``(cu, cv)`` (px); default the image centre.
    """
    if not baseline_m > 0.0:
        raise ValueError(f"baseline_m must be positive, got {baseline_m}")
    if not 0.0 <= toe_in_rad < 0.5 * np.pi:
        raise ValueError(f"toe_in_rad must be in [0, pi/2), got {toe_in_rad}")
    pp = _default_pp(resolution_px, principal_point_px)
    # R_CCk has the C_k axes as columns: the left camera is C rotated by -a about z (its
    # boresight [0,1,0] -> [sin a, cos a, 0]), the right one by +a.  R_CkC = R_CCk^T.
    R_C0C = _rot_z(-toe_in_rad).T
    R_C1C = _rot_z(+toe_in_rad).T
    left = Camera(focal_px, pp, resolution_px, R_C0C, np.zeros(3))
    right = Camera(focal_px, pp, resolution_px, R_C1C, np.array([baseline_m, 0.0, 0.0]))
    return StereoRig(left, right, "convergent")


def chang2021_rig() -> StereoRig:
    """The convergent rig of Chang 2021 (Sec. 3.2 and Table 1).

    Baseline 0.92 m, each camera toed in by 10 deg, ``f = 2029.8`` px and principal point
    ``(640, 640)`` px.  The paper states a 35 deg field of view and a 1024 x 1024 image; these
    are inconsistent: ``2 atan(640 / 2029.8) = 35.0 deg`` needs a 1280 px wide image (principal
    point at its centre), while 1024 px would give ``2 atan(512 / 2029.8) = 28.3 deg`` and an
    off-centre principal point.  We use 1280 x 1280, which matches both the stated field of
    view and the intrinsic matrix.  (The text's "rotation matrix of the left camera ... all
    zeros, ... right camera ... identity" is not a valid rig description either; we use the
    stated 10 deg toe-in per camera.)
    """
    return convergent_rig(
        focal_px=2029.8,
        baseline_m=0.92,
        toe_in_rad=np.deg2rad(10.0),
        resolution_px=(1280, 1280),
        principal_point_px=(640.0, 640.0),
    )


def chang2021_text_rig() -> StereoRig:
    """Chang 2021's rig as its text gives it: 1024 x 1024 px and a 35 deg field of view
    (``f = 512 / tan 17.5 deg = 1623.86`` px, principal point at the image centre, 512 px),
    baseline 0.92 m, 10 deg toe-in per camera; :func:`chang2021_rig` is Table 1's."""
    return convergent_rig(
        focal_px=512.0 / np.tan(np.deg2rad(17.5)),
        baseline_m=0.92,
        toe_in_rad=np.deg2rad(10.0),
        resolution_px=(1024, 1024),
        principal_point_px=(512.0, 512.0),
    )


def _points_in_cameras(rig: StereoRig, p_inC: ArrayLike) -> Array:
    """Feature positions in each camera frame, ``(..., N, 3) -> (..., 2, N, 3)`` (m)."""
    p = np.asarray(p_inC, dtype=float)
    if p.ndim < 2 or p.shape[-1] != 3:
        raise ValueError(f"p_inC must have shape (..., N, 3), got {p.shape}")
    rel = p[..., None, :, :] - rig.centres_inC[:, None, :]  # (..., 2, N, 3)
    return rel @ np.swapaxes(rig.R_CkC, -1, -2)  # (..., 2, N, 3): R_CkC[k] rel


def project(rig: StereoRig, p_inC: ArrayLike) -> tuple[Array, BoolArray]:
    """Noise-free pinhole projection of feature points into both cameras.

    ``u = cu + f x/y``, ``v = cv + f z/y`` in each camera frame (Hu 2024 eq. 1 with ``y`` as
    the depth axis, see the module notes; Kabir 2025 eq. 16-17 plus the principal point).

    Parameters
    ----------
    rig : StereoRig
    p_inC : (..., N, 3) array
        Feature positions in the rig frame ``C`` (m).

    Returns
    -------
    uv : (..., 2, N, 2) array
        Pixel coordinates ``(u, v)`` (px) in camera 0 (left) and 1 (right); NaN where the
        point is not in front of the camera (``y <= 0`` in ``C_k``).
    in_view : (..., 2, N) bool array
        True where the point is in front of the camera (``y > 0``) and its projection lies
        inside the image ``[0, width] x [0, height]``.
    """
    p_k = _points_in_cameras(rig, p_inC)
    x, y, z = p_k[..., 0], p_k[..., 1], p_k[..., 2]
    f = np.array([c.focal_px for c in rig.cameras])[:, None]  # (2, 1)
    cu = np.array([c.principal_point_px[0] for c in rig.cameras])[:, None]
    cv = np.array([c.principal_point_px[1] for c in rig.cameras])[:, None]
    w = np.array([c.resolution_px[0] for c in rig.cameras], dtype=float)[:, None]
    h = np.array([c.resolution_px[1] for c in rig.cameras], dtype=float)[:, None]
    front = y > 0.0
    y_safe = np.where(front, y, 1.0)
    u = np.where(front, cu + f * x / y_safe, np.nan)
    v = np.where(front, cv + f * z / y_safe, np.nan)
    inside = (u >= 0.0) & (u <= w) & (v >= 0.0) & (v <= h)  # NaN compares False
    return np.stack([u, v], axis=-1), front & inside


@dataclass(frozen=True, eq=False)
class StereoMeasurement:
    """Noisy stereo pixel measurements of N features.

    Attributes
    ----------
    uv : (..., 2, N, 2) array
        Measured ``(u, v)`` (px) per camera (0 = left, 1 = right); NaN where not observed.
    observed : (..., 2, N) bool array
        True where the feature was observed by that camera (in view and not occluded).
    noise_px : float
        Standard deviation of the i.i.d. Gaussian noise on each of ``u`` and ``v`` (px).
    """

    uv: Array
    observed: BoolArray
    noise_px: float

    @property
    def stereo_observed(self) -> BoolArray:
        """``(..., N)``: True where both cameras observed the feature (a stereo pair)."""
        return np.all(self.observed, axis=-2)


def measure(
    rig: StereoRig,
    p_inC: ArrayLike,
    rng: np.random.Generator,
    noise_px: float,
    visible: ArrayLike | None = None,
) -> StereoMeasurement:
    """Project features and add i.i.d. Gaussian pixel noise; unobserved entries become NaN.

    Parameters
    ----------
    rig : StereoRig
    p_inC : (..., N, 3) array
        True feature positions in ``C`` (m).
    rng : numpy.random.Generator
        Source of the pixel noise (seed it for reproducible runs).
    noise_px : float
        Standard deviation of the noise on each of ``u`` and ``v`` (px), >= 0.  Use
        :func:`angular_noise_to_px` for a sensor specified by angular resolution.
    visible : bool array, optional
        Extra visibility mask (occlusion), combined with the in-view mask by logical AND.  It
        must have the same number of dimensions as the ``(..., 2, N)`` mask (sizes may be 1
        for broadcasting), e.g. ``self_occlusion_mask(...)`` as is, a per-feature mask
        ``m[..., None, :]`` or a per-epoch mask from :mod:`tumblenav.sensors.occlusion` as
        ``m[:, None, None]``.  Requiring the full rank avoids silent mis-broadcasting.

    Returns
    -------
    StereoMeasurement
        Nothing is dropped: shapes follow ``p_inC``, unobserved entries are NaN.
    """
    if not noise_px >= 0.0:
        raise ValueError(f"noise_px must be >= 0, got {noise_px}")
    uv, observed = project(rig, p_inC)
    if visible is not None:
        vis = np.asarray(visible, dtype=bool)
        if vis.ndim != observed.ndim:
            raise ValueError(
                f"visible must have {observed.ndim} dims broadcastable to {observed.shape}, "
                f"got shape {vis.shape}"
            )
        observed = observed & vis
        if observed.shape != uv.shape[:-1]:
            raise ValueError(f"visible {vis.shape} does not broadcast to {uv.shape[:-1]}")
    noisy = uv + rng.normal(0.0, 1.0, size=uv.shape) * noise_px
    noisy = np.where(observed[..., None], noisy, np.nan)
    return StereoMeasurement(uv=noisy, observed=observed, noise_px=float(noise_px))


def angular_noise_to_px(sigma_rad: ArrayLike, focal_px: float) -> Array | float:
    """Pixel noise equivalent to an angular resolution (small angle): ``sigma_rad * focal_px``.

    Parameters
    ----------
    sigma_rad : float or array
        Angular standard deviation (rad), e.g. Kabir 2025's ``sigma_p``.
    focal_px : float
        Focal length (px).

    Returns
    -------
    float or array
        Standard deviation on the image plane (px), exact at the principal point.
    """
    out = np.asarray(sigma_rad, dtype=float) * float(focal_px)
    return float(out) if out.ndim == 0 else out


def disparity(uv: ArrayLike) -> Array:
    """Horizontal disparity ``u_left - u_right`` (px) of ``(..., 2, N, 2)`` pixels -> ``(..., N)``.

    For the parallel rig ``u_l - u_r = f b / y`` (Hu 2024 eq. 1 corrected; Kabir 2025's
    disparity measurement ``u_L - u_R``).  NaN wherever either camera did not observe.
    """
    uv = np.asarray(uv, dtype=float)
    return uv[..., 0, :, 0] - uv[..., 1, :, 0]


def make_rig(cfg) -> StereoRig:
    """The rig a scenario's stereo ``sensor`` settings describe (parallel or convergent)."""
    res = (int(cfg.resolution_px[0]), int(cfg.resolution_px[1]))
    if cfg.rig == "parallel":
        return parallel_rig(cfg.focal_px, cfg.baseline_m, res, cfg.principal_point)
    return convergent_rig(
        cfg.focal_px, cfg.baseline_m, np.radians(cfg.toe_in_deg), res, cfg.principal_point
    )
