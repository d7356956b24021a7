"""Stereo feature tracks: what a calibrated stereo rig gives (pixel pairs with IDs and a
visibility mask), the input of the stereo front ends and estimators; ``measurements.nc``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr
from numpy.typing import NDArray

from tumblenav import sensors
from tumblenav.measurements._attrs import _a

Array = NDArray[np.float64]


@dataclass(frozen=True)
class StereoMeasurements:
    """Raw stereo pixel measurements (what the cameras give) plus the chaser's own knowledge.

    uv : (n, 2, N, 2) px -- [time, camera (0 left, 1 right), feature, (u, v)], NaN if unseen.
    observed : (n, 2, N) bool -- explicit visibility mask.
    q_CL : (n, 4) -- rig attitude (known to the chaser); q_LI : (n, 4) -- LVLH attitude.
    noise_px : 1-sigma noise on each of u and v (px) the estimators weight by.
    slide_px2_per_frame : how fast a track slides over the surface, as a random walk (px^2 per
        frame, each of u and v; 0: tracks that stay on their surface point, e.g. simulated
        corners). A tracker that follows a rotating patch frame to frame (LK) slides as the
        track ages; an estimator that keeps the tracks' surface points as a map (ekf-pose)
        lets each map point walk by this much per frame.
    track_noise_px : 1-sigma noise (px, each of u and v) of a track's sightings after its
        first, where a tracker states it apart from ``noise_px`` (None: ``noise_px`` for
        every sighting). The image front end's affine refinement holds a tracked feature to
        its first-sighting patch, which is more precise than a new corner's localisation and
        first match (``noise_px``); ekf-pose weights its updates by it.
    """

    t: Array
    uv: Array
    observed: NDArray[np.bool_]
    q_CL: Array
    q_LI: Array
    rig: sensors.StereoRig
    noise_px: float
    slide_px2_per_frame: float = 0.0
    track_noise_px: float | None = None

    def to_dataset(self, scenario_name: str = "") -> xr.Dataset:
        from tumblenav.io import with_coordinates

        rig = self.rig
        ds = xr.Dataset(
            {
                "uv": (
                    ("time", "camera", "feature", "pixel"),
                    self.uv,
                    _a(
                        "px",
                        "measured image coordinates of the features (pinhole model plus "
                        "Gaussian noise); NaN where unobserved",
                    ),
                ),
                "observed": (
                    ("time", "camera", "feature"),
                    self.observed.astype(np.int8),
                    _a(
                        "1",
                        "1 if that camera measured the feature (in front of it, inside the "
                        "image, not occluded), else 0",
                    ),
                ),
                **attitude_variables(self.q_CL, self.q_LI),
                **rig_variables(rig),
            },
            attrs={
                "title": "tumblenav stereo measurements",
                "scenario": scenario_name,
                "rig": rig.kind,
                "baseline_m": rig.baseline_m,
                "noise_px": self.noise_px,
                "slide_px2_per_frame": self.slide_px2_per_frame,
                "track_noise_px": (
                    self.noise_px if self.track_noise_px is None else self.track_noise_px
                ),
                "camera_model": CAMERA_MODEL,
            },
        )
        return with_coordinates(ds, time=self.t, feature=np.arange(self.uv.shape[2]))

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> StereoMeasurements:
        rig = rig_from_dataset(ds)
        return cls(
            t=np.asarray(ds["time"].values, dtype=float),
            uv=np.asarray(ds["uv"].values, dtype=float),
            observed=np.asarray(ds["observed"].values).astype(bool),
            q_CL=np.asarray(ds["q_CL"].values, dtype=float),
            q_LI=np.asarray(ds["q_LI"].values, dtype=float),
            rig=rig,
            noise_px=float(ds.attrs.get("noise_px", np.nan)),
            slide_px2_per_frame=float(ds.attrs.get("slide_px2_per_frame", 0.0)),
            track_noise_px=_tracked_noise(ds.attrs),
        )


def _tracked_noise(attrs) -> float | None:
    """The file's ``track_noise_px``; None where it is absent (files before it), not a
    number, or equals ``noise_px``."""
    if "track_noise_px" not in attrs:
        return None
    v = float(attrs["track_noise_px"])
    return None if not np.isfinite(v) or v == float(attrs.get("noise_px", np.nan)) else v


CAMERA_MODEL = (
    "pinhole; camera axes x right, y optical axis, z = x cross y; u = cu + f x/y, v = cv + f z/y"
)


def attitude_variables(q_CL: Array, q_LI: Array) -> dict[str, tuple]:
    """The chaser's own attitudes as dataset variables (every stereo measurement file)."""
    return {
        "q_CL": (
            ("time", "quat"),
            q_CL,
            _a("1", "rig attitude: maps L into C (known to the chaser)"),
        ),
        "q_LI": (
            ("time", "quat"),
            q_LI,
            _a("1", "LVLH attitude: maps I into L (known to the chaser)"),
        ),
    }


def rig_variables(rig: sensors.StereoRig) -> dict[str, tuple]:
    """The rig's calibration as dataset variables (shared by every stereo measurement file)."""
    cams = (rig.left, rig.right)
    return {
        "R_CkC": (
            ("camera", "row", "col"),
            np.stack([c.R_CkC for c in cams]),
            _a("1", "rotation from the rig frame C into the camera frame"),
        ),
        "p_CkinC": (
            ("camera", "xyz"),
            np.stack([c.p_CkinC for c in cams]),
            _a("m", "camera centre in the rig frame C"),
        ),
        "focal_px": (
            ("camera",),
            np.array([c.focal_px for c in cams]),
            _a("px", "focal length"),
        ),
        "principal_point_px": (
            ("camera", "pixel"),
            np.array([c.principal_point_px for c in cams], dtype=float),
            _a("px", "principal point (cu, cv)"),
        ),
        "resolution_px": (
            ("camera", "pixel"),
            np.array([c.resolution_px for c in cams], dtype=float),
            _a("px", "image size (W, H)"),
        ),
    }


def rig_from_dataset(ds: xr.Dataset) -> sensors.StereoRig:
    """The rig of a stereo measurement file (:func:`rig_variables`, attribute ``rig``)."""
    cams = []
    for k in range(2):
        cu, cv = (float(x) for x in ds["principal_point_px"].values[k])
        width, height = (int(x) for x in ds["resolution_px"].values[k])
        cams.append(
            sensors.Camera(
                focal_px=float(ds["focal_px"].values[k]),
                principal_point_px=(cu, cv),
                resolution_px=(width, height),
                R_CkC=np.asarray(ds["R_CkC"].values[k], dtype=float),
                p_CkinC=np.asarray(ds["p_CkinC"].values[k], dtype=float),
            )
        )
    return sensors.StereoRig(left=cams[0], right=cams[1], kind=str(ds.attrs.get("rig", "parallel")))
