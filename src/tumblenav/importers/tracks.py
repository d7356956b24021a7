"""Stereo feature tracks from a CSV or Parquet table: one row per epoch and feature,
``t_s, feature_id, u_left_px, v_left_px, u_right_px, v_right_px``; NaN (an empty cell) or a
missing row where a camera did not see the feature; a row with an empty ``feature_id`` (and no
pixels) marks an epoch at which nothing was seen."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.importers.calibration import (
    Context,
    StereoCalibration,
    _number,
    load_context,
    stereo_calibration,
)
from tumblenav.importers.tables import missing_columns, read_table, row_name
from tumblenav.measurements import StereoMeasurements

COLUMNS = ("t_s", "feature_id", "u_left_px", "v_left_px", "u_right_px", "v_right_px")
ONE_CAMERA = ("error", "drop", "keep")

__all__ = ["COLUMNS", "TrackTable", "read_tracks", "tracks_measurements"]


@dataclass(frozen=True)
class TrackTable:
    """The table as read: epochs ``t`` (s, as in the file), feature labels, and pixels
    ``uv`` (n, 2, N, 2) in the file's convention, NaN where unseen."""

    t: NDArray[np.float64]
    labels: list[str]
    uv: NDArray[np.float64]
    one_camera: int  # sightings by one camera only


def _feature_order(ids: list[str]) -> list[str]:
    """Integer IDs in numerical order (feature k = ID k for 0 ... N-1), others as text."""
    try:
        return sorted(ids, key=lambda s: (int(s), s))
    except ValueError:
        return sorted(ids)


def read_tracks(path: Path) -> TrackTable:
    """The rows of a tracks file, checked: InputError naming the file and row for a missing
    column, unsorted times, a feature twice at one time, or a pixel pair with one half NaN."""
    path = Path(path)
    cols = read_table(
        path, text=("feature_id",), numeric=tuple(c for c in COLUMNS if c != "feature_id")
    )
    missing_columns(cols, COLUMNS, path)
    t_all = cols["t_s"]
    fid = cols["feature_id"]
    if len(t_all) == 0:
        raise InputError("no rows", str(path))
    bad = ~np.isfinite(t_all)
    if bad.any():
        raise InputError(
            f"{row_name(path, int(np.flatnonzero(bad)[0]))}: t_s is not a number", str(path)
        )
    back = np.flatnonzero(np.diff(t_all) < 0)
    if len(back):
        i = int(back[0]) + 1
        raise InputError(
            f"{row_name(path, i)}: t_s {float(t_all[i])!r} is earlier than the row before "
            f"({float(t_all[i - 1])!r}): sort the rows by time",
            str(path),
        )
    px = np.stack([cols[c] for c in COLUMNS[2:]], axis=1).reshape(-1, 2, 2)  # row, cam, uv
    inf = np.isinf(px)
    if inf.any():
        i, cam, c = (int(x) for x in np.argwhere(inf)[0])
        raise InputError(
            f"{row_name(path, i)}: {('u', 'v')[c]}_{('left', 'right')[cam]}_px is infinite "
            "(give a pixel coordinate, or leave both empty where the camera did not see it)",
            str(path),
        )
    fin = np.isfinite(px)
    half = fin[:, :, 0] != fin[:, :, 1]
    if half.any():
        i, cam = (int(x) for x in np.argwhere(half)[0])
        name = ("left", "right")[cam]
        raise InputError(
            f"{row_name(path, i)}: NaN in u_{name}_px or v_{name}_px but not both (a sighting "
            "needs both pixel coordinates; leave both empty where the camera did not see it)",
            str(path),
        )
    empty_id = fid == ""
    stray = empty_id & fin.any(axis=(1, 2))
    if stray.any():
        raise InputError(
            f"{row_name(path, int(np.flatnonzero(stray)[0]))}: pixels without a feature_id",
            str(path),
        )
    t, epoch = np.unique(t_all, return_inverse=True)
    labels = _feature_order(sorted(set(fid[~empty_id].tolist())))
    index = {s: j for j, s in enumerate(labels)}
    uv = np.full((len(t), 2, max(len(labels), 1), 2), np.nan)
    seen = np.zeros((len(t), max(len(labels), 1)), dtype=bool)
    for r in np.flatnonzero(~empty_id).tolist():
        k, j = int(epoch[r]), index[fid[r]]
        if seen[k, j]:
            raise InputError(
                f"{row_name(path, r)}: feature {fid[r]} twice at t_s {float(t_all[r])!r} "
                "(duplicate timestamp for this feature)",
                str(path),
            )
        seen[k, j] = True
        uv[k, :, j, :] = px[r]
    obs = np.isfinite(uv[..., 0])
    one = int((obs[:, 0] != obs[:, 1]).sum())
    return TrackTable(t=t, labels=labels, uv=uv, one_camera=one)


def tracks_measurements(
    path: Path, cfg: dict, cfg_path: Path
) -> tuple[StereoMeasurements, StereoCalibration, list[str], list[str], Context, float]:
    """StereoMeasurements of a tracks file and its calibration/context mapping, the
    calibration as read, the feature labels, warnings, the chaser's context and the time
    offset (the first t_s: times are stored from 0)."""
    where = str(cfg_path)
    table = read_tracks(path)
    cal = stereo_calibration(cfg, where)
    one_camera = cfg.get("one_camera_sightings", "error")
    if one_camera not in ONE_CAMERA:
        raise InputError(
            f"one_camera_sightings: {one_camera!r} is not one of {', '.join(ONE_CAMERA)}", where
        )
    uv = table.uv
    W, H = cal.size
    with np.errstate(invalid="ignore"):
        outside = (uv[..., 0] < -1) | (uv[..., 0] > W) | (uv[..., 1] < -1) | (uv[..., 1] > H)
    if outside.any():
        k, cam, j = (int(x) for x in np.argwhere(outside)[0])
        u, v = (float(c) for c in uv[k, cam, j])
        raise InputError(
            f"feature {table.labels[j]} at t_s {float(table.t[k])!r}: the "
            f"{('left', 'right')[cam]} pixel ({u:g}, {v:g}) lies outside the {W} x {H} image "
            "(image_size_px in the calibration)",
            str(path),
        )
    warnings = []
    if table.one_camera:
        obs = np.isfinite(uv[..., 0])
        mono = obs[:, 0] != obs[:, 1]
        if one_camera == "error":
            k, j = (int(x) for x in np.argwhere(mono)[0])
            raise InputError(
                f"feature {table.labels[j]} at t_s {float(table.t[k])!r} is seen by one camera only "
                f"({table.one_camera} such sightings; set one_camera_sightings: drop or keep in "
                f"{cfg_path.name} to accept them)",
                str(path),
            )
        if one_camera == "drop":
            uv = np.where(mono[:, None, :, None], np.nan, uv)
            warnings.append(
                f"dropped {table.one_camera} sightings by one camera only (one_camera_sightings: "
                "drop)"
            )
    if cal.note:
        warnings.append(cal.note)
    uv_tn = cal.to_tumblenav_uv(uv)
    observed = np.isfinite(uv_tn[..., 0])
    t_offset = float(table.t[0])
    t = table.t - t_offset if t_offset != 0 else table.t
    noise = cfg.get("noise_px")
    try:
        noise_px = float(noise)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(
            "missing or bad key noise_px (1-sigma pixel noise the estimators weight by, px)", where
        ) from None
    if not (np.isfinite(noise_px) and noise_px > 0):
        raise InputError(f"noise_px must be > 0 px, got {noise}", where)
    slide_px2 = _number(cfg, "slide_px2_per_frame", where, 0.0)  # absent: tracks that stay
    if slide_px2 < 0:
        raise InputError(f"slide_px2_per_frame must be >= 0 px^2 per frame, got {slide_px2}", where)
    track_noise: float | None = None  # absent: every sighting at noise_px
    if cfg.get("track_noise_px") is not None:
        track_noise = _number(cfg, "track_noise_px", where)  # a finite number, or InputError
        if not track_noise > 0:
            raise InputError(f"track_noise_px must be > 0 px, got {cfg['track_noise_px']}", where)
    ctx = load_context(cfg, where, Path(path).parent, t, cal.axes, t_offset)
    R = cal.R_CC0
    if np.array_equal(R, np.eye(3)):
        q_CL = ctx.q_C0L
    else:
        q_CL = rot.quat_multiply(rot.matrix_to_quat(R), ctx.q_C0L)
    meas = StereoMeasurements(
        t=t,
        uv=uv_tn,
        observed=observed,
        q_CL=q_CL,
        q_LI=ctx.q_LI,
        rig=cal.rig,
        noise_px=noise_px,
        slide_px2_per_frame=slide_px2,
        track_noise_px=track_noise,
    )
    return meas, cal, table.labels, warnings, ctx, t_offset
