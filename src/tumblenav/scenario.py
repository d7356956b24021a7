"""Scenarios: pydantic models, YAML loading and clear one-line errors.

A scenario says everything a run needs: the chaser's orbit and attitude, the target's inertia
and initial relative state, its feature points, the sensor, occlusions, noise, duration and
rates, the estimator and its tuning, and the Monte Carlo settings. Units are in the field
names (``_m``, ``_s``, ``_rad``, ``_deg``, ``_hz``, ``_px``, ``_kg_m2``) or stated per field.
Frames are those of :mod:`tumblenav.frames`; quaternions are ``[x, y, z, w]``.

Built-in scenarios live in ``tumblenav/scenarios/*.yaml``; ``load_scenario(name_or_path)``
accepts either. Any problem raises :class:`tumblenav.errors.InputError` naming the file, the
key path and what is wrong.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import numpy.typing as npt
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from tumblenav.errors import InputError

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]

# annotations that are plain numbers, for _Model's true/false check
_NUMBERS = (float, int, float | None, int | None)


class _Model(BaseModel):
    """Strict base: unknown keys are errors, values are validated on assignment too, numbers
    must be finite (NaN and infinities are errors), and true/false is not a number (a text
    that reads as a number is one: YAML 1.1 reads 6.8e6 as text)."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False
    )

    @model_validator(mode="before")
    @classmethod
    def _no_bool_numbers(cls, data: Any) -> Any:
        # YAML's true/false would pass as 1/0 where a number is meant (duration_s: true)
        if isinstance(data, dict):
            for key, v in data.items():
                field = cls.model_fields.get(key) if isinstance(key, str) else None
                if field is None or field.annotation not in _NUMBERS:
                    continue
                if isinstance(v, bool):
                    raise ValueError(f"{key}: expected a number, got {str(v).lower()}")
        return data


def _finite(v: npt.ArrayLike, what: str) -> None:
    arr = np.atleast_1d(np.asarray(v, dtype=float))
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be finite numbers")


class OrbitConfig(_Model):
    """The chaser's orbit (circular; Hu 2024 and Yu 2019 assume it)."""

    radius_m: float = Field(6.8e6, gt=0, description="orbit radius (m)")
    inclination_deg: float = 0.0
    raan_deg: float = 0.0
    arg_latitude_deg: float = Field(0.0, description="initial argument of latitude (deg)")
    mu_m3_s2: float = Field(3.986004418e14, gt=0)
    j2: bool = Field(False, description="include J2 in the nonlinear truth")

    @field_validator("radius_m")
    @classmethod
    def _above_earth(cls, v: float) -> float:
        if v <= 6.378137e6:
            raise ValueError(f"radius {v} m is inside the Earth (equatorial radius 6378137 m)")
        return v

    @property
    def mean_motion_rad_s(self) -> float:
        return math.sqrt(self.mu_m3_s2 / self.radius_m**3)


class ChaserConfig(_Model):
    orbit: OrbitConfig | None = Field(
        OrbitConfig(),
        description="the chaser's circular orbit; null: chaser inertially fixed in free space "
        "(Kabir 2025 Sec. 2.1), then L coincides with I and translation is force-free",
    )
    attitude: Literal["target-pointing", "lvlh"] = Field(
        "lvlh",
        description="'lvlh': body frame = L (LVLH-pointing); 'target-pointing': the rig's "
        "boresight tracks the target's mass centre (its z axis kept near zenith)",
    )
    camera_mount_R_LC: list[Vec3] | None = Field(
        None,
        description="for attitude 'lvlh': rotation matrix R_LC (rig axes as columns in L); "
        "default boresight along +x_L (along-track), rig z axis to zenith",
    )

    @field_validator("camera_mount_R_LC")
    @classmethod
    def _rotation(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None:
            R = np.asarray(v, dtype=float)
            _finite(R, "camera_mount_R_LC")
            if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise ValueError(
                    "camera_mount_R_LC must be a proper rotation matrix (R^T R = I, det +1)"
                )
        return v

    @model_validator(mode="after")
    def _mount_with_lvlh(self) -> ChaserConfig:
        if self.camera_mount_R_LC is not None and self.attitude != "lvlh":
            raise ValueError(
                "camera_mount_R_LC: the rig's mount in L applies to attitude 'lvlh' only; with "
                f"'{self.attitude}' the rig points at the target (remove the key, or set "
                "attitude: lvlh)"
            )
        return self

    @property
    def R_LC_fixed(self) -> np.ndarray:
        if self.camera_mount_R_LC is not None:
            return np.asarray(self.camera_mount_R_LC, dtype=float)
        return np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


class RandomFeatures(_Model):
    """Feature points drawn uniformly in a box of the target frame T (Hu 2024 Sec. 5)."""

    count: int = Field(ge=3, le=10_000, description="number of features (3 to 10 000)")
    low_m: float = -1.5
    high_m: float = 1.5
    seed: int | None = Field(
        None, description="fixed seed for the geometry; default: drawn per Monte Carlo run"
    )

    @model_validator(mode="after")
    def _box(self) -> RandomFeatures:
        if not self.high_m > self.low_m:
            raise ValueError("high_m must be greater than low_m")
        return self


class ProceduralModelConfig(_Model):
    """Procedural satellite (metres): box bus, two solar panels along x, docking ring on +z,
    nozzle on -z (``tumblenav.target_model.procedural_satellite``)."""

    kind: Literal["procedural"] = "procedural"
    bus_m: Vec3 = Field(
        [0.9, 1.2, 1.5], description="bus box (m); unequal sides keep its faces distinguishable"
    )
    panel_m: Annotated[list[float], Field(min_length=2, max_length=2)] = [1.8, 0.8]
    panel_thickness_m: float = Field(0.03, gt=0)
    ring_radius_m: float = Field(0.3, ge=0)
    ring_height_m: float = Field(0.08, ge=0)
    nozzle_radius_m: float = Field(0.15, ge=0)
    nozzle_height_m: float = Field(0.25, ge=0)

    @field_validator("bus_m", "panel_m")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if min(v) <= 0:
            raise ValueError("dimensions must be positive")
        return v


class MeshFileConfig(_Model):
    """A user's mesh (OBJ/STL/glTF via trimesh), metres, in the nominal model frame."""

    kind: Literal["file"] = "file"
    path: str


class TargetConfig(_Model):
    inertia_kg_m2: list[float] | list[Vec3] = Field(
        description="principal moments [Ix, Iy, Iz] (kg m^2) of frame T, or a full 3x3 tensor"
    )
    r0_L_m: Vec3 = Field(description="initial relative position of the mass centre in L (m)")
    v0_L_m_s: Vec3 = Field(description="initial relative velocity in L, rotating frame (m/s)")
    q0_TI: list[float] = Field([0.0, 0.0, 0.0, 1.0], description="initial attitude [x,y,z,w]")
    omega0_T_rad_s: Vec3 = Field(description="initial rate of T w.r.t. I, in T (rad/s)")
    mass_centre_offset_T_m: Vec3 = Field(
        [0.0, 0.0, 0.0],
        description="offset b of the true mass centre from the nominal model origin (Yu 2019)",
    )
    features_T_m: list[Vec3] | RandomFeatures | None = Field(
        None, description="feature points in T (m): an explicit list or a random draw"
    )
    model: Annotated[ProceduralModelConfig | MeshFileConfig, Field(discriminator="kind")] = Field(
        ProceduralModelConfig(),
        description="geometry seen by a depth sensor; its nominal frame is parallel to T, "
        "with the mass centre at mass_centre_offset_T_m from the model origin",
    )
    feature_normals_T: list[Vec3] | None = Field(
        None,
        description="outward surface normals of the features (self-occlusion); default: "
        "radial from the mass centre",
    )

    @field_validator("r0_L_m")
    @classmethod
    def _apart(cls, v: list[float]) -> list[float]:
        if not np.linalg.norm(v) > 0:
            raise ValueError("the target starts at the chaser (0, 0, 0): give its position in L")
        return v

    @field_validator("inertia_kg_m2")
    @classmethod
    def _physical_inertia(cls, v: list[Any]) -> list[Any]:
        arr = np.asarray(v, dtype=float)
        if arr.shape not in ((3,), (3, 3)):
            raise ValueError("inertia must be 3 principal moments or a 3x3 matrix")
        _finite(arr, "inertia")
        if arr.shape == (3, 3):
            if not np.allclose(arr, arr.T, rtol=1e-9, atol=1e-12):
                raise ValueError("inertia matrix must be symmetric")
            moments = np.linalg.eigvalsh(arr)
        else:
            moments = arr
        if np.any(moments <= 0):
            raise ValueError(f"inertia moments must be positive, got {moments.tolist()}")
        a, b, c = sorted(moments)
        if a + b < c * (1 - 1e-12):
            raise ValueError(
                f"non-physical inertia: moments {moments.tolist()} violate the triangle "
                "inequality (the two smaller must sum to at least the largest)"
            )
        return v

    @field_validator("q0_TI")
    @classmethod
    def _unit_quaternion(cls, v: list[float]) -> list[float]:
        if len(v) != 4:
            raise ValueError("quaternion must have 4 components [x, y, z, w]")
        _finite(v, "quaternion")
        n = float(np.linalg.norm(v))
        if abs(n - 1.0) > 1e-6:
            raise ValueError(f"quaternion must be unit norm (norm {n:.6g}); order is [x,y,z,w]")
        return v

    @field_validator("features_T_m")
    @classmethod
    def _features(cls, v: Any) -> Any:
        if isinstance(v, list):
            pts = np.asarray(v, dtype=float)
            _finite(pts, "feature coordinates")
            if len(pts) < 3:
                raise ValueError("at least 3 feature points are needed")
            d = pts - pts[0]
            if np.linalg.matrix_rank(d, tol=1e-6 * max(1.0, np.abs(d).max())) < 2:
                raise ValueError("feature points are all collinear (no attitude can be defined)")
        return v

    @model_validator(mode="after")
    def _normals_match(self) -> TargetConfig:
        if self.feature_normals_T is not None:
            if self.features_T_m is None:
                raise ValueError("feature_normals_T given without features_T_m")
            n = (
                len(self.features_T_m)
                if isinstance(self.features_T_m, list)
                else self.features_T_m.count
            )
            if len(self.feature_normals_T) != n:
                raise ValueError(
                    f"feature_normals_T has {len(self.feature_normals_T)} entries for {n} features"
                )
        return self

    @property
    def inertia_matrix(self) -> np.ndarray:
        arr = np.asarray(self.inertia_kg_m2, dtype=float)
        return np.diag(arr) if arr.shape == (3,) else arr


class NoiseConfig(_Model):
    """Image noise: either an angular resolution (rad, as Hu 2024) or pixels (1-sigma)."""

    angular_rad: float | None = Field(None, ge=0)
    pixels: float | None = Field(None, ge=0)

    @model_validator(mode="after")
    def _one(self) -> NoiseConfig:
        if (self.angular_rad is None) == (self.pixels is None):
            raise ValueError("give exactly one of angular_rad or pixels")
        return self

    def sigma_px(self, focal_px: float) -> float:
        if self.pixels is not None:
            return self.pixels
        assert self.angular_rad is not None  # _one: exactly one of the two is given
        return float(self.angular_rad) * focal_px


class ImageNoiseConfig(_Model):
    """The camera's noise chain (Basilisk's camera module is the reference), applied in this
    order to the rendered irradiance: photon (shot) noise, dark current, read noise, blur,
    dead and hot pixels, 8-bit quantisation. Each step is off at its zero value."""

    full_well_e: float = Field(
        20000.0, gt=0, description="electrons at 8-bit full scale (sets the shot noise)"
    )
    shot: bool = Field(True, description="Poisson photon noise on the signal electrons")
    read_noise_e: float = Field(10.0, ge=0, description="Gaussian read noise, electrons rms")
    dark_current_e: float = Field(5.0, ge=0, description="mean dark electrons per frame (Poisson)")
    blur_sigma_px: float = Field(0.0, ge=0, description="Gaussian blur (optics, defocus), px")
    dead_pixel_fraction: float = Field(0.0, ge=0, le=1, description="pixels stuck at 0")
    hot_pixel_fraction: float = Field(0.0, ge=0, le=1, description="pixels stuck at full scale")


class ImagesConfig(_Model):
    """Render stereo images of the target (Chang 2021) instead of projecting feature points:
    the image front end finds and tracks features in them for the estimators."""

    sun_direction_I: Vec3 | None = Field(
        None,
        description="unit vector towards the sun, inertial; default: behind the chaser at the "
        "start, 30 deg off the line of sight (the target's camera-facing side is lit)",
    )
    eclipse: bool = Field(
        True, description="the Earth's shadow (cylinder) on the chaser's orbit gives dark frames"
    )
    exposure: float = Field(
        0.8, gt=0, description="image level (fraction of full scale) of a white face lit head-on"
    )
    ambient: float = Field(
        0.02, ge=0, le=1, description="ambient light (Earth shine) as a fraction of the sun's"
    )
    supersample: int = Field(1, ge=1, le=4, description="rays per pixel side (anti-aliasing)")
    texture: Literal["procedural", "mesh"] = Field(
        "procedural",
        description="'procedural': MLI foil and solar cells; 'mesh': the mesh file's own texture",
    )
    noise: ImageNoiseConfig | None = Field(
        ImageNoiseConfig(), description="the camera's noise chain; null: noise-free images"
    )
    frontend: dict[str, Any] = Field(
        {}, description="settings of the image front end (docs/formats.md: image front end)"
    )


class StereoSensorConfig(_Model):
    kind: Literal["stereo"] = "stereo"
    rig: Literal["parallel", "convergent"] = "parallel"
    focal_length_px: float | None = Field(None, gt=0)
    fov_deg: float | None = Field(
        None,
        gt=0,
        lt=180,
        description="horizontal field of view; sets the focal length "
        "from the resolution when focal_length_px is not given",
    )
    resolution_px: Annotated[list[int], Field(min_length=2, max_length=2)] = [2048, 2048]
    principal_point_px: Annotated[list[float], Field(min_length=2, max_length=2)] | None = None
    baseline_m: float = Field(description="distance between the centres of projection (m)")
    toe_in_deg: float = Field(
        0.0, ge=0, lt=45, description="convergent rig: inward tilt of each camera"
    )
    noise: NoiseConfig = Field(
        description="feature localisation noise: of the simulated pixels, or with `images` the "
        "1-sigma the estimators assume for the corners the front end finds"
    )
    images: ImagesConfig | None = Field(
        None, description="render images and track features in them (Chang 2021)"
    )

    @field_validator("baseline_m")
    @classmethod
    def _baseline(cls, v: float) -> float:
        if not v > 0:
            raise ValueError(f"baseline must be positive, got {v} m (zero baseline has no depth)")
        return v

    @field_validator("resolution_px")
    @classmethod
    def _res(cls, v: list[int]) -> list[int]:
        if min(v) <= 0:
            raise ValueError("resolution must be positive")
        return v

    @model_validator(mode="after")
    def _focal(self) -> StereoSensorConfig:
        if self.focal_length_px is None and self.fov_deg is None:
            raise ValueError("give focal_length_px or fov_deg")
        if self.rig == "parallel" and self.toe_in_deg != 0:
            raise ValueError("toe_in_deg is only for rig: convergent")
        if self.principal_point_px is not None:
            (cu, cv), (w, h) = self.principal_point_px, self.resolution_px
            if not (0 <= cu <= w and 0 <= cv <= h):
                raise ValueError(
                    f"principal point ({cu:g}, {cv:g}) px lies outside the {w} x {h} px image"
                )
        return self

    @property
    def focal_px(self) -> float:
        if self.focal_length_px is not None:
            return self.focal_length_px
        assert self.fov_deg is not None  # _focal: focal_length_px or fov_deg is given
        return 0.5 * self.resolution_px[0] / math.tan(math.radians(self.fov_deg) / 2)

    @property
    def principal_point(self) -> tuple[float, float]:
        if self.principal_point_px is not None:
            return (self.principal_point_px[0], self.principal_point_px[1])
        return (self.resolution_px[0] / 2, self.resolution_px[1] / 2)


class DepthSensorConfig(_Model):
    """Flash-LIDAR / time-of-flight camera (Yu 2019): ray-cast point clouds."""

    kind: Literal["depth"] = "depth"
    fov_deg: float = Field(40.0, gt=0, lt=180)
    points: int = Field(
        1800, gt=0, le=1_000_000, description="points per cloud (Yu 2019 Sec. 4: 1800; at most 1e6)"
    )
    range_noise_m: float = Field(0.01, ge=0)
    outlier_fraction: float = Field(0.0, ge=0, le=1)
    max_range_m: float = Field(100.0, gt=0)
    on_target: bool = Field(
        True,
        description="spread the rays over the target so that about `points` hit it "
        "(Yu 2019 draws its points on the target surface); false: a fixed grid over the FOV",
    )


class OcclusionWindow(_Model):
    start_s: float = Field(ge=0)
    end_s: float

    @model_validator(mode="after")
    def _order(self) -> OcclusionWindow:
        if not self.end_s > self.start_s:
            raise ValueError("end_s must be after start_s")
        return self


class OcclusionConfig(_Model):
    windows: list[OcclusionWindow] = Field(
        [], description="scheduled windows of complete loss (Hu 2024: 20 s)"
    )
    loss_from_s: float | None = Field(
        None, ge=0, description="long-term loss of all features from this time on (Kabir 2025)"
    )
    self_occlusion: bool = Field(
        False, description="a feature is seen only while its surface normal faces the camera"
    )


class ProcessNoiseConfig(_Model):
    """The random disturbances of the target: what the estimators' process noise Q assumes
    (their default Q is derived from it) and, with ``disturb_truth``, what the simulated truth
    carries. Definitions: :mod:`tumblenav.dynamics.disturbances`. With ``disturb_truth: false``
    the truth is torque-free and force-free apart from gravity, which a filter's Q of 0 would
    describe: any Q > 0 then makes it conservative by design (NEES/dof below 1)."""

    translational_m2_s4: float = Field(
        2e-6,
        ge=0,
        description="spectral density (m^2/s^3) of a white random acceleration of the target's "
        "mass centre per axis of L (sigma_t^2, Hu 2024 Sec. 5)",
    )
    rotational_rad2_s4: float = Field(
        2.5e-5,
        ge=0,
        description="spectral density (rad^2/s^3) of the white random angular acceleration "
        "about the target's axis of largest moment; the torque is isotropic, so about a "
        "principal axis of moment I_i it is this x (I_max/I_i)^2 (sigma_r^2, Hu 2024 eq. 22, "
        "Sec. 5)",
    )
    disturb_truth: bool = Field(
        False,
        description="the simulated truth carries these disturbances (a random torque and "
        "force with these spectral densities), so that a filter whose Q equals them can be "
        "judged by NEES; false: torque-free and force-free truth",
    )


class EstimatorConfig(_Model):
    name: str = "ekf-dpacf"
    tuning: dict[str, Any] = Field(
        {}, description="estimator-specific settings, validated by the estimator"
    )


class MonteCarloConfig(_Model):
    runs: int = Field(20, ge=1)
    seed: int = Field(0, ge=0, description="base seed: run k uses SeedSequence(seed).spawn(...)[k]")


class Scenario(_Model):
    name: str
    description: str = ""
    duration_s: float = Field(gt=0)
    rate_hz: float = Field(gt=0, description="measurement (and truth output) rate")
    chaser: ChaserConfig = ChaserConfig()
    target: TargetConfig
    sensor: Annotated[StereoSensorConfig | DepthSensorConfig, Field(discriminator="kind")]
    other_sensors: list[
        Annotated[StereoSensorConfig | DepthSensorConfig, Field(discriminator="kind")]
    ] = Field(
        [],
        description="sensors of other kinds on the same chaser, for `compare`: an estimator "
        "that cannot run on `sensor` gets its own measurements from the first of these it runs "
        "on, simulated from the same truth with the same seeds",
    )
    occlusion: OcclusionConfig = OcclusionConfig()
    process_noise: ProcessNoiseConfig = ProcessNoiseConfig()
    estimator: EstimatorConfig = EstimatorConfig()
    montecarlo: MonteCarloConfig = MonteCarloConfig()
    steady_state_window_s: Annotated[list[float], Field(min_length=2, max_length=2)] | None = Field(
        None, description="window for summary RMSE; default: the last quarter of the run"
    )

    @model_validator(mode="after")
    def _times(self) -> Scenario:
        n = self.duration_s * self.rate_hz
        if n < 2:
            raise ValueError("duration_s * rate_hz gives fewer than 2 samples")
        if n > 5e6:
            raise ValueError(f"duration_s * rate_hz = {n:.3g} samples is too many (max 5e6)")
        turn = float(np.linalg.norm(self.target.omega0_T_rad_s)) / self.rate_hz
        if turn > np.pi:
            raise ValueError(
                f"target.omega0_T_rad_s: the target turns {turn:.3g} rad between samples, more "
                f"than half a turn: no estimator can tell it from a slower spin; raise rate_hz "
                f"or lower the rate"
            )
        if self.steady_state_window_s is not None:
            a, b = self.steady_state_window_s
            if not 0 <= a < b <= self.duration_s:
                raise ValueError(
                    "steady_state_window_s must satisfy 0 <= start < end <= duration_s"
                )
        if (
            self.sensor.kind == "stereo"
            and self.sensor.images is None
            and self.target.features_T_m is None
        ):
            raise ValueError(
                "target.features_T_m: a stereo sensor needs feature points (or sensor.images, "
                "to find features in rendered images)"
            )
        return self

    @property
    def n_features(self) -> int:
        f = self.target.features_T_m
        if f is None:
            return 0
        return len(f) if isinstance(f, list) else f.count

    @property
    def window_s(self) -> tuple[float, float]:
        if self.steady_state_window_s is not None:
            return (self.steady_state_window_s[0], self.steady_state_window_s[1])
        return (0.75 * self.duration_s, self.duration_s)

    @property
    def times(self) -> np.ndarray:
        n = int(round(self.duration_s * self.rate_hz))
        return np.arange(n + 1) / self.rate_hz

    def with_updates(self, **changes: Any) -> Scenario:
        """A validated copy with top-level or dotted-path changes, e.g.
        ``with_updates(**{"sensor.noise.angular_rad": 5e-5})``."""
        data = self.model_dump()
        for key, value in changes.items():
            node = data
            parts = key.split(".")
            for p in parts[:-1]:
                node = node[p]
            node[parts[-1]] = value
        return validate_scenario(data, source=f"{self.name} (updated)")


# --- loading -------------------------------------------------------------------------------

BUILTIN_PACKAGE = "tumblenav.scenarios"


def builtin_names() -> list[str]:
    files = resources.files(BUILTIN_PACKAGE)
    return sorted(p.name[:-5] for p in files.iterdir() if p.name.endswith(".yaml"))


def builtin_text(name: str) -> str:
    if name not in builtin_names():
        raise InputError(
            f"unknown scenario '{name}' (built-ins: {', '.join(builtin_names())}; "
            "or give a path to a YAML file)"
        )
    return (resources.files(BUILTIN_PACKAGE) / f"{name}.yaml").read_text(encoding="utf-8")


_UNION_TAGS = ("stereo", "depth", "procedural", "file", "list[list[float]]", "RandomFeatures")


def _format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in _UNION_TAGS or "[" in str(part):
            continue  # union branch tags from pydantic, not user keys
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def validate_scenario(data: Any, source: str = "<scenario>") -> Scenario:
    """Validate a parsed YAML mapping; raise InputError naming ``source`` and the key path."""
    if not isinstance(data, dict):
        raise InputError("a scenario must be a YAML mapping of keys to values", source)
    if isinstance(data.get("sensor"), dict) and "kind" not in data["sensor"]:
        data = {**data, "sensor": {"kind": "stereo", **data["sensor"]}}  # the documented default
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors()
        # Prefer the most specific error (longest key path) of a union's alternatives, and of
        # those the alternative whose type matched (its error is about the value, not the type)
        err = max(errors, key=lambda e: (len(e["loc"]), not str(e["type"]).endswith("_type")))
        if any(e["type"] == "extra_forbidden" for e in errors):
            err = next(e for e in errors if e["type"] == "extra_forbidden")
        loc = _format_loc(err["loc"])
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "missing":
            msg = "missing required key"
        else:
            msg = err["msg"].removeprefix("Value error, ")
        more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
        raise InputError(f"{loc}: {msg}{more}", source) from None


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a built-in scenario by name or a YAML file by path."""
    text: str
    source = str(name_or_path)
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if p.is_dir():
            raise InputError("a folder, not a scenario file (give the path of a YAML file)", source)
        if not p.is_file():
            raise InputError("no such scenario file", source)
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read file ({exc.__class__.__name__})", source) from None
    else:
        text = builtin_text(str(name_or_path))
        source = f"built-in scenario {name_or_path}"
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise InputError(f"invalid YAML{where}: {problem}", source) from None
    return validate_scenario(data, source)


def scenario_to_yaml(s: Scenario) -> str:
    return yaml.safe_dump(s.model_dump(mode="json"), sort_keys=False)
