"""Depth point clouds: what a flash LIDAR / ToF camera gives (one scan per epoch in the
sensor frame), the input of the plane front end and ekf-depth; ``measurements.nc``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr
from numpy.typing import NDArray

from tumblenav.errors import InputError
from tumblenav.measurements._attrs import _a

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DepthMeasurements:
    """Ray-cast point clouds in the sensor frame S (= the rig frame C of the chaser's pointing).

    points : (n, R, 3) m -- [time, ray, xyz], NaN where a ray returned nothing.
    observed : (n, R) bool.  q_CL, q_LI : (n, 4) -- sensor and LVLH attitudes (known).
    """

    t: Array
    points: Array
    observed: NDArray[np.bool_]
    q_CL: Array
    q_LI: Array
    fov_rad: float
    range_noise_m: float

    def to_dataset(self, scenario_name: str = "") -> xr.Dataset:
        from tumblenav.io import with_coordinates

        ds = xr.Dataset(
            {
                "points": (
                    ("time", "ray", "xyz"),
                    self.points,
                    _a("m", "the returns of each scan in the sensor frame S; NaN where none"),
                ),
                "observed": (
                    ("time", "ray"),
                    self.observed.astype(np.int8),
                    _a("1", "1 for a return, 0 for padding"),
                ),
                "q_CL": (
                    ("time", "quat"),
                    self.q_CL,
                    _a("1", "sensor attitude: maps L into S (known to the chaser)"),
                ),
                "q_LI": (
                    ("time", "quat"),
                    self.q_LI,
                    _a("1", "LVLH attitude: maps I into L (known to the chaser)"),
                ),
            },
            attrs={
                "title": "tumblenav depth measurements",
                "scenario": scenario_name,
                "sensor": "flash LIDAR / ToF, boresight +y of S",
                "fov_rad": self.fov_rad,
                "range_noise_m": self.range_noise_m,
            },
        )
        return with_coordinates(ds, time=self.t, ray=np.arange(self.points.shape[1]))

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> DepthMeasurements:
        """The clouds of a depth ``measurements.nc`` dataset; InputError if a variable or a
        global attribute is missing."""
        variables = ("points", "observed", "q_CL", "q_LI")
        missing = [k for k in variables if k not in ds.variables]
        missing += [f"attribute {k}" for k in ("fov_rad", "range_noise_m") if k not in ds.attrs]
        if missing:
            raise InputError(f"depth measurements: missing {', '.join(missing)}")
        return cls(
            t=np.asarray(ds["time"].values, dtype=float),
            points=np.asarray(ds["points"].values, dtype=float),
            observed=np.asarray(ds["observed"].values).astype(bool),
            q_CL=np.asarray(ds["q_CL"].values, dtype=float),
            q_LI=np.asarray(ds["q_LI"].values, dtype=float),
            fov_rad=float(ds.attrs["fov_rad"]),
            range_noise_m=float(ds.attrs["range_noise_m"]),
        )
