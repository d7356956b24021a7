"""Stereo image pairs: an index table (``t_s, left, right``) naming 8-bit grayscale PNG files
(paths relative to the index), with a stereo calibration. The images are checked (readable,
grayscale, the calibration's size) and copied into the output's ``images/`` folder: as they are
for ``camera_axes: opencv`` (a camera's images, top of the scene first, which is how
measurement files hold them), turned over for ``camera_axes: tumblenav`` (rows in the order of
tumblenav's ``v``, which grows up the scene: :mod:`tumblenav.measurements.images`)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.importers.calibration import load_context, stereo_calibration
from tumblenav.measurements import StereoImageMeasurements
from tumblenav.measurements.images import read_png, write_frame

__all__ = ["image_measurements"]


class _NoSource:
    def __len__(self) -> int:
        return 0

    def pair(self, k: int):
        raise IndexError(k)


def image_measurements(path: Path, cfg: dict, cal_path: Path, out: Path):
    """StereoImageMeasurements of an index and its calibration; the images copied into
    ``out/images``. Returns the measurements (without a frame source: the written
    measurements.nc names the copies), the calibration, the context, the time offset and the
    copied files (left, right, left, ...)."""
    from tumblenav.importers.clouds import read_index
    from tumblenav.importers.tables import row_name

    where = str(cal_path)
    path = Path(path)
    t_file, cols = read_index(path, ("left", "right"))
    cal = stereo_calibration(cfg, where)
    if cal.rectify is not None:
        raise InputError(
            "images need a calibration that is a tumblenav rig as it stands (fx = fy, K1 = K2, "
            "no distortion, parallel or symmetric toe-in): rectify the images first "
            "(cv2.stereoRectify, cv2.initUndistortRectifyMap, cv2.remap) and give the "
            "rectified calibration (P1, P2 as K1, K2; R = identity; zero distortion)",
            where,
        )
    try:
        noise_px = float(cfg["noise_px"])
    except (KeyError, TypeError, ValueError):
        raise InputError(
            "missing or bad key noise_px (1-sigma corner noise the estimators assume, px)", where
        ) from None
    if not (np.isfinite(noise_px) and noise_px > 0):
        raise InputError(f"noise_px must be > 0 px, got {cfg['noise_px']}", where)
    W, H = cal.size
    files: list[Path] = []
    names = StereoImageMeasurements.file_names(len(t_file))
    for i in range(len(t_file)):
        for side, dest in zip(("left", "right"), (names[0][i], names[1][i]), strict=True):
            name = cols[side][i]
            if name == "":
                raise InputError(f"{row_name(path, i)}: no {side} image", str(path))
            src = path.parent / name
            try:
                img = read_png(src, (H, W))
            except InputError as exc:
                raise InputError(
                    f"{exc.what} ({row_name(path, i)} of {path.name})", exc.where
                ) from None
            target = out / dest
            if cal.axes == "opencv":  # a camera's own image: the measurement file as it is
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, target)
            else:  # rows in tumblenav's order (row j = v): files hold the scene's top first
                write_frame(target, img)
            files.append(target)
    t_offset = float(t_file[0])
    t = t_file - t_offset if t_offset != 0 else t_file
    ctx = load_context(cfg, where, path.parent, t, cal.axes, t_offset)
    R = cal.R_CC0
    q_CL = (
        ctx.q_C0L
        if np.array_equal(R, np.eye(3))
        else rot.quat_multiply(rot.matrix_to_quat(R), ctx.q_C0L)
    )
    meas = StereoImageMeasurements(
        t=t, q_CL=q_CL, q_LI=ctx.q_LI, rig=cal.rig, noise_px=noise_px, source=_NoSource()
    )
    return meas, cal, ctx, t_offset, files
