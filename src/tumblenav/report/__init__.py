"""One self-contained HTML report for any output folder (simulate, estimate, montecarlo, compare,
reproduce): the scenario (its YAML and what differs from the built-in of the same name), the
tables, the figures (embedded), NEES/NIS against their bounds, failed runs with their seeds and
errors, the versions of tumblenav and its main dependencies, and the command that made it.
Nothing is fetched when it is opened (no script, no external resource)."""

from __future__ import annotations

import base64
import difflib
import html
import importlib.metadata
import json
import platform
from pathlib import Path
from typing import Any

from tumblenav import io
from tumblenav.errors import InputError

DEPENDENCIES = ("numpy", "scipy", "numba", "xarray", "netCDF4", "matplotlib", "pydantic")

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; }
table { border-collapse: collapse; margin: .6em 0; }
th, td { border: 1px solid #ccc; padding: .25em .6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
.bad { color: #b00; font-weight: bold; } .ok { color: #070; }
pre { background: #f6f6f6; padding: .8em; overflow-x: auto; font-size: .85em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: .9em; color: #555; }
.warn { background: #fff4e0; border-left: 4px solid #e90; padding: .4em .8em; margin: .3em 0; }
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return _e(v)


def _consistency_cell(c: dict | None) -> str:
    if not c or c.get("mean") is None or not c.get("bounds95"):
        return "-"
    lo, hi = c["bounds95"]
    inside = lo <= c["mean"] <= hi
    cls, word = ("ok", "inside") if inside else ("bad", "above" if c["mean"] > hi else "below")
    frac = c.get("inside_fraction")
    extra = f", {100 * frac:.0f}% of the window inside" if frac is not None else ""
    return f'<span class="{cls}">{c["mean"]:.3g} ({word} {lo:.3g}-{hi:.3g}{extra})</span>'


def _summary_table(cases: list[dict]) -> str:
    """RMSE per quantity, NEES and NIS against their bounds, run counts: one column a case."""
    head = "".join(f"<th>{_e(_case_label(c))}</th>" for c in cases)
    rows = []
    keys = list(dict.fromkeys(k for c in cases for k in (c.get("rmse") or {})))
    for k in keys:
        cells = "".join(f"<td>{_num((c.get('rmse') or {}).get(k))}</td>" for c in cases)
        rows.append(f"<tr><td>RMSE {_e(k)}</td>{cells}</tr>")
    for name in ("nees", "nis"):
        if any(c.get(name) for c in cases):
            cells = "".join(f"<td>{_consistency_cell(c.get(name))}</td>" for c in cases)
            rows.append(f"<tr><td>{name.upper()}/dof (95% bounds)</td>{cells}</tr>")
    for label, key in (
        ("runs", "runs"),
        ("runs failed", "runs_failed"),
        ("runs without estimate", "runs_without_estimate"),
        ("runs diverged", "runs_diverged"),
        ("time per run (s)", "seconds_per_run"),
    ):
        if any(key in c for c in cases):
            cells = "".join(f"<td>{_num(c.get(key))}</td>" for c in cases)
            rows.append(f"<tr><td>{label}</td>{cells}</tr>")
    if any(c.get("branches") for c in cases):
        cells = "".join(f"<td>{_branches_cell(c.get('branches'))}</td>" for c in cases)
        rows.append(f"<tr><td>runs per branch</td>{cells}</tr>")
    return f"<table><tr><th>quantity</th>{head}</tr>{''.join(rows)}</table>"


def _branches_cell(branches: dict | None) -> str:
    """Runs per branch (summary.json ``branches``): the runs compared in a symmetric frame
    of the estimator's own (relabelled or turned axes) are marked."""
    if not branches:
        return "-"
    parts = [f"{_e(name)}: {_num(n)}" for name, n in branches.items() if n or name == "nominal"]
    other = any(n for name, n in branches.items() if name != "nominal")
    return f'<span class="{"bad" if other else "ok"}">{", ".join(parts)}</span>'


def _case_label(c: dict) -> str:
    params = [f"{k}={v}" for k, v in c.items() if k in ("noise_rad", "noise_m", "f_T_hz", "case")]
    return " ".join([str(c.get("estimator", c.get("scenario", "")))] + params)


def _paper_values(cases: list[dict]) -> str:
    rows = []
    for c in cases:
        pv = c.get("paper_values")
        if not pv:
            continue
        for k, v in pv.items():
            ours = (c.get("rmse") or {}).get(k)
            rows.append(
                f"<tr><td>{_e(_case_label(c))}</td><td>{_e(k)}</td><td>{_num(ours)}</td>"
                f"<td>{_num(v)}</td></tr>"
            )
    if not rows:
        return ""
    return (
        "<h2>Ours next to the paper's</h2><table><tr><th>case</th><th>quantity</th>"
        f"<th>ours</th><th>paper</th></tr>{''.join(rows)}</table>"
    )


def _failures(folder: Path) -> str:
    items = []
    for p in sorted(folder.rglob("run_*.failed.json")):
        try:
            f = io.read_json(p)
        except InputError:
            continue
        items.append(
            f"<tr><td>{_e(p.parent.parent.relative_to(folder) if p.parent.parent != folder else '.')}"
            f"</td><td>{_e(f.get('run'))}</td><td>{_e(f.get('base_seed'))}</td>"
            f"<td>{_e(f.get('spawn_key'))}</td><td style='text-align:left'>{_e(f.get('error'))}"
            "</td></tr>"
        )
    if not items:
        return "<h2>Failed runs</h2><p>None.</p>"
    return (
        "<h2>Failed runs</h2><table><tr><th>campaign</th><th>run</th><th>base seed</th>"
        f"<th>spawn key</th><th>error</th></tr>{''.join(items)}</table>"
    )


def _scenario(folder: Path) -> str:
    path = next((p for p in (folder / "scenario.yaml", *folder.rglob("scenario.yaml"))
                 if p.is_file()), None)  # fmt: skip
    if path is None:
        return "<h2>Scenario</h2><p>No scenario.yaml in this folder.</p>"
    text = path.read_text(encoding="utf-8")
    out = f"<h2>Scenario</h2><p>{_e(path.relative_to(folder))}</p><pre>{_e(text)}</pre>"
    try:
        from tumblenav.scenario import builtin_names, load_scenario, scenario_to_yaml

        name = load_scenario(str(path)).name
        if name in builtin_names():
            base = scenario_to_yaml(load_scenario(name)).splitlines()
            mine = scenario_to_yaml(load_scenario(str(path))).splitlines()
            diff = list(difflib.unified_diff(base, mine, "built-in " + name, "this", lineterm=""))
            body = "\n".join(diff) if diff else "(identical to the built-in)"
            out += f"<h3>What differs from the built-in {_e(name)}</h3><pre>{_e(body)}</pre>"
    except Exception as exc:  # noqa: BLE001 - the report shows what it can
        out += f"<p>(the scenario could not be compared with the built-ins: {_e(exc)})</p>"
    return out


def _figures(folder: Path) -> str:
    pngs = sorted(folder.glob("*.png")) + sorted(
        p for p in folder.glob("*/*.png") if p.parent.name != "runs"
    )
    if not pngs:
        return "<h2>Figures</h2><p>No figures in this folder (made with --no-plots?).</p>"
    figs = []
    for p in pngs:
        data = base64.b64encode(p.read_bytes()).decode("ascii")
        rel = p.relative_to(folder)
        figs.append(
            f'<figure><img alt="{_e(rel)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{_e(rel)}</figcaption></figure>"
        )
    return "<h2>Figures</h2>" + "".join(figs)


def _versions() -> str:
    rows = [("python", platform.python_version())]
    for name in ("tumblenav", *DEPENDENCIES):
        try:
            rows.append((name, importlib.metadata.version(name)))
        except importlib.metadata.PackageNotFoundError:
            rows.append((name, "not installed"))
    cells = "".join(f"<tr><td>{_e(n)}</td><td>{_e(v)}</td></tr>" for n, v in rows)
    return f"<h2>Versions</h2><table>{cells}</table>"


def build(folder: Path) -> str:
    """The report of ``folder`` as one HTML document (InputError if it is no tumblenav output
    folder)."""
    folder = Path(folder)
    path = folder / "summary.json"
    if not folder.is_dir():
        raise InputError("not a folder", str(folder))
    summary: dict[str, Any] = io.read_json(path) if path.is_file() else {}
    _check_summary(summary, path)
    if not summary and (folder / "campaign.json").is_file():
        raise InputError(
            "a Monte Carlo campaign whose summary is not written yet (interrupted?): run its "
            "montecarlo command again to finish it, then the report",
            str(folder),
        )
    if not summary and not (folder / "truth.nc").is_file():
        raise InputError(
            "holds no summary.json or truth.nc: not a tumblenav output folder", str(folder)
        )
    cases = summary.get("cases") or ([summary] if summary.get("estimator") else [])
    title = f"tumblenav: {summary.get('paper') or summary.get('scenario') or folder.name}" + (
        f" / {summary['estimator']}" if summary.get("estimator") else ""
    )
    parts = [f"<h1>{_e(title)}</h1>"]
    command = summary.get("command")
    parts.append(
        f"<p>Made by <code>{_e(command)}</code></p>" if command else "<p>(command not recorded)</p>"
    )
    many = len(cases) > 1
    warnings = [
        (f"{_case_label(c)}: " if many else "") + w
        for c in cases
        for w in (c.get("warnings") or [])
    ]
    if warnings:
        parts.append(
            "<h2>Warnings</h2>" + "".join(f'<div class="warn">{_e(w)}</div>' for w in warnings)
        )
    if cases:
        w = summary.get("window_s") or cases[0].get("window_s")
        parts.append(
            "<h2>Results</h2>"
            + (f"<p>Steady-state window {w[0]:g}-{w[1]:g} s.</p>" if w else "")
            + _summary_table(cases)
        )
        parts.append(_paper_values(cases))
    parts.append(_scenario(folder))
    parts.append(_figures(folder))
    parts.append(_failures(folder))
    parts.append(_versions())
    parts.append(
        "<h2>summary.json</h2><pre>" + _e(json.dumps(summary, indent=1)[:200_000]) + "</pre>"
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>"
        + "\n".join(p for p in parts if p)
        + "</body></html>\n"
    )


# summary.json keys the report reads, and the types tumblenav writes them with
_SUMMARY_TYPES: dict[str, tuple[type, ...]] = {
    "rmse": (dict,),
    "median": (dict,),
    "runs": (int,),
    "window_s": (list,),
    "cases": (list,),
    "warnings": (list,),
    "estimator_warnings": (list,),
    "scenario": (str,),
    "estimator": (str,),
    "paper": (str,),
}


def _check_summary(summary: Any, path: Path) -> None:
    """An InputError if ``summary.json`` is not laid out as tumblenav writes it (edited by
    hand, or another program's): a mapping, the keys the report reads of their types, and
    each case of a comparison or reproduction a mapping as well."""
    if not isinstance(summary, dict):
        raise InputError(
            f"is a JSON {type(summary).__name__}, not tumblenav's summary (a mapping)", str(path)
        )
    for key, types in _SUMMARY_TYPES.items():
        if key in summary and summary[key] is not None and not isinstance(summary[key], types):
            raise InputError(
                f"{key}: {summary[key]!r} where tumblenav writes a "
                f"{' or '.join(t.__name__ for t in types)} (was the file edited?)",
                str(path),
            )
    window = summary.get("window_s")
    if window is not None and len(window) != 2:
        raise InputError("window_s is not [start, end]", str(path))
    for case in summary.get("cases") or []:
        _check_summary(case, path)


def write_report(folder: Path, name: str = "report.html") -> Path:
    """Write ``folder/report.html`` atomically; returns its path."""
    text = build(Path(folder))
    return io.atomic_write(Path(folder) / name, lambda tmp: tmp.write_text(text, encoding="utf-8"))
