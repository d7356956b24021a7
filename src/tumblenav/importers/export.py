"""Write a simulated run in the formats ``tumblenav import`` reads (docs/own_data.md): stereo
tracks as CSV or Parquet, depth clouds as PLY or PCD files with an index, image pairs as PNG
files with an index, each with its ``calibration.yaml`` (stereo calibration in OpenCV's form,
noise, the chaser's attitude per epoch in ``attitude.csv`` and its orbit).

Floats are written exactly (``repr`` in text, float64 in binary files). With the default
``camera_axes: tumblenav`` and ``pixel_origin: centre`` nothing is computed on the way out or
back for a parallel rig, so export -> import gives the very same measurements (bit for bit);
``camera_axes: opencv`` / ``pixel_origin: opencv`` write what an OpenCV pipeline would (rows
flipped, ``v = H - v``, half-pixel shift), equal after import to rounding (~1e-13 px).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tumblenav import rotations as rot
from tumblenav import sensors
from tumblenav.importers.calibration import R_TN_CV
from tumblenav.importers.clouds import write_pcd, write_ply
from tumblenav.importers.tables import write_table
from tumblenav.io import atomic_write
from tumblenav.measurements import DepthMeasurements, StereoImageMeasurements, StereoMeasurements

__all__ = ["export_clouds", "export_images", "export_run", "export_tracks"]


def _rotate(R: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``q(R) (x) q``; ``q`` itself (no arithmetic) when R is the identity."""
    if np.array_equal(R, np.eye(3)):
        return np.asarray(q, dtype=float)
    return rot.quat_multiply(rot.matrix_to_quat(R), q)


def stereo_calibration_keys(rig: sensors.StereoRig, axes: str, origin: str) -> dict[str, Any]:
    """The calibration keys (K1, D1, K2, D2, R, T_m, image_size_px, camera_axes,
    pixel_origin) of a tumblenav rig, as an OpenCV calibration would give them."""
    o = 0.5 if origin == "opencv" else 0.0
    L, Rt = rig.left, rig.right
    R_10 = Rt.R_CkC @ L.R_CkC.T
    p = L.R_CkC @ (Rt.p_CkinC - L.p_CkinC)
    T = -(R_10 @ p)
    W, H = L.resolution_px
    Ks = []
    for c in (L, Rt):
        cu, cv = c.principal_point_px
        cy = (cv - o) if axes == "tumblenav" else (float(H) - cv) - o
        Ks.append([[c.focal_px, 0.0, cu - o], [0.0, c.focal_px, cy], [0.0, 0.0, 1.0]])
    if axes == "opencv":
        R_10 = R_TN_CV.T @ R_10 @ R_TN_CV
        T = R_TN_CV.T @ T
    return {
        "camera_axes": axes,
        "pixel_origin": origin,
        "image_size_px": [int(W), int(H)],
        "K1": Ks[0],
        "D1": [0.0, 0.0, 0.0, 0.0, 0.0],
        "K2": Ks[1],
        "D2": [0.0, 0.0, 0.0, 0.0, 0.0],
        "R": R_10.tolist(),
        "T_m": [float(x) for x in T],
    }


def _chaser_keys(scenario, folder: Path, t, q_C0L, q_LI) -> dict[str, Any]:
    cols = {"t_s": np.asarray(t, float)}
    for name, q in (("q_CL", q_C0L), ("q_LI", q_LI)):
        for i, c in enumerate("xyzw"):
            cols[f"{name}_{c}"] = np.asarray(q)[:, i]
    write_table(folder / "attitude.csv", cols)
    orbit = scenario.chaser.orbit
    return {
        "attitude_file": "attitude.csv",
        "orbit": None if orbit is None else orbit.model_dump(mode="json"),
    }


def _write_yaml(path: Path, data: dict[str, Any], comment: str) -> Path:
    text = "".join(f"# {line}\n" for line in comment.splitlines()) + yaml.safe_dump(
        data, sort_keys=False, default_flow_style=None, width=100
    )
    return atomic_write(Path(path), lambda tmp: tmp.write_text(text, encoding="utf-8"))


def export_tracks(
    meas: StereoMeasurements,
    scenario,
    folder: Path,
    table: str = "tracks.csv",
    camera_axes: str = "tumblenav",
    pixel_origin: str = "centre",
) -> list[Path]:
    """``folder/tracks.csv`` (or ``.parquet``: by the name), ``attitude.csv`` and
    ``calibration.yaml`` of stereo tracks. A row per epoch and feature seen by a camera; a
    feature never seen gets one empty row at the first epoch (so that the feature count stays),
    an epoch with nothing seen a row with an empty feature_id."""
    from tumblenav.importers.calibration import StereoCalibration

    folder = Path(folder)
    cal = StereoCalibration(
        meas.rig, {}, np.eye(3), camera_axes, pixel_origin, meas.rig.left.resolution_px
    )
    uv = cal.from_tumblenav_uv(np.where(meas.observed[..., None], meas.uv, np.nan))
    n, _, N, _ = uv.shape
    seen = np.asarray(np.asarray(meas.observed, dtype=bool).any(axis=1), dtype=bool)  # (n, N)
    never = ~seen.any(axis=0)
    none = np.zeros_like(never)
    rows_t, rows_id, rows_px = [], [], []
    for k in range(n):
        ids = np.flatnonzero(seen[k] | (never if k == 0 else none))
        if len(ids) == 0:
            rows_t.append(meas.t[k])
            rows_id.append("")
            rows_px.append(np.full(4, np.nan))
        for j in ids:
            rows_t.append(meas.t[k])
            rows_id.append(str(j))
            rows_px.append(uv[k, :, j, :].reshape(4))
    px = np.array(rows_px).reshape(-1, 4)
    path = write_table(
        folder / table,
        {
            "t_s": np.array(rows_t, float),
            "feature_id": np.array(rows_id, dtype=object),
            "u_left_px": px[:, 0],
            "v_left_px": px[:, 1],
            "u_right_px": px[:, 2],
            "v_right_px": px[:, 3],
        },
    )
    q_C0L = _rotate(meas.rig.left.R_CkC, meas.q_CL)
    if camera_axes == "opencv":
        q_C0L = _rotate(R_TN_CV.T, q_C0L)
    keys = {
        **stereo_calibration_keys(meas.rig, camera_axes, pixel_origin),
        "noise_px": float(meas.noise_px),
        **({"slide_px2_per_frame": meas.slide_px2_per_frame} if meas.slide_px2_per_frame else {}),
        **({} if meas.track_noise_px is None else {"track_noise_px": meas.track_noise_px}),
        "one_camera_sightings": "keep",
        "chaser": _chaser_keys(scenario, folder, meas.t, q_C0L, meas.q_LI),
    }
    cal_path = _write_yaml(
        folder / "calibration.yaml",
        keys,
        f"stereo tracks exported by tumblenav from scenario {scenario.name}\n"
        "import: tumblenav import stereo-tracks "
        f"{table} -o DIR",
    )
    return [path, folder / "attitude.csv", cal_path]


def export_clouds(
    meas: DepthMeasurements,
    scenario,
    folder: Path,
    cloud_format: str = "ply",
    binary: bool = False,
    camera_axes: str = "tumblenav",
) -> list[Path]:
    """``folder/clouds.csv`` (t_s, file), one ``clouds/NNNNNN.ply`` (or .pcd) per epoch with
    returns (an empty file cell where none), ``attitude.csv`` and ``calibration.yaml``."""
    folder = Path(folder)
    write = write_ply if cloud_format == "ply" else write_pcd
    names = []
    for k in range(len(meas.t)):
        pts = meas.points[k][meas.observed[k]]
        if len(pts) == 0:
            names.append("")
            continue
        if camera_axes == "opencv":
            pts = np.stack([pts[:, 0], -pts[:, 2], pts[:, 1]], axis=1)  # R_TN_CV^T, exact
        name = f"clouds/{k:06d}.{cloud_format}"
        write(folder / name, pts, binary=binary)
        names.append(name)
    index = write_table(
        folder / "clouds.csv", {"t_s": np.asarray(meas.t, float), "file": np.array(names, object)}
    )
    q = meas.q_CL if camera_axes == "tumblenav" else _rotate(R_TN_CV.T, meas.q_CL)
    keys = {
        "camera_axes": camera_axes,
        "fov_deg": float(np.degrees(meas.fov_rad)),
        "range_noise_m": float(meas.range_noise_m),
        "chaser": _chaser_keys(scenario, folder, meas.t, q, meas.q_LI),
    }
    cal_path = _write_yaml(
        folder / "calibration.yaml",
        keys,
        f"depth clouds exported by tumblenav from scenario {scenario.name}\n"
        "import: tumblenav import depth-clouds clouds.csv -o DIR",
    )
    return [index, folder / "attitude.csv", cal_path]


def export_images(
    meas: StereoImageMeasurements, scenario, folder: Path, camera_axes: str = "tumblenav"
) -> list[Path]:
    """``folder/images.csv`` (t_s, left, right), the PNG pairs under ``folder/images/``
    (upside down for ``camera_axes: opencv``), ``attitude.csv`` and ``calibration.yaml``."""
    from tumblenav.measurements.images import write_png

    folder = Path(folder)
    left, right = StereoImageMeasurements.file_names(len(meas.t))
    for k, (a, b) in enumerate(meas.pairs()):
        if camera_axes == "opencv":
            a, b = np.ascontiguousarray(a[::-1]), np.ascontiguousarray(b[::-1])
        write_png(folder / left[k], a)
        write_png(folder / right[k], b)
    index = write_table(
        folder / "images.csv",
        {
            "t_s": np.asarray(meas.t, float),
            "left": np.array(left, object),
            "right": np.array(right, object),
        },
    )
    q_C0L = _rotate(meas.rig.left.R_CkC, meas.q_CL)
    if camera_axes == "opencv":
        q_C0L = _rotate(R_TN_CV.T, q_C0L)
    keys = {
        **stereo_calibration_keys(meas.rig, camera_axes, "centre"),
        "noise_px": float(meas.noise_px),
        "chaser": _chaser_keys(scenario, folder, meas.t, q_C0L, meas.q_LI),
    }
    cal_path = _write_yaml(
        folder / "calibration.yaml",
        keys,
        f"stereo image pairs exported by tumblenav from scenario {scenario.name}\n"
        "import: tumblenav import stereo-images images.csv -o DIR",
    )
    return [index, folder / "attitude.csv", cal_path]


def export_run(meas, scenario, folder: Path, **options: Any) -> list[Path]:
    """Export any simulated measurements (tracks, clouds or image pairs) into ``folder``."""
    if isinstance(meas, StereoMeasurements):
        return export_tracks(meas, scenario, folder, **options)
    if isinstance(meas, DepthMeasurements):
        return export_clouds(meas, scenario, folder, **options)
    return export_images(meas, scenario, folder, **options)
