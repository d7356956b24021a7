"""Compare two folders of ``reproduce`` summaries (before / after a change that must not move them).

Each folder holds ``<paper>_summary.json`` (a copy of ``reproduce <paper> -o DIR``'s
``DIR/summary.json``). For every paper, case and quantity the script prints before, after, the
difference, the Monte Carlo standard error (SE) and a verdict:

* ``bit-equal``: the same float;
* ``within``: |after - before| <= 2 SE;
* ``OUTSIDE``: farther than 2 SE, or (quantities without an SE) not equal to 1e-9 relative;
* ``missing``: the case or quantity is absent after.

Quantities: per filter case ``rmse.<q>``, ``nees.mean``, ``nis.mean`` (both per dof),
``max_attitude_jump_deg`` and the counts (``runs``, ``runs_failed``, ``runs_without_estimate``,
``skipped.*``); the other sections (yu2019 ``table1``-``table4``, kabir2025 ``gp_study``): every
number except timings and the paper's or theory's constants. ``per_run`` percentiles are left
out (the RMSE and its SE cover them).

SE. ``rmse.<q>``, ``nees.mean`` and ``nis.mean``: bootstrap over runs (B = 2000, seed 0), read
from ``BEFORE/se.json``, which ``--bootstrap-se`` writes from the campaign folders' stored runs
(``runs/run_*.npz``); each replicate redraws the case's runs with replacement and recomputes the
statistic exactly as ``summary.json`` does (RMSE over runs per time, then over the window).
Without ``se.json`` an RMSE falls back to RMSE / sqrt(2 N) (Gaussian errors, N runs) and the
NEES/NIS means get no SE. kabir2025 ``gp_study.gp_rmse_rad`` (median over runs): bootstrap
of the median from ``gp_rmse_rad_runs``. Everything else is deterministic for the seeds and
has no SE. Runs share their seeds before and after (common random numbers), so an unchanged
computation gives bit-equal values and the 2-SE test only judges changes that move them.

Usage:
    python benchmarks/compare_summaries.py BEFORE AFTER [--all]
    python benchmarks/compare_summaries.py --bootstrap-se OUT_ROOT -o BEFORE/se.json
        (OUT_ROOT/<paper>/ are ``reproduce <paper> -o`` folders with their campaign folders)
Last line: ``quantities=<n> outside_2se=<m> bit_equal=<k>``
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

B_BOOT = 2000
SEED = 0
ID_KEYS = (
    "noise_rad",
    "noise_m",
    "multi_solution_fix",
    "f_T_hz",
    "T_train_s",
    "estimator",
    "label",
    "gp_variance",
    "outliers",
    "points",
    "noise_cm",
)
SKIP_KEYS = {
    "per_run",
    "paper_values",
    "targets",
    "window_s",
    "bounds95",
    "dof",
    "units",
    "time_ms",
    "train_time_s",
    "train_time_s_runs",
    "gp_rmse_rad_runs",
    "failed",
    "warnings",
    "inside_fraction",
}
SKIP_PREFIXES = ("paper_", "theory")
REL_EXACT = 1e-9


# --- cases and quantities --------------------------------------------------------------------


def case_id(case: dict) -> str:
    keys = [k for k in ID_KEYS if k in case and not (k == "estimator" and "label" in case)]
    return " ".join(f"{k}={case[k]}" for k in keys)


def _leaves(obj, prefix: str):
    """(name, value) of every number under ``obj`` except the skipped keys."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k in SKIP_KEYS or k.startswith(SKIP_PREFIXES):
                continue
            yield from _leaves(v, f"{prefix}.{k}" if prefix else k)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _leaves(v, f"{prefix}[{i}]")
    elif isinstance(obj, bool):
        return
    elif isinstance(obj, int | float) or obj is None:
        yield prefix, obj


def quantities(summary: dict) -> dict[tuple[str, str], float | None]:
    """{(case, quantity): value} of one paper's summary."""
    out: dict[tuple[str, str], float | None] = {}
    for section, items in summary.items():
        if not isinstance(items, list):
            continue
        for i, case in enumerate(items):
            if not isinstance(case, dict):
                continue
            cid = case_id(case) or f"#{i}"
            name = cid if section == "cases" else f"{section} {cid}"
            for q, v in _leaves(case, ""):
                if q in ID_KEYS:
                    continue
                if q.startswith(("nees.", "nis.")) and q not in ("nees.mean", "nis.mean"):
                    continue
                out[(name, q)] = v
    return out


def median_boot_se(values: list, rng: np.random.Generator) -> float | None:
    v = np.array([np.nan if x is None else x for x in values], dtype=float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return None
    idx = rng.integers(0, v.size, size=(B_BOOT, v.size))
    return float(np.std(np.median(v[idx], axis=1), ddof=1))


def standard_errors(paper: str, summary: dict, se_file: dict) -> dict[tuple[str, str], float]:
    """SE of each quantity that has one: se.json's bootstrap, else the fallbacks above."""
    se: dict[tuple[str, str], float] = {}
    rng = np.random.default_rng(SEED)
    for section, items in summary.items():
        if not isinstance(items, list):
            continue
        for i, case in enumerate(items):
            if not isinstance(case, dict):
                continue
            cid = case_id(case) or f"#{i}"
            name = cid if section == "cases" else f"{section} {cid}"
            for q, v in (case.get("rmse") or {}).items():
                if v is not None and case.get("runs"):
                    se[(name, f"rmse.{q}")] = v / math.sqrt(2 * case["runs"])
            if "gp_rmse_rad_runs" in case:
                s = median_boot_se(case["gp_rmse_rad_runs"], rng)
                if s is not None:
                    se[(name, "gp_rmse_rad")] = s
    for key, s in se_file.get(paper, {}).items():
        cid, q = key.split(" | ")
        se[(cid, q)] = s
    return se


# --- bootstrap from stored runs ------------------------------------------------------------


def _boot_stat(x: np.ndarray, w: np.ndarray, sqrt: bool) -> np.ndarray:
    """Statistic of ``x`` (runs, n_window; NaN = no value) for run weights ``w`` (B, runs):
    mean over the window of the weighted mean over runs (then sqrt for an RMSE)."""
    ok = np.isfinite(x)
    s = w @ np.where(ok, x, 0.0)
    c = w @ ok.astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_t = np.where(c > 0, s / np.where(c > 0, c, 1.0), np.nan)
    fin = np.isfinite(per_t)
    m = np.where(fin, per_t, 0.0).sum(axis=1) / np.maximum(fin.sum(axis=1), 1)
    m = np.where(fin.any(axis=1), m, np.nan)
    return np.sqrt(m) if sqrt else m


def bootstrap_campaign(folder: Path, window: list[float]) -> dict[str, tuple[float, float]]:
    """{quantity: (statistic recomputed from all runs, its bootstrap SE)} of a campaign."""
    runs = json.loads((folder / "campaign.json").read_text())["runs_requested"]
    files = sorted(p for p in (folder / "runs").glob("run_*.npz") if int(p.stem[4:]) < runs)
    if len(files) < 2:
        return {}
    data = [np.load(p) for p in files]
    t = data[0]["t"]
    m = (t >= window[0] - 1e-9) & (t <= window[1] + 1e-9)
    R = len(data)
    rng = np.random.default_rng(SEED)
    w = np.stack([np.bincount(rng.integers(0, R, R), minlength=R) for _ in range(B_BOOT)])
    w = w.astype(float)
    full = np.ones((1, R))
    keys = list(dict.fromkeys(k for z in data for k in z.files if k.startswith("err_")))
    out: dict[str, float] = {}
    for k in keys:
        e = np.stack([z[k] if k in z.files else np.full(len(t), np.nan) for z in data])[:, m]
        out[f"rmse.{k[4:]}"] = (
            float(_boot_stat(e**2, full, True)[0]),
            float(np.nanstd(_boot_stat(e**2, w, True), ddof=1)),
        )
    for name in ("nees", "nis"):
        v = np.stack([z[name] for z in data]).astype(float)
        d = np.broadcast_to(
            np.stack([np.broadcast_to(z[f"{name}_dof"], t.shape) for z in data]).astype(float),
            v.shape,
        )
        valid = np.isfinite(v) & (d > 0)
        norm = np.where(valid, v / np.where(d > 0, d, 1.0), np.nan)[:, m]
        if np.isfinite(norm).any():
            out[f"{name}.mean"] = (
                float(_boot_stat(norm, full, False)[0]),
                float(np.nanstd(_boot_stat(norm, w, False), ddof=1)),
            )
    return out


def write_bootstrap_se(root: Path, output: Path) -> None:
    """se.json from ``root/<paper>/summary.json`` and the campaign folders under it; checks
    that the recomputed statistics equal the summary's before trusting the match."""
    result: dict[str, dict[str, float]] = {}
    for paper_dir in sorted(p for p in root.iterdir() if (p / "summary.json").is_file()):
        summary = json.loads((paper_dir / "summary.json").read_text())
        paper = summary.get("paper", paper_dir.name)
        cases = summary.get("cases", [])
        campaigns = sorted(p.parent for p in paper_dir.rglob("campaign.json"))
        by_rmse = {}
        for c in campaigns:
            s = json.loads((c / "summary.json").read_text())
            by_rmse[json.dumps(s.get("rmse"), sort_keys=True)] = c
        result[paper] = {}
        for case in cases:
            folder = by_rmse.get(json.dumps(case.get("rmse"), sort_keys=True))
            if folder is None or not case.get("rmse"):
                print(f"{paper} {case_id(case)}: no campaign folder matches", file=sys.stderr)
                continue
            stats = bootstrap_campaign(folder, case["window_s"])
            for q, (value, s) in stats.items():
                if q.startswith("rmse."):
                    ref = case["rmse"].get(q[5:])
                elif q.split(".")[0] in case:  # kabir2025's cases carry no NIS
                    ref = (case[q.split(".")[0]] or {}).get("mean")
                else:
                    continue
                if ref is None or not math.isclose(value, ref, rel_tol=1e-9, abs_tol=1e-15):
                    raise SystemExit(f"{folder}: {q} recomputed {value!r} != summary {ref!r}")
                result[paper][f"{case_id(case)} | {q}"] = s
        print(
            f"{paper}: {len(result[paper])} SEs from {len(campaigns)} campaign folders",
            file=sys.stderr,
        )
    output.write_text(json.dumps(result, indent=1) + "\n")


# --- comparison ------------------------------------------------------------------------------


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.6g}"


def compare(before: Path, after: Path, show_all: bool) -> int:
    se_path = before / "se.json"
    se_file = json.loads(se_path.read_text()) if se_path.is_file() else {}
    n = outside = equal = 0
    for path in sorted(before.glob("*_summary.json")):
        paper = path.name.removesuffix("_summary.json")
        b_sum = json.loads(path.read_text())
        a_path = after / path.name
        a_q = quantities(json.loads(a_path.read_text())) if a_path.is_file() else {}
        b_q = quantities(b_sum)
        se = standard_errors(paper, b_sum, se_file)
        extra = [k for k in a_q if k not in b_q]
        print(f"== {paper}")
        print(
            f"{'case':<44} {'quantity':<28} {'before':>12} {'after':>12} {'diff':>11} "
            f"{'SE':>10}  verdict"
        )
        for key, b in b_q.items():
            n += 1
            s = se.get(key)
            if key not in a_q:
                verdict, a, d = "missing", None, None
            else:
                a = a_q[key]
                d = None if a is None or b is None else a - b
                if a == b or (a is not None and b is not None and np.isnan(a) and np.isnan(b)):
                    verdict = "bit-equal"
                elif d is None:
                    verdict = "OUTSIDE"
                elif s is not None:
                    verdict = "within" if abs(d) <= 2 * s else "OUTSIDE"
                else:
                    ok = math.isclose(a, b, rel_tol=REL_EXACT, abs_tol=0.0)
                    verdict = "within" if ok else "OUTSIDE"
            equal += verdict == "bit-equal"
            outside += verdict in ("OUTSIDE", "missing")
            if show_all or verdict != "bit-equal" or s is not None:
                print(
                    f"{key[0]:<44} {key[1]:<28} {_fmt(b):>12} {_fmt(a):>12} {_fmt(d):>11} "
                    f"{_fmt(s):>10}  {verdict}"
                )
        if extra:
            print(f"{len(extra)} quantities only after, e.g. {extra[0][0]} {extra[0][1]}")
    print(f"quantities={n} outside_2se={outside} bit_equal={equal}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("before", type=Path, nargs="?")
    ap.add_argument("after", type=Path, nargs="?")
    ap.add_argument("--all", action="store_true", help="also print bit-equal rows without SE")
    ap.add_argument(
        "--bootstrap-se",
        type=Path,
        metavar="OUT_ROOT",
        help="write se.json from reproduce folders OUT_ROOT/<paper>/",
    )
    ap.add_argument("-o", "--output", type=Path, help="se.json to write (--bootstrap-se)")
    args = ap.parse_args()
    if args.bootstrap_se:
        if not args.output:
            ap.error("--bootstrap-se needs -o")
        write_bootstrap_se(args.bootstrap_se, args.output)
        return 0
    if not (args.before and args.after):
        ap.error("BEFORE and AFTER are required")
    return compare(args.before, args.after, args.all)


if __name__ == "__main__":
    sys.exit(main())
