"""File formats: NetCDF through xarray (truth, measurements, estimates) and JSON summaries.

Every write is atomic: the data go to a temporary file in the destination folder, which is
then renamed over the target (``os.replace``), so an interrupted run never leaves a
half-written file behind and an existing good file is never lost.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from tumblenav.errors import InputError

FORMAT_VERSION = "1"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_netcdf(ds: xr.Dataset, path: str | Path) -> Path:
    """Write ``ds`` to NetCDF-4 atomically (compressed float variables)."""
    ds = ds.copy()
    ds.attrs.setdefault("tumblenav_format", FORMAT_VERSION)
    encoding = {
        name: {"zlib": True, "complevel": 4}
        for name, var in ds.data_vars.items()
        if var.dtype.kind in "fiu" and var.ndim > 0
    }

    def _write(tmp: Path) -> None:
        ds.to_netcdf(tmp, engine="netcdf4", encoding=encoding)

    return atomic_write(Path(path), _write)


def read_netcdf(path: str | Path, required: tuple[str, ...] = ()) -> xr.Dataset:
    """Open a tumblenav NetCDF file fully into memory; InputError if missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", str(path))
    try:
        with xr.open_dataset(path, engine="netcdf4") as ds:
            ds = ds.load()
    except Exception as exc:  # netCDF4/HDF5 raise many types for a bad file
        raise InputError(
            f"not a readable NetCDF file ({exc.__class__.__name__})", str(path)
        ) from None
    missing = [v for v in required if v not in ds.variables]
    if missing:
        raise InputError(f"missing variable(s) {', '.join(missing)}", str(path))
    return ds


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_json(obj: Any, path: str | Path) -> Path:
    """Write JSON atomically; NaN/inf become null (valid JSON)."""
    text = json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n"

    def _write(tmp: Path) -> None:
        tmp.write_text(text, encoding="utf-8")

    return atomic_write(Path(path), _write)


def read_json(path: str | Path) -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("file not found", str(path)) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", str(path)) from None


def estimates_dataset(history, scenario: str, estimator: str, x_true=None) -> xr.Dataset:
    """``estimates.nc``: every state block, its 1-sigma, the full error-state covariance,
    NIS, and (when the truth is known) the error state."""
    lay = history.layout
    data: dict = {}
    for b in lay.blocks:
        val = history.x[:, lay.nom(b.name)]
        sig = history.sigma(b.name)
        if b.kind == "quat":
            data[b.name] = (
                ("time", "quat"),
                val,
                {"units": "1", "description": f"{b.name} q_TI [x,y,z,w]"},
            )
            data[f"sigma_{b.name}"] = (
                ("time", "xyz"),
                sig,
                {"units": "rad", "description": "1-sigma of the attitude error in T"},
            )
        elif b.name == "features":
            n = val.shape[1] // 3
            data[b.name] = (("time", "feature", "xyz"), val.reshape(-1, n, 3), {"units": "m"})
            data[f"sigma_{b.name}"] = (
                ("time", "feature", "xyz"),
                sig.reshape(-1, n, 3),
                {"units": "m"},
            )
        else:
            dim = f"{b.name}_component"
            data[b.name] = (("time", dim), val, {"units": _BLOCK_UNITS.get(b.name, "1")})
            data[f"sigma_{b.name}"] = (("time", dim), sig, {"units": _BLOCK_UNITS.get(b.name, "1")})
    data["covariance"] = (
        ("time", "state", "state_"),
        history.P,
        {"description": "error-state covariance; blocks in attribute 'layout'"},
    )
    data["nis"] = (("time",), history.nis, {"description": "normalised innovation squared"})
    data["nis_dof"] = (("time",), history.nis_dof)
    if x_true is not None:
        data["error"] = (
            ("time", "state"),
            lay.boxminus(x_true, history.x),
            {"description": "truth [-] estimate, error-state coordinates"},
        )
    layout_txt = "; ".join(
        f"{b.name}:{lay.err(b.name).start}-{lay.err(b.name).stop}" for b in lay.blocks
    )
    return xr.Dataset(
        data,
        coords={
            "time": ("time", history.t, {"units": "s"}),
            "quat": ["x", "y", "z", "w"],
            "xyz": ["x", "y", "z"],
        },
        attrs={
            "title": "tumblenav estimates",
            "scenario": scenario,
            "estimator": estimator,
            "layout": layout_txt,
            "skipped": "; ".join(f"{k}={v}" for k, v in history.skipped.items()),
            "frames": "attitude maps I into the estimator's principal frame T; position "
            "and velocity in L; features in T",
        },
    )


_BLOCK_UNITS = {"rate": "rad/s", "position": "m", "velocity": "m/s", "offset": "m"}
