"""The NetCDF formats as tables, generated from the code that writes the files.

docs/formats.md holds these tables between the markers ``<!-- BEGIN GENERATED: NAME -->``
and ``<!-- END GENERATED: NAME -->``. Each table is read off a file written and read back by
the same code as the CLI: truth and measurements from two seconds of a built-in scenario,
estimates from a history in every registered estimator's state layout. The dimensions,
units and descriptions therefore come from the files themselves; only the meaning of the
global attributes is written here (:data:`ATTRIBUTES`), and a file attribute without one, or
one without a file attribute, is an error.

Regenerate the tables in place, or check them (exit status 1 when out of date)::

    .venv/bin/python -m tumblenav.formats --write docs/formats.md
    .venv/bin/python -m tumblenav.formats --check docs/formats.md

Without arguments it prints every generated section, markers included.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from pydantic import BaseModel

from tumblenav import io
from tumblenav.estimators.base import EstimateHistory, StateLayout

# The meaning of each global attribute (the values depend on the run).
ATTRIBUTES: dict[str, str] = {
    "title": "what the file is",
    "scenario": "name of the scenario",
    "tumblenav_format": "format version",
    "quaternion_convention": "the quaternion convention",
    "frames": "the frames the variables are expressed in",
    "rig": "`parallel` or `convergent`",
    "baseline_m": "distance between the centres of projection (m)",
    "noise_px": "1-sigma noise on each of u and v (px); the estimators weight by it",
    "slide_px2_per_frame": "how fast a track slides over the surface, as a random walk across "
    "the line of sight (px^2 per frame, each of u and v; 0: tracks that stay on their points); "
    "ekf-pose lets its map points walk by it",
    "track_noise_px": "1-sigma noise (px, each of u and v) of a track's sightings after its "
    "first (equal to `noise_px` unless the tracker states it apart, as the image front end's "
    "affine refinement does); ekf-pose weights its updates by it",
    "camera_model": "the projection that gives `uv` from points in the camera frames",
    "sensor": "the sensor and its boresight",
    "fov_rad": "square field of view (rad)",
    "range_noise_m": "1-sigma range noise along each ray (m)",
    "estimator": "name of the estimator",
    "layout": "error-state slice of each block, `name:start-stop`, for example "
    "`attitude:0-3; rate:3-6; ...`",
    "skipped": "measurements the estimator skipped and why, `reason=count; ...`",
    "kind": "the measurement type (`stereo-images`)",
}
# Attributes whose value is the same in every file of its kind: shown in the tables.
_FIXED_VALUES: tuple[str, ...] = ("title", "tumblenav_format", "quaternion_convention", "frames")
_FIXED_VALUES += ("camera_model", "sensor", "kind")

# Sizes of the dimensions whose size depends on the run.
_SIZES = {
    "time": "n",
    "feature": "N",
    "ray": "R",
    "state": "m",
    "state_": "m",
    "inertia_param": "k",
}

_EXAMPLE_FEATURES = 2


def estimator_layouts(n_features: int) -> dict[str, StateLayout]:
    """The state layout of every registered estimator, with ``n_features`` features."""
    from tumblenav.estimators import ukf
    from tumblenav.estimators.chang2021 import model as chang_model
    from tumblenav.estimators.hu2024 import model as hu_model
    from tumblenav.estimators.yu2019 import model as yu_model

    hu, kabir = hu_model.layout(n_features), ukf.layout(n_features)
    return {
        "ekf-dpacf": hu,
        "ekf-baseline": hu,
        "ekf-depth": yu_model.LAYOUT,
        "ekf-pose": chang_model.LAYOUT,
        "ukf": kabir,
        "ukf-mult": kabir,
        "ukf-gp": kabir,
    }


def _written(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` as the file holds it: written by :func:`io.write_netcdf` and read back."""
    with tempfile.TemporaryDirectory() as tmp:
        path = io.write_netcdf(ds, Path(tmp) / "example.nc")
        return io.read_netcdf(path)


def _history(layout: StateLayout, n: int = 2) -> EstimateHistory:
    """A history of ``n`` epochs in ``layout`` (identity attitudes, unit covariance)."""
    x = np.zeros((n, layout.nominal_dim))
    for b in layout.blocks:
        if b.kind == "quat":
            x[:, layout.nom(b.name).stop - 1] = 1.0
    return EstimateHistory(
        t=np.arange(n, dtype=float),
        x=x,
        P=np.broadcast_to(np.eye(layout.dim), (n, layout.dim, layout.dim)).copy(),
        layout=layout,
        nis=np.full(n, np.nan),
        nis_dof=np.zeros(n),
    )


def _example_images():
    """Two epochs of stereo image pairs (the rig of chang2021_close) without rendering."""
    from tumblenav import sensors
    from tumblenav.measurements import StereoImageMeasurements
    from tumblenav.scenario import load_scenario

    rig = sensors.make_rig(load_scenario("chang2021_close").sensor)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (2, 1))
    return StereoImageMeasurements(
        t=np.array([0.0, 0.2]),
        q_CL=q,
        q_LI=q,
        rig=rig,
        noise_px=0.5,
        source=None,  # type: ignore[arg-type]
    )


def example_files() -> dict[str, xr.Dataset]:
    """truth.nc, both measurements.nc and estimates.nc of every estimator, as written."""
    from tumblenav.measurements import StereoImageMeasurements
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate

    out = {}
    for name, label in (("hu2024", "stereo"), ("yu2019", "depth")):
        s = load_scenario(name).with_updates(duration_s=2.0, steady_state_window_s=None)
        truth, meas = simulate(s, 0)
        assert not isinstance(meas, StereoImageMeasurements)  # tracks or clouds here
        if label == "stereo":
            out["truth.nc"] = _written(truth.to_dataset(s.name))
        out[f"measurements.nc ({label})"] = _written(meas.to_dataset(s.name))
    out["measurements.nc (stereo images)"] = _written(
        _example_images().to_dataset("example", *StereoImageMeasurements.file_names(2))
    )
    for est, layout in estimator_layouts(_EXAMPLE_FEATURES).items():
        hist = _history(layout)
        out[f"estimates.nc {est}"] = _written(io.estimates_dataset(hist, "example", est, hist.x))
    return out


# --- tables ----------------------------------------------------------------------------------


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _code(names: Iterable[object]) -> str:
    return ", ".join(f"`{n}`" for n in names)


def _coordinate_values(coord: xr.DataArray) -> str:
    dim = str(coord.dims[0])
    fixed = io.DIMENSIONS.get(dim, (None, ""))[0]
    if coord.name == dim and fixed is not None:
        return _code(fixed)
    if coord.dtype.kind in "iu":
        return f"integers 0 ... {_SIZES.get(dim, 'size')}-1"
    if coord.dtype.kind == "f":
        return f"numbers ({coord.attrs.get('units', '1')})"
    return "labels (see meaning)" if coord.name == dim else "strings"


def _coordinates_rows(files: Sequence[xr.Dataset]) -> list[list[str]]:
    rows: dict[str, list[str]] = {}
    for ds in files:
        for name, coord in ds.coords.items():
            dim = str(coord.dims[0])
            size = _SIZES.get(dim, str(ds.sizes[dim]))
            if name != dim:
                size = f"on `{dim}`"
            row = [f"`{name}`", size, _coordinate_values(coord), coord.attrs["description"]]
            if rows.setdefault(str(name), row) != row:
                raise ValueError(
                    f"coordinate {name} differs between files: {rows[str(name)]}, {row}"
                )
    return list(rows.values())


def _variable_row(var: xr.DataArray) -> list[str]:
    kind = "str" if var.dtype.kind in "OUS" else str(var.dtype)
    dims = ", ".join(str(d) for d in var.dims)
    return [f"`{var.name}`", dims, kind, var.attrs["units"], var.attrs["description"]]


def _variables_rows(files: Sequence[xr.Dataset]) -> list[list[str]]:
    rows: dict[str, list[str]] = {}
    for ds in files:
        for name, var in ds.data_vars.items():
            row = _variable_row(var)
            if rows.setdefault(str(name), row) != row:
                raise ValueError(f"variable {name} differs between files: {rows[str(name)]}, {row}")
    rank = {v: i for i, v in enumerate(v for b in io.BLOCKS for v in (b, f"sigma_{b}"))}
    return [row for _, row in sorted(rows.items(), key=lambda kv: rank.get(kv[0], len(rank)))]


def _attributes_rows(files: Sequence[xr.Dataset]) -> list[list[str]]:
    rows: dict[str, list[str]] = {}
    for ds in files:
        for name, value in ds.attrs.items():
            if name not in ATTRIBUTES:
                raise ValueError(f"global attribute {name} has no meaning in formats.ATTRIBUTES")
            shown = f": `{value}`" if name in _FIXED_VALUES else ""
            rows.setdefault(name, [f"`{name}`", ATTRIBUTES[name] + shown])
    return list(rows.values())


def file_tables(files: Sequence[xr.Dataset]) -> str:
    """Coordinates, variables and global attributes of one kind of file (several examples
    of it when its variables depend on the estimator)."""
    return "\n\n".join(
        [
            _table(("coordinate", "size", "values", "meaning"), _coordinates_rows(files)),
            _table(("variable", "dims", "type", "units", "meaning"), _variables_rows(files)),
            _table(("global attribute", "meaning"), _attributes_rows(files)),
        ]
    )


def estimators_table() -> str:
    """The blocks of every estimator's estimates.nc (error-state sizes, N features) and the
    names of its inertia parameters."""

    def size(with_one: int, with_two: int) -> str:  # a + bN from the sizes at N = 1 and 2
        b = with_two - with_one
        a = with_one - b
        return " + ".join(([str(a)] if a or not b else []) + ([f"{b}N"] if b else []))

    one, two = estimator_layouts(1), estimator_layouts(2)
    rows = []
    for est in one:
        blocks = zip(one[est].blocks, two[est].blocks, strict=True)
        sizes = ", ".join(f"{b1.name} {size(b1.size, b2.size)}" for b1, b2 in blocks)
        ds = io.estimates_dataset(_history(one[est]), "", est)
        params = _code(ds["inertia_param"].values) if "inertia_param" in ds.coords else "(none)"
        rows.append([f"`{est}`", sizes, size(one[est].dim, two[est].dim), params])
    return _table(("estimator", "blocks (error-state size)", "m", "inertia_param"), rows)


def _default(field: Any) -> str:
    """A tuning field's default as the YAML would say it."""
    if field.is_required():
        return "(required)"
    v = field.get_default(call_default_factory=True)
    if v is None:
        return "`null`"
    if isinstance(v, BaseModel):  # a nested settings model: its own table
        return "(a mapping: its keys below)"
    return f"`{v}`"


def tuning_table(model: Any, only: Iterable[str] | None = None) -> str:
    """key | default | meaning of an estimator's tuning model (its pydantic fields)."""
    keys = list(model.model_fields) if only is None else list(only)
    rows = [
        [f"`{k}`", _default(model.model_fields[k]), model.model_fields[k].description or ""]
        for k in keys
    ]
    return _table(["key", "default", "meaning"], rows)


def tuning_sections() -> dict[str, str]:
    """The ``estimator.tuning`` tables, read off the estimators' tuning models, so that the
    documented defaults are the ones used."""
    from tumblenav.estimators import ukf
    from tumblenav.estimators.hu2024 import tuning as hu_tuning
    from tumblenav.estimators.kabir2025 import ukf_gp
    from tumblenav.estimators.yu2019 import tuning as yu_tuning
    from tumblenav.frontends.depth_pose import PlanesTuning
    from tumblenav.frontends.projections import ProjectionsTuning
    from tumblenav.frontends.stereo_points import StereoPointsTuning

    hu, base = hu_tuning.HuTuning, hu_tuning.BaselineTuning
    differ = [
        k for k in hu.model_fields if _default(hu.model_fields[k]) != _default(base.model_fields[k])
    ]
    kabir, gp = ukf.KabirTuning, ukf_gp.UKFGPTuning
    from tumblenav.estimators.chang2021.tuning import PoseTuning
    from tumblenav.frontends.stereo_images import ImageFrontEndTuning
    from tumblenav.scenario import ImageNoiseConfig, ImagesConfig

    return {
        "sensor.images": tuning_table(ImagesConfig),
        "sensor.images.noise": tuning_table(ImageNoiseConfig),
        "tuning: image front end": tuning_table(ImageFrontEndTuning),
        "tuning: ekf-dpacf": tuning_table(hu),
        "tuning: stereo-points front end": tuning_table(StereoPointsTuning),
        "tuning: projections front end": tuning_table(ProjectionsTuning),
        "tuning: planes front end": tuning_table(PlanesTuning),
        "tuning: ekf-baseline": tuning_table(base, differ),
        "tuning: ekf-depth": tuning_table(yu_tuning.DepthTuning),
        "tuning: ekf-pose": tuning_table(PoseTuning),
        "tuning: ukf": tuning_table(kabir),
        "tuning: ukf-gp": tuning_table(
            gp, [k for k in gp.model_fields if k not in kabir.model_fields]
        ),
    }


def sections(files: dict[str, xr.Dataset] | None = None) -> dict[str, str]:
    """Every generated section of docs/formats.md, by name (from :func:`example_files`)."""
    files = example_files() if files is None else files
    estimates = [ds for name, ds in files.items() if name.startswith("estimates.nc ")]
    out = {
        name: file_tables([ds])
        for name, ds in files.items()
        if not name.startswith("estimates.nc ")
    }
    out["estimates.nc"] = file_tables(estimates)
    out["estimates.nc estimators"] = estimators_table()
    out.update(tuning_sections())
    unused = set(ATTRIBUTES) - {a for ds in files.values() for a in ds.attrs}
    if unused:
        raise ValueError(f"formats.ATTRIBUTES names attributes no file has: {sorted(unused)}")
    return out


def _block(name: str, body: str) -> str:
    return f"<!-- BEGIN GENERATED: {name} -->\n{body}\n<!-- END GENERATED: {name} -->"


def update(text: str, generated: dict[str, str]) -> str:
    """``text`` with every generated section replaced; ValueError if one has no markers."""
    for name, body in generated.items():
        pattern = re.compile(
            rf"<!-- BEGIN GENERATED: {re.escape(name)} -->\n.*?<!-- END GENERATED: "
            rf"{re.escape(name)} -->",
            re.DOTALL,
        )
        block = _block(name, body)
        text, count = pattern.subn(lambda _m: block, text)  # noqa: B023 (used at once)
        if count != 1:
            raise ValueError(f"expected one generated section '{name}', found {count}")
    return text


def main(argv: Sequence[str] | None = None, out: Callable[[str], object] = print) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tumblenav.formats",
        description="Generate the NetCDF format tables of docs/formats.md from the code.",
    )
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", type=Path, metavar="PATH", help="update PATH in place")
    group.add_argument(
        "--check", type=Path, metavar="PATH", help="exit status 1 if PATH is out of date"
    )
    args = parser.parse_args(argv)
    generated = sections()
    if args.write is None and args.check is None:
        out("\n\n".join(_block(n, b) for n, b in generated.items()))
        return 0
    path = args.write or args.check
    text = path.read_text(encoding="utf-8")
    new = update(text, generated)
    if args.check is not None:
        if new != text:
            out(f"{path} is out of date: run python -m tumblenav.formats --write {path}")
            return 1
        return 0
    if new != text:
        path.write_text(new, encoding="utf-8")
        out(f"updated {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
