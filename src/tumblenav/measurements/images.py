"""Stereo image pairs: what a calibrated stereo camera rig gives before any feature is found
(Chang 2021), the input of the image front end (:mod:`tumblenav.frontends.stereo_images`),
which turns them into stereo feature tracks.

On disk (``tumblenav simulate`` with ``sensor.images``, or a user's own recording): a folder with
``measurements.nc`` (times, the chaser's attitudes, the rig's calibration and, per epoch, the
file names of the left and right image) and the images themselves, 8-bit grayscale PNG files
(``images/000000_left.png``, ``images/000000_right.png``, ... by default), named relative to the
folder. Images are read one pair at a time: a run of 1024 x 1024 pairs does not fit in memory.

Orientation: in memory an image's row j holds ``v`` in [j, j+1), and ``v`` grows along the
camera's ``z = x cross y`` axis, which points *up* in the scene (x right, y along the optical
axis). The files hold the rows as a camera delivers them, top of the scene first (the view a
person expects), so :func:`read_frame` and :func:`write_frame` turn the rows over; a file row
``r`` holds ``v`` in ``[H - r - 1, H - r)``.

In memory the pixels come from a :class:`FrameSource`: the files, or the renderer of a
simulation (rendering each pair when it is asked for, deterministic per epoch).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import xarray as xr
from numpy.typing import NDArray

from tumblenav import sensors
from tumblenav.errors import InputError
from tumblenav.measurements._attrs import _a
from tumblenav.measurements.stereo import (
    CAMERA_MODEL,
    attitude_variables,
    rig_from_dataset,
    rig_variables,
)

Array = NDArray[np.float64]
Image = NDArray[np.uint8]

__all__ = [
    "FrameSource",
    "PngFrames",
    "StereoImageMeasurements",
    "read_frame",
    "read_png",
    "write_frame",
    "write_png",
]


class FrameSource(Protocol):
    """Random access to the image pairs of a run."""

    def __len__(self) -> int: ...

    def pair(self, k: int) -> tuple[Image, Image]:
        """The (left, right) 8-bit grayscale images of epoch ``k``."""
        ...


def read_png(path: Path, shape_hw: tuple[int, int] | None = None) -> Image:
    """An 8-bit grayscale image; InputError naming the file if it is missing, unreadable, not
    8-bit grayscale, or not of ``shape_hw`` (height, width)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError("image file not found", str(path))
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("cannot read the image (not a PNG/JPEG/TIFF file?)", str(path))
    if img.ndim == 3 and img.shape[2] in (3, 4):
        raise InputError(
            f"a {img.shape[2]}-channel colour image: give 8-bit grayscale images", str(path)
        )
    if img.dtype != np.uint8 or img.ndim != 2:
        raise InputError(f"not an 8-bit grayscale image ({img.dtype}, {img.ndim} axes)", str(path))
    if shape_hw is not None and img.shape != tuple(shape_hw):
        h, w = shape_hw
        raise InputError(
            f"image is {img.shape[1]} x {img.shape[0]} px but the calibration says {w} x {h} px",
            str(path),
        )
    return np.asarray(img, dtype=np.uint8)


def write_png(path: Path, image: Image) -> Path:
    """Write an 8-bit grayscale PNG atomically."""
    import cv2

    from tumblenav.io import atomic_write

    def _write(tmp: Path) -> None:
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise OSError(f"cannot encode {path} as PNG")
        tmp.write_bytes(buf.tobytes())

    return atomic_write(Path(path), _write)


def read_frame(path: Path, shape_hw: tuple[int, int] | None = None) -> Image:
    """A measurement image file (top of the scene first) as tumblenav's array (row j = v)."""
    return np.ascontiguousarray(read_png(path, shape_hw)[::-1])


def write_frame(path: Path, image: Image) -> Path:
    """tumblenav's image array (row j = v) as a measurement file, top of the scene first."""
    return write_png(path, np.ascontiguousarray(np.asarray(image)[::-1]))


@dataclass(frozen=True)
class PngFrames:
    """Image pairs read from files (names relative to ``root``)."""

    root: Path
    left: tuple[str, ...]
    right: tuple[str, ...]
    shapes_hw: tuple[tuple[int, int], tuple[int, int]]

    def __len__(self) -> int:
        return len(self.left)

    def pair(self, k: int) -> tuple[Image, Image]:
        return (
            read_frame(self.root / self.left[k], self.shapes_hw[0]),
            read_frame(self.root / self.right[k], self.shapes_hw[1]),
        )


@dataclass(frozen=True)
class StereoImageMeasurements:
    """Stereo image pairs (from ``source``) with the rig's calibration and the chaser's own
    attitudes.

    t : (n,) s.  q_CL, q_LI : (n, 4) -- rig and LVLH attitudes (known to the chaser).
    noise_px : the corner localisation noise (1-sigma, px) the estimators assume for the
    features the front end will find in these images.
    """

    t: Array
    q_CL: Array
    q_LI: Array
    rig: sensors.StereoRig
    noise_px: float
    source: FrameSource

    def pairs(self) -> Iterator[tuple[Image, Image]]:
        """The image pairs in time order, one at a time."""
        for k in range(len(self.t)):
            yield self.source.pair(k)

    @staticmethod
    def file_names(n: int, folder: str = "images") -> tuple[list[str], list[str]]:
        return (
            [f"{folder}/{k:06d}_left.png" for k in range(n)],
            [f"{folder}/{k:06d}_right.png" for k in range(n)],
        )

    def write(
        self,
        directory: Path,
        scenario_name: str = "",
        progress: Callable[[int], None] | None = None,
    ) -> list[Path]:
        """Write the images (PNG) and ``measurements.nc`` into ``directory``; measurements.nc
        last, so that a folder with it is complete. ``progress(k)`` after each pair."""
        from tumblenav.io import write_netcdf

        directory = Path(directory)
        left, right = self.file_names(len(self.t))
        for k, (img_l, img_r) in enumerate(self.pairs()):
            write_frame(directory / left[k], img_l)
            write_frame(directory / right[k], img_r)
            if progress is not None:
                progress(k)
        ds = self.to_dataset(scenario_name, left, right)
        return [directory / "images", write_netcdf(ds, directory / "measurements.nc")]

    def to_dataset(self, scenario_name: str, left: list[str], right: list[str]) -> xr.Dataset:
        from tumblenav.io import with_coordinates

        ds = xr.Dataset(
            {
                "left_image": (
                    ("time",),
                    np.array(left, dtype=object),
                    _a("1", "left image file (8-bit grayscale), relative to this file's folder"),
                ),
                "right_image": (
                    ("time",),
                    np.array(right, dtype=object),
                    _a("1", "right image file (8-bit grayscale), relative to this file's folder"),
                ),
                **attitude_variables(self.q_CL, self.q_LI),
                **rig_variables(self.rig),
            },
            attrs={
                "title": "tumblenav stereo images",
                "kind": "stereo-images",
                "scenario": scenario_name,
                "rig": self.rig.kind,
                "baseline_m": self.rig.baseline_m,
                "noise_px": self.noise_px,
                "camera_model": CAMERA_MODEL + "; pixel (column i, row j) is centred at "
                "(u, v) = (i + 0.5, j + 0.5)",
            },
        )
        return with_coordinates(ds, time=self.t)

    @classmethod
    def from_dataset(cls, ds: xr.Dataset, root: Path) -> StereoImageMeasurements:
        """The image pairs a ``measurements.nc`` of kind stereo-images names (files relative
        to ``root``); InputError if a variable is missing. The images are read when used."""
        need = ("left_image", "right_image", "q_CL", "q_LI", "focal_px", "resolution_px")
        missing = [k for k in need if k not in ds.variables]
        if missing:
            raise InputError(f"stereo images: missing {', '.join(missing)}")
        rig = rig_from_dataset(ds)
        shapes = tuple((c.resolution_px[1], c.resolution_px[0]) for c in rig.cameras)
        return cls(
            t=np.asarray(ds["time"].values, dtype=float),
            q_CL=np.asarray(ds["q_CL"].values, dtype=float),
            q_LI=np.asarray(ds["q_LI"].values, dtype=float),
            rig=rig,
            noise_px=float(ds.attrs.get("noise_px", np.nan)),
            source=PngFrames(
                Path(root),
                tuple(str(x) for x in ds["left_image"].values),
                tuple(str(x) for x in ds["right_image"].values),
                (shapes[0], shapes[1]),
            ),
        )
