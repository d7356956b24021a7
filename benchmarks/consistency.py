"""The consistency table of docs/results/consistency.md: every estimator on its paper's scenario
and on scenarios of our own, mean NEES/dof and NIS/dof against their 95 % bounds.

The cases are listed in docs/results/scenarios/consistency/cases.yaml (estimator, scenario, what
differs, runs). Each case is a resumable `tumblenav montecarlo` campaign in OUT/<name>/; rerun
the same command to finish an interrupted table. Then the table is printed in Markdown (and
written to OUT/table.md, OUT/table.json).

    python benchmarks/consistency.py -o out/consistency [--workers 2] [--only NAME,...]
    python benchmarks/consistency.py -o out/consistency --table-only   # the table of what ran
    python benchmarks/consistency.py -o docs/results/consistency --table-only   # from the stored
                                                                  # summaries (NAME.json)

Last line: ``consistency cases=<n> nees_inside=<k> nis_inside=<m>``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
CASES = ROOT / "docs/results/scenarios/consistency/cases.yaml"


def _scenario_ref(ref: str) -> str:
    p = ROOT / ref
    return str(p) if p.suffix in (".yaml", ".yml") else ref


def _fmt(x: float | None, spec: str = ".3g") -> str:
    return "-" if x is None else format(x, spec)


def _row(case: dict, summary: dict) -> dict:
    nees, nis = summary.get("nees") or {}, summary.get("nis") or {}
    rm = summary.get("rmse") or {}

    def inside(c: dict) -> bool | None:
        if not c or c.get("mean") is None:
            return None
        lo, hi = c["bounds95"]
        return bool(lo <= c["mean"] <= hi)

    return {
        "name": case["name"],
        "estimator": summary.get("estimator", case["estimator"]),
        "scenario": case["scenario"],
        "differs": case.get("differs", ""),
        "runs": summary.get("runs"),
        "runs_without_estimate": summary.get("runs_without_estimate", 0),
        "nees": nees.get("mean"),
        "nees_bounds": nees.get("bounds95"),
        "nees_inside": inside(nees),
        "nis": nis.get("mean"),
        "nis_bounds": nis.get("bounds95"),
        "nis_inside": inside(nis),
        "attitude_deg": rm.get("attitude_deg"),
        "position_m": rm.get("position_m"),
        "diverged": summary.get("runs_diverged", 0),
        "failed": summary.get("runs_failed", 0),
        "branches": summary.get("branches"),
    }


def table(rows: list[dict]) -> str:
    head = (
        "| estimator | scenario | differs from the paper's | runs | NEES/dof [95 % bounds] "
        "| NIS/dof [95 % bounds] | attitude RMSE deg | position RMSE m | diverged | branches |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:

        def c(v, b, ok):
            if v is None:
                return "-"
            mark = "" if ok else " **out**"
            return f"{v:.3g} [{b[0]:.3g}, {b[1]:.3g}]{mark}"

        runs = f"{r['runs']}"
        if r.get("runs_without_estimate"):  # never started: the NEES is over the others
            runs += f" ({r['runs_without_estimate']} without an estimate)"
        br = r["branches"]
        br_s = ", ".join(f"{k} {v}" for k, v in br.items()) if br else "-"
        lines.append(
            f"| {r['estimator']} | {Path(r['scenario']).stem} | {r['differs']} | {runs} "
            f"| {c(r['nees'], r['nees_bounds'], r['nees_inside'])} "
            f"| {c(r['nis'], r['nis_bounds'], r['nis_inside'])} "
            f"| {_fmt(r['attitude_deg'])} | {_fmt(r['position_m'])} | {r['diverged']} | {br_s} |"
        )
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=Path("out/consistency"))
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--only", default="", help="comma-separated case names")
    ap.add_argument("--runs", type=int, default=None, help="override every case's runs")
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--cases", type=Path, default=CASES)
    a = ap.parse_args(argv)
    cases = yaml.safe_load(a.cases.read_text())["cases"]
    if a.only:
        keep = set(a.only.split(","))
        cases = [c for c in cases if c["name"] in keep]
    rows = []
    for case in cases:
        out = a.output / case["name"]
        if not a.table_only:
            from tumblenav.pipeline import run_montecarlo

            print(f"== {case['name']}: {case['estimator']} on {case['scenario']}", flush=True)
            run_montecarlo(
                _scenario_ref(case["scenario"]),
                case["estimator"],
                a.runs or case.get("runs", 20),
                out,
                workers=a.workers,
                plots=False,
            )
        f = out / "summary.json"
        if not f.exists():  # a folder of stored summaries, NAME.json (docs/results/consistency)
            f = a.output / f"{case['name']}.json"
        if f.exists():
            rows.append(_row(case, json.loads(f.read_text())))
    text = table(rows)
    a.output.mkdir(parents=True, exist_ok=True)
    (a.output / "table.md").write_text(text)
    (a.output / "table.json").write_text(json.dumps(rows, indent=1))
    print(text)
    n_in = sum(bool(r["nees_inside"]) for r in rows)
    s_in = sum(bool(r["nis_inside"]) for r in rows)
    print(f"consistency cases={len(rows)} nees_inside={n_in} nis_inside={s_in}")
    return 0


if __name__ == "__main__":
    from tumblenav.errors import Interrupted

    try:
        sys.exit(main())
    except (Interrupted, KeyboardInterrupt) as exc:  # Ctrl-C: say what was kept, as the CLI does
        kept = getattr(exc, "kept", None)
        print(f"interrupted: {kept or 'rerun the same command to resume'}")
        sys.exit(128 + getattr(exc, "signum", 2))
