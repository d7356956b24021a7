"""The calibration/context YAML beside a user's measurements: the stereo calibration as OpenCV
gives it, the noise, the pixel and camera-axis conventions, and the chaser's attitude and orbit.

Conventions (docs/own_data.md says the same for users)
------------------------------------------------------
* ``camera_axes: opencv`` (the default for a calibration from OpenCV): camera frames have
  x right, y down, z along the optical axis; images have row 0 at the top. tumblenav's camera
  frame has x right, y along the optical axis and z = x cross y, with ``v = cv + f z / y``
  (Hu 2024 eq. 1's axes). For a *physical* camera, x cross y of tumblenav's frame points up the
  image, so the proper rotation between the two is ``x = x_cv, y = z_cv, z = -y_cv``
  (:data:`R_TN_CV`, det +1), and a tumblenav image is the OpenCV image upside down:
  ``v = H - v_cv``, ``cv = H - cy`` and the rows are flipped. (Mapping ``(x_cv, y_cv, z_cv) =
  (x, z, y)`` keeps the pixels but is a reflection, det -1: no rotation ``q_CL`` could then
  relate the camera to LVLH, and the estimators would see a mirrored world.)
* ``camera_axes: tumblenav``: K, R, T, pixels, attitudes and images are already in tumblenav's
  camera axes (what :mod:`tumblenav.importers.export` writes by default: no arithmetic, so a
  round trip is exact).
* ``pixel_origin: opencv`` puts pixel centres at integers (OpenCV keypoints, ``cv2.KeyPoint``,
  optical flow, ``cv2.projectPoints``); ``centre`` at ``i + 0.5`` (tumblenav's: pixel
  ``(i, j)`` covers ``[i, i+1) x [j, j+1)``). It applies to the principal point of K as well.
* ``R``, ``T`` map the left camera frame into the right one: ``x_right = R x_left + T``
  (``cv2.stereoCalibrate``); T in metres (``T_m``) or in ``translation_unit_m`` units (``T``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav import sensors
from tumblenav.errors import InputError

Array = NDArray[np.float64]

__all__ = [
    "R_TN_CV",
    "CameraAxes",
    "Context",
    "StereoCalibration",
    "load_context",
    "load_yaml",
    "stereo_calibration",
]

# x_tumblenav = R_TN_CV x_opencv for a physical camera (x right, optical axis y, z = x cross y)
R_TN_CV = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
CameraAxes = str  # "opencv" | "tumblenav"
_AXES = ("opencv", "tumblenav")
_ORIGINS = ("opencv", "centre")
# a calibration within these of a tumblenav rig is that rig; otherwise tracks are rectified
RIG_TOL = 1e-9  # tumblenav default: rotation entries and baseline direction, relative
# cv2.undistortPoints inverts the distortion iteratively (5 steps by default, ~0.01 px off for a
# strong lens): iterate to 1e-12 (normalised units) -- tumblenav default
_UNDISTORT = (3, 200, 1e-12)  # cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS


# --- YAML with OpenCV's FileStorage dialect -----------------------------------------------


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader plus OpenCV FileStorage's ``!!opencv-matrix`` (rows, cols, dt,
    data) as a NumPy array."""


def _opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> Array:
    assert isinstance(node, yaml.MappingNode)
    m = loader.construct_mapping(node, deep=True)
    try:
        rows, cols = int(m["rows"]), int(m["cols"])
        data = np.asarray(m["data"], dtype=float)
        return data.reshape(rows, cols)
    except (KeyError, ValueError, TypeError) as exc:
        raise yaml.constructor.ConstructorError(
            None, None, f"malformed !!opencv-matrix ({exc})", node.start_mark
        ) from None


for _tag in ("tag:yaml.org,2002:opencv-matrix", "!opencv-matrix", "!!opencv-matrix"):
    _Loader.add_constructor(_tag, _opencv_matrix)


def load_yaml(path: Path) -> dict[str, Any]:
    """A YAML mapping, plain or OpenCV FileStorage (``%YAML:1.0``, ``!!opencv-matrix``);
    InputError naming the file if missing or malformed."""
    path = Path(path)
    if path.is_dir():
        raise InputError("a folder, not a calibration file", str(path))
    if not path.is_file():
        raise InputError("calibration file not found", str(path))
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read ({exc.__class__.__name__})", str(path)) from None
    # OpenCV writes the directive as "%YAML:1.0", which PyYAML does not know
    text = re.sub(r"^%YAML[: ]\s*1\.\d+\s*$", "", text, count=1, flags=re.M)
    try:
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise InputError(
            f"invalid YAML{where}: {getattr(exc, 'problem', None) or exc}", str(path)
        ) from None
    if not isinstance(data, dict):
        raise InputError("must be a YAML mapping of keys to values", str(path))
    return data


# --- small validated getters ----------------------------------------------------------------


def _matrix(d: dict, key: str, shape: tuple[int, ...], where: str) -> Array:
    try:
        a = np.asarray(d[key], dtype=float)
    except KeyError:
        raise InputError(f"missing key {key}", where) from None
    except (ValueError, TypeError):
        raise InputError(f"{key}: not a matrix of numbers", where) from None
    if a.size == math.prod(shape):
        a = a.reshape(shape)
    if a.shape != shape:
        raise InputError(f"{key}: expected shape {shape}, got {a.shape}", where)
    if not np.all(np.isfinite(a)):
        raise InputError(f"{key}: not finite", where)
    return a


def _number(d: dict, key: str, where: str, default: float | None = None) -> float:
    if key not in d:
        if default is None:
            raise InputError(f"missing key {key}", where)
        return default
    try:
        v = float(d[key])
    except (TypeError, ValueError):
        raise InputError(f"{key}: not a number ({d[key]!r})", where) from None
    if not math.isfinite(v):
        raise InputError(f"{key}: not finite", where)
    return v


def _choice(d: dict, key: str, options: tuple[str, ...], where: str, default: str | None) -> str:
    v = d.get(key, default)
    if v is None:
        raise InputError(f"missing key {key} (one of {', '.join(options)})", where)
    if v not in options:
        raise InputError(f"{key}: {v!r} is not one of {', '.join(options)}", where)
    return str(v)


def _distortion(d: dict, key: str, where: str) -> Array:
    if key not in d or d[key] is None:
        return np.zeros(5)
    try:
        a = np.asarray(d[key], dtype=float).ravel()
    except (ValueError, TypeError):
        raise InputError(f"{key}: not a list of numbers", where) from None
    if a.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(a)):
        raise InputError(f"{key}: expected 4, 5, 8, 12 or 14 finite coefficients", where)
    return a


def _image_size(d: dict, where: str) -> tuple[int, int]:
    """(W, H) of both cameras; mismatched sizes are refused."""
    sizes = {}
    for cam in ("", "_left", "_right"):
        for key in (f"image_size{cam}_px", f"imageSize{cam}"):
            if key in d:
                try:
                    v = np.asarray(d[key], dtype=float).ravel()
                except (TypeError, ValueError):
                    raise InputError(f"{key}: expected [width, height] in px", where) from None
                if v.size != 2 or not np.all(v > 0) or not np.all(v == np.round(v)):
                    raise InputError(f"{key}: expected [width, height] in px", where)
                sizes[key] = (int(v[0]), int(v[1]))
    if "image_width_px" in d or "image_height_px" in d:
        sizes["image_width_px/image_height_px"] = (
            int(_number(d, "image_width_px", where)),
            int(_number(d, "image_height_px", where)),
        )
    if not sizes:
        raise InputError("missing key image_size_px ([width, height] of the images)", where)
    if len(set(sizes.values())) > 1:
        detail = ", ".join(f"{k} {v[0]} x {v[1]}" for k, v in sizes.items())
        raise InputError(f"mismatched image sizes: {detail} (both cameras must agree)", where)
    return next(iter(sizes.values()))


def _is_rotation(R: Array, tol: float = 1e-6) -> bool:
    return bool(np.allclose(R @ R.T, np.eye(3), atol=tol) and np.linalg.det(R) > 0)


# --- the stereo calibration -----------------------------------------------------------------


@dataclass(frozen=True)
class StereoCalibration:
    """A user's stereo calibration, turned into a tumblenav rig.

    rig : the tumblenav rig (``C`` = the rig frame of a scenario's parallel or convergent rig).
    sensor : the scenario's ``sensor`` keys of that rig (rig, focal_length_px, ...).
    R_CC0 : rotation from the user's left camera frame (tumblenav axes) into ``C``.
    axes, origin : the file's camera axes and pixel origin.
    rectify : OpenCV's rectification (K, D, R1, P1 per camera) when the calibration is not a
      tumblenav rig as it stands (then tracks are mapped into the rectified cameras).
    """

    rig: sensors.StereoRig
    sensor: dict[str, Any]
    R_CC0: Array
    axes: str
    origin: str
    size: tuple[int, int]
    rectify: dict[str, list[Array]] | None = None
    note: str = ""

    def to_tumblenav_uv(self, uv: Array) -> Array:
        """Pixels ``(..., 2, N, 2)`` of the file (camera 0 left, 1 right) in tumblenav's
        convention for :attr:`rig` (rectified when :attr:`rectify` is set)."""
        uv = np.array(uv, dtype=float)
        o = 0.5 if self.origin == "opencv" else 0.0
        H = float(self.size[1])
        if self.rectify is not None:
            import cv2

            if o == 0.0:  # the file's centres at i + 0.5 -> OpenCV's at i
                uv = uv - 0.5
            out = np.full_like(uv, np.nan)
            for k, (K, D, R, P) in enumerate(
                zip(
                    self.rectify["K"],
                    self.rectify["D"],
                    self.rectify["R"],
                    self.rectify["P"],
                    strict=True,
                )
            ):
                pts = uv[..., k, :, :].reshape(-1, 2)
                ok = np.all(np.isfinite(pts), axis=1)
                res = np.full_like(pts, np.nan)
                if ok.any():
                    res[ok] = cv2.undistortPoints(
                        pts[ok].reshape(-1, 1, 2), K, D, R=R, P=P, criteria=_UNDISTORT
                    ).reshape(-1, 2)
                out[..., k, :, :] = res.reshape(uv[..., k, :, :].shape)
            uv, o = out, 0.5  # now OpenCV's rectified pixels
        if self.axes == "tumblenav":
            return uv + o if o else uv
        out = np.empty_like(uv)
        out[..., 0] = uv[..., 0] + o
        out[..., 1] = H - (uv[..., 1] + o)
        return out

    def from_tumblenav_uv(self, uv: Array) -> Array:
        """The inverse of :meth:`to_tumblenav_uv` (no rectification): what the file holds."""
        uv = np.array(uv, dtype=float)
        o = 0.5 if self.origin == "opencv" else 0.0
        if self.axes == "tumblenav":
            return uv - o if o else uv
        out = np.empty_like(uv)
        out[..., 0] = uv[..., 0] - o
        out[..., 1] = (float(self.size[1]) - uv[..., 1]) - o
        return out


def _axes_rotation(axes: str) -> Array:
    return R_TN_CV if axes == "opencv" else np.eye(3)


def stereo_calibration(d: dict, where: str) -> StereoCalibration:
    """The rig of a calibration mapping (K1, D1, K2, D2, R, T_m, image_size_px, camera_axes,
    pixel_origin): a tumblenav parallel or convergent rig when the calibration is one (to
    :data:`RIG_TOL`), else the rectified parallel rig of ``cv2.stereoRectify`` (OpenCV axes
    only). InputError naming the file and key for anything else."""
    axes = _choice(d, "camera_axes", _AXES, where, "opencv")
    origin = _choice(d, "pixel_origin", _ORIGINS, where, None)
    W, H = _image_size(d, where)
    K1 = _matrix(d, "K1", (3, 3), where)
    K2 = _matrix(d, "K2", (3, 3), where)
    D1, D2 = _distortion(d, "D1", where), _distortion(d, "D2", where)
    R = _matrix(d, "R", (3, 3), where)
    if not _is_rotation(R):
        raise InputError(
            "not a rotation matrix (R R^T = I and det R = +1 within 1e-6; det R = "
            f"{np.linalg.det(R):.6g})",
            f"{where}: R",
        )
    if "T_m" in d:
        T = _matrix(d, "T_m", (3,), where)
    else:
        T = _matrix(d, "T", (3,), where) * _number(d, "translation_unit_m", where, 1.0)
    if not np.linalg.norm(T) > 0:
        raise InputError("T is zero: the cameras share a centre (no depth)", f"{where}: T_m")
    for name, K in (("K1", K1), ("K2", K2)):
        if K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1 or K[1, 0] != 0:
            raise InputError(
                f"{name}: not a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]", where
            )
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(f"{name}: focal lengths must be positive", where)
    o = 0.5 if origin == "opencv" else 0.0
    Q = _axes_rotation(axes)
    # the right camera in the left one's frame, tumblenav axes: x_C1 = R_C10 x_C0 + Q T
    R_C10 = R if axes == "tumblenav" else Q @ R @ Q.T
    p_C1in0 = -(R_C10.T @ (T if axes == "tumblenav" else Q @ T))
    exact = (
        np.array_equal(K1, K2)
        and K1[0, 0] == K1[1, 1]
        and K1[0, 1] == 0
        and not np.any(D1)
        and not np.any(D2)
    )
    f = float(K1[0, 0])
    if axes == "tumblenav":
        cu, cv = float(K1[0, 2]) + o, float(K1[1, 2]) + o
    else:
        cu, cv = float(K1[0, 2]) + o, float(H) - (float(K1[1, 2]) + o)
    rig_fit = _fit_rig(R_C10, p_C1in0) if exact else None
    if rig_fit is not None:
        kind, toe_in_deg, baseline = rig_fit
        sensor = {
            "kind": "stereo",
            "rig": kind,
            "focal_length_px": f,
            "fov_deg": None,
            "resolution_px": [W, H],
            "principal_point_px": [cu, cv],
            "baseline_m": baseline,
            "toe_in_deg": toe_in_deg,
        }
        rig = _make_rig(sensor, where)
        # C0 is C turned by R_C0C (identity for a parallel rig)
        R_CC0 = rig.left.R_CkC.T
        return StereoCalibration(rig, sensor, R_CC0, axes, origin, (W, H))
    if axes != "opencv":
        raise InputError(
            "not a tumblenav rig (one focal length fx = fy, K1 = K2, no distortion, a parallel "
            "or symmetric toed-in pair) and only calibrations in OpenCV axes are rectified",
            where,
        )
    return _rectified(K1, D1, K2, D2, R, T, (W, H), origin, where)


def _fit_rig(R_C10: Array, p: Array) -> tuple[str, float, float] | None:
    """``(kind, toe_in_deg, baseline_m)`` of the tumblenav rig with this relative pose, or None."""
    b = float(np.linalg.norm(p))
    if np.abs(R_C10 - np.eye(3)).max() <= RIG_TOL and np.abs(p[1:]).max() <= RIG_TOL * b:
        return ("parallel", 0.0, float(p[0])) if p[0] > 0 else None
    # convergent: R_C10 = rot_z(-2a), p_C1in0 = b [cos a, sin a, 0] (sensors.convergent_rig)
    a = -0.5 * math.atan2(R_C10[1, 0], R_C10[0, 0])
    if not 0 < a < math.radians(45):
        return None
    c2, s2 = math.cos(2 * a), math.sin(2 * a)
    expect = np.array([[c2, s2, 0.0], [-s2, c2, 0.0], [0.0, 0.0, 1.0]])
    if np.abs(R_C10 - expect).max() > RIG_TOL:
        return None
    if np.abs(p / b - [math.cos(a), math.sin(a), 0.0]).max() > RIG_TOL:
        return None
    return ("convergent", math.degrees(a), b)


def _make_rig(sensor: dict, where: str) -> sensors.StereoRig:
    from tumblenav.scenario import StereoSensorConfig

    cfg = StereoSensorConfig.model_validate({**sensor, "noise": {"pixels": 1.0}})
    try:
        return sensors.make_rig(cfg)
    except ValueError as exc:
        raise InputError(f"not a usable stereo rig ({exc})", where) from None


def _rectified(K1, D1, K2, D2, R, T, size, origin, where) -> StereoCalibration:
    """OpenCV's rectification of a general calibration: a parallel rig with one focal length
    (``cv2.stereoRectify``, zero disparity at infinity, all pixels kept: alpha -1)."""
    import cv2

    W, H = size
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        K1, D1, K2, D2, (W, H), R, T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1
    )
    if abs(P2[1, 3]) > 1e-9 * abs(P2[0, 3]) or not P2[0, 3] < 0:
        raise InputError(
            "the right camera is not to the right of the left one (T must point along -x of "
            "the left camera: x_right = R x_left + T); swap the cameras",
            f"{where}: T_m",
        )
    f = float(P1[0, 0])
    b = float(-P2[0, 3] / f)
    cu, cv = float(P1[0, 2]) + 0.5, float(H) - (float(P1[1, 2]) + 0.5)
    if not (0 <= cu <= W and 0 <= cv <= H):
        raise InputError(
            f"rectified principal point ({cu:.1f}, {cv:.1f}) px lies outside the image: the "
            "calibration is too far from a stereo pair for rectification",
            where,
        )
    sensor = {
        "kind": "stereo",
        "rig": "parallel",
        "focal_length_px": f,
        "fov_deg": None,
        "resolution_px": [W, H],
        "principal_point_px": [cu, cv],
        "baseline_m": b,
        "toe_in_deg": 0.0,
    }
    rig = _make_rig(sensor, where)
    R_CC0 = R_TN_CV @ R1 @ R_TN_CV.T
    return StereoCalibration(
        rig,
        sensor,
        R_CC0,
        "opencv",
        origin,
        (W, H),
        rectify={"K": [K1, K2], "D": [D1, D2], "R": [R1, R2], "P": [P1, P2]},
        note="the calibration is not a tumblenav rig as it stands (distortion, fx != fy, "
        "different cameras or a general relative pose): tracks were mapped into OpenCV's "
        "rectified cameras (cv2.stereoRectify, cv2.undistortPoints), a parallel rig with "
        f"f = {f:.6g} px and baseline {b:.6g} m",
    )


# --- the chaser's context -------------------------------------------------------------------


@dataclass(frozen=True)
class Context:
    """What the context YAML says besides the rig: the chaser's attitudes per epoch and its
    orbit (the scenario's ``chaser.orbit``: a mapping or None)."""

    q_C0L: Array  # (n, 4): L into the left camera (tumblenav axes), or the depth sensor frame
    q_LI: Array  # (n, 4)
    orbit: dict[str, Any] | None
    extra: dict[str, Any] = field(default_factory=dict)


def _quat(v: Any, key: str, where: str) -> Array:
    try:
        q = np.asarray(v, dtype=float).ravel()
    except (TypeError, ValueError):
        raise InputError(f"{key}: not a list of 4 numbers", where) from None
    if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > 1e-6:
        raise InputError(f"{key}: expected a unit quaternion [x, y, z, w]", where)
    return q


def load_context(
    d: dict, where: str, folder: Path, t: Array, axes: str, t_offset: float
) -> Context:
    """The ``chaser`` block: ``q_CL`` and ``q_LI`` (constant ``[x, y, z, w]``) or an
    ``attitude_file`` (CSV: t_s, q_CL_x ... q_CL_w, q_LI_x ... q_LI_w, one row per epoch), and
    ``orbit`` (required: the scenario's chaser.orbit mapping, or null for an inertially fixed
    chaser). Without q_LI: the circular orbit's LVLH attitude (identity without an orbit)."""
    from tumblenav.scenario import OrbitConfig

    ch = d.get("chaser")
    if not isinstance(ch, dict):
        raise InputError("missing key chaser (q_CL or attitude_file, q_LI, orbit)", where)
    w = f"{where}: chaser"
    if "orbit" not in ch:
        raise InputError(
            "missing key orbit (the chaser's circular orbit: radius_m, ...; or null for a "
            "chaser inertially fixed in free space)",
            w,
        )
    orbit = ch["orbit"]
    if orbit is not None:
        if not isinstance(orbit, dict):
            raise InputError("orbit: expected a mapping (radius_m, inclination_deg, ...)", w)
        try:
            orbit = OrbitConfig.model_validate(orbit).model_dump()
        except Exception as exc:  # noqa: BLE001 - pydantic's ValidationError, shown in one line
            first = str(exc).splitlines()
            raise InputError(f"orbit: {' '.join(first[1:3]).strip()}", w) from None
    n = len(t)
    q_CL = q_LI = None
    if "attitude_file" in ch:
        q_CL, q_LI = _attitude_file(folder / str(ch["attitude_file"]), t, t_offset)
    if "q_CL" in ch:
        if q_CL is not None:
            raise InputError("give q_CL or attitude_file columns q_CL_*, not both", w)
        q_CL = np.tile(_quat(ch["q_CL"], "q_CL", w), (n, 1))
    if "q_LI" in ch:
        if q_LI is not None:
            raise InputError("give q_LI or attitude_file columns q_LI_*, not both", w)
        q_LI = np.tile(_quat(ch["q_LI"], "q_LI", w), (n, 1))
    if q_CL is None:
        raise InputError(
            "missing key q_CL (the left camera's attitude: maps L into it) or attitude_file", w
        )
    if q_LI is None:
        q_LI = _lvlh_attitude(orbit, t)
    if axes == "opencv":
        q_C0L = rot.quat_multiply(rot.matrix_to_quat(R_TN_CV), q_CL)
    else:
        q_C0L = q_CL
    return Context(q_C0L=q_C0L, q_LI=q_LI, orbit=orbit)


def _lvlh_attitude(orbit: dict | None, t: Array) -> Array:
    """q_LI of a circular orbit (argument of latitude at the first epoch, t from it)."""
    from tumblenav.dynamics.relative_orbit import circular_orbit_state
    from tumblenav.frames import lvlh_axes

    if orbit is None:
        return np.tile(rot.IDENTITY, (len(t), 1))
    n = math.sqrt(orbit["mu_m3_s2"] / orbit["radius_m"] ** 3)
    r, v = zip(
        *(
            circular_orbit_state(
                orbit["radius_m"],
                math.radians(orbit["inclination_deg"]),
                math.radians(orbit["raan_deg"]),
                math.radians(orbit["arg_latitude_deg"]) + n * tk,
                orbit["mu_m3_s2"],
            )
            for tk in t
        ),
        strict=True,
    )
    return rot.matrix_to_quat(np.swapaxes(lvlh_axes(np.array(r), np.array(v)), -1, -2))


def _attitude_file(path: Path, t: Array, t_offset: float) -> tuple[Array | None, Array | None]:
    from tumblenav.importers.tables import read_table

    cols = read_table(path)
    if "t_s" not in cols:
        raise InputError("missing column t_s", str(path))
    ta = cols["t_s"] - t_offset
    if len(ta) != len(t) or not np.array_equal(ta, t):
        raise InputError(
            f"{len(ta)} rows: needs one row per measurement epoch ({len(t)}), at the same t_s",
            str(path),
        )
    out: list[Array | None] = []
    for name in ("q_CL", "q_LI"):
        keys = [f"{name}_{c}" for c in "xyzw"]
        have = [k in cols for k in keys]
        if not any(have):
            out.append(None)
            continue
        if not all(have):
            raise InputError(f"needs all of {', '.join(keys)}", str(path))
        q = np.stack([cols[k] for k in keys], axis=1)
        bad = ~np.isfinite(q).all(axis=1) | (np.abs(np.linalg.norm(q, axis=1) - 1) > 1e-6)
        if bad.any():
            raise InputError(
                f"row {int(np.flatnonzero(bad)[0]) + 2}: {name} is not a unit quaternion",
                str(path),
            )
        out.append(q)
    return out[0], out[1]
