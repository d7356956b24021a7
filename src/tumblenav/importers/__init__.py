"""A user's own measurements in (``tumblenav import KIND PATH -o DIR``): stereo feature tracks
(CSV or Parquet), depth point clouds (PLY or PCD files named by an index table) or stereo image
pairs (PNG files named by an index table), each with a calibration/context YAML in the form
people have (OpenCV's stereo calibration, the chaser's attitude and orbit), turned into the
``measurements.nc`` the estimators read plus a ``scenario.yaml`` whose sensor block is the
calibration's, so that ``tumblenav estimate DIR/scenario.yaml --measurements DIR`` runs.

The output is written into a temporary folder beside ``DIR`` and renamed at the end: bad data
(one-line :class:`~tumblenav.errors.InputError` naming the file, the row or key) leaves
nothing behind. docs/own_data.md documents the formats; :mod:`tumblenav.importers.export`
writes a simulated run in them (the round trip of tests/test_import.py).
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tumblenav.errors import InputError

__all__ = ["BASE_SCENARIO", "KINDS", "ImportResult", "import_measurements"]

KINDS = ("stereo-tracks", "depth-clouds", "stereo-images")
# the built-in scenario the imported scenario.yaml starts from (its estimator, tuning,
# process noise, target model), per kind -- tumblenav default
BASE_SCENARIO = {
    "stereo-tracks": "hu2024",
    "depth-clouds": "yu2019",
    "stereo-images": "chang2021_close",
}


@dataclass
class ImportResult:
    """What ``import`` wrote: ``files`` (in ``output``), the epochs, the scenario it derived,
    and warnings (one line each)."""

    output: Path
    files: list[Path]
    epochs: int
    scenario: str
    warnings: list[str] = field(default_factory=list)


def default_calibration(path: Path) -> Path:
    """``calibration.yaml`` beside the data file (or in the data folder)."""
    path = Path(path)
    return (path if path.is_dir() else path.parent) / "calibration.yaml"


def import_measurements(
    kind: str,
    path: Path,
    output: Path,
    calibration: Path | None = None,
    scenario: str | None = None,
) -> ImportResult:
    """Read a user's measurements of ``kind`` at ``path`` with the calibration/context YAML
    (default: ``calibration.yaml`` beside them) and write ``output/measurements.nc`` (for
    images also ``output/images/``) and ``output/scenario.yaml`` (``scenario``, default
    :data:`BASE_SCENARIO`, with the calibration's sensor, orbit and times). Every check runs
    before anything is written; the folder appears whole or not at all."""
    from tumblenav.importers.calibration import load_yaml
    from tumblenav.scenario import load_scenario

    if kind not in KINDS:
        raise InputError(f"unknown kind {kind!r} (one of {', '.join(KINDS)})", "KIND")
    path = Path(path)
    if not path.exists():
        raise InputError("not found", str(path))
    output = Path(output)
    if output.exists() and (not output.is_dir() or any(output.iterdir())):
        raise InputError(
            "exists and is not empty: give a new output folder (nothing was written)", str(output)
        )
    cal_path = Path(calibration) if calibration is not None else default_calibration(path)
    cfg = load_yaml(cal_path)
    cfg = _with_opencv_file(cfg, cal_path)
    base = load_scenario(scenario or BASE_SCENARIO[kind])
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{output.name}.", suffix=".tmp", dir=output.parent))
    try:
        result = _import(kind, path, cfg, cal_path, base, tmp)
        if output.exists():
            output.rmdir()  # empty, checked above
        tmp.rename(output)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    result.output = output
    result.files = [output / f.relative_to(tmp) for f in result.files]
    return result


def _with_opencv_file(cfg: dict, cal_path: Path) -> dict:
    """``opencv_calibration: FILE`` pulls the stereo keys from an OpenCV FileStorage file (the
    context YAML's own keys win)."""
    from tumblenav.importers.calibration import load_yaml

    ref = cfg.get("opencv_calibration")
    if ref is None:
        return cfg
    other = load_yaml(cal_path.parent / str(ref))
    return {**other, **{k: v for k, v in cfg.items() if k != "opencv_calibration"}}


def _import(kind: str, path: Path, cfg: dict, cal_path: Path, base, tmp: Path) -> ImportResult:
    from tumblenav import io

    warnings: list[str] = []
    files: list[Path] = []
    if kind == "stereo-tracks":
        from tumblenav.importers.tracks import tracks_measurements

        meas, cal, labels, warnings, ctx, t_offset = tracks_measurements(path, cfg, cal_path)
        sensor = {**cal.sensor, "noise": {"pixels": meas.noise_px}}
        ds = meas.to_dataset(f"{base.name} (imported)")
        ds["feature_label"] = (
            ("feature",),
            np.array(labels + [""] * (meas.uv.shape[2] - len(labels)), dtype=object),
            {"units": "1", "description": "the feature_id of the imported file"},
        )
        t = meas.t
    elif kind == "depth-clouds":
        from tumblenav.importers.clouds import depth_measurements

        meas, ctx, t_offset, sensor = depth_measurements(path, cfg, cal_path)
        sensor = {**base.sensor.model_dump(), **sensor} if base.sensor.kind == "depth" else sensor
        ds = meas.to_dataset(f"{base.name} (imported)")
        t = meas.t
    else:
        from tumblenav.importers.images import image_measurements

        meas, cal, ctx, t_offset, files = image_measurements(path, cfg, cal_path, tmp)
        sensor = {**cal.sensor, "noise": {"pixels": meas.noise_px}}
        if getattr(base.sensor, "images", None) is not None:
            sensor["images"] = base.sensor.images.model_dump()
        left = [str(f.relative_to(tmp)) for f in files[0::2]]
        right = [str(f.relative_to(tmp)) for f in files[1::2]]
        ds = meas.to_dataset(f"{base.name} (imported)", left, right)
        t = meas.t
    ds.attrs["imported_from"] = str(path)
    ds.attrs["calibration"] = str(cal_path)
    ds.attrs["time_offset_s"] = t_offset
    scenario = _derived_scenario(base, kind, sensor, ctx.orbit, t, path)
    from tumblenav.scenario import scenario_to_yaml

    sc_path = io.atomic_write(
        tmp / "scenario.yaml",
        lambda p: p.write_text(scenario_to_yaml(scenario), encoding="utf-8"),
    )
    files.append(io.write_netcdf(ds, tmp / "measurements.nc"))
    files.append(sc_path)
    # the very check `estimate DIR/scenario.yaml --measurements DIR` makes, before DIR exists
    from tumblenav.pipeline import _load_measurements

    _load_measurements(tmp, scenario)
    if t_offset:
        warnings.append(
            f"times start at t_s = {t_offset!r}: stored from 0 (attribute time_offset_s)"
        )
    return ImportResult(tmp, files, len(t), scenario.name, warnings)


def _derived_scenario(base, kind: str, sensor: dict, orbit, t: np.ndarray, path: Path):
    """``base`` with the calibration's sensor, the chaser's orbit, the data's duration and
    mean rate, no simulated occlusions, and its steady-state window if it still fits."""
    from tumblenav.scenario import validate_scenario

    data: dict[str, Any] = base.model_dump(mode="json")
    duration = float(t[-1] - t[0])
    if not duration > 0:
        raise InputError("needs at least two epochs at different times", str(path))
    data["name"] = f"{base.name}-imported"
    data["description"] = (
        f"{kind} imported from {path.name}: the calibration's sensor on built-in scenario "
        f"{base.name}'s estimator settings (its target block is not used by estimators)"
    )
    data["duration_s"] = duration
    # the mean rate (nominal: estimators use the measurement times); a scenario needs two
    # intervals at least, which two epochs do not have
    data["rate_hz"] = max(len(t) - 1, 2) / duration
    data["sensor"] = sensor
    data["chaser"]["orbit"] = orbit
    data["occlusion"] = {}
    w = data.get("steady_state_window_s")
    if w is not None and not (0 <= w[0] < w[1] <= duration):
        data["steady_state_window_s"] = None
    return validate_scenario(data, source=f"scenario derived from {base.name}")
