"""When does the DPACF attitude (Hu 2024 Fig. 5) converge? Two readings of the same runs.

For each angular resolution of Hu 2024 Sec. 5, ``--runs`` runs of ekf-dpacf on the hu2024
scenario (the campaign runner, the scenario's seeds, as ``reproduce hu2024``); from each run's
DPACF attitude error (``err_dpacf_attitude_deg``, NaN while the front end has no DPACF frame):

* the time of the first DPACF estimate, median over **all** runs;
* the first time the error's median over the runs **that have a DPACF at that time** is below
  5 deg and below 1 deg (the reading of the Fig. 5 table until 2026-11-22: it ignores the runs
  still without an estimate);
* the first time the median over **all** runs (a run without an estimate counts as failing)
  is below 5 deg and 1 deg;
* that median at 50 s and 200 s.

Usage: python benchmarks/hu2024_dpacf_convergence.py [--runs 100] [--workers 2]
       [--noise 5e-6 ...] [--set key=value ...]  (ekf-dpacf tuning overrides, YAML values)
Last line: ``first_dpacf_s=<per level> all_runs_below_5deg_s=<per level>``
"""

from __future__ import annotations

import argparse
import glob
import tempfile
import warnings
from pathlib import Path

import numpy as np
from _tuning import with_tuning  # noqa: I001 (benchmarks/, on sys.path when run)

from tumblenav.pipeline import run_montecarlo
from tumblenav.scenario import load_scenario

NOISE_RAD = (1e-6, 5e-6, 2e-5, 5e-5)


def first_below(t: np.ndarray, curve: np.ndarray, threshold: float) -> float:
    ok = curve < threshold
    return float(t[np.argmax(ok)]) if ok.any() else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--noise", type=float, nargs="*", default=list(NOISE_RAD))
    ap.add_argument("--set", action="append", default=[], help="tuning key=value")
    args = ap.parse_args()
    base = with_tuning(load_scenario("hu2024"), args.set)
    firsts, below5 = [], []
    print(
        "| noise [rad] | first DPACF, median of all runs [s] | available runs' median < 5 / < 1 deg from [s] | all runs' median < 5 / < 1 deg from [s] | all runs' median at 50 / 200 s [deg] |"
    )
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for noise in args.noise:
            sc = base.with_updates(**{"sensor.noise.angular_rad": noise})
            out = Path(tmp) / f"{noise:.0e}"
            run_montecarlo(sc.name, "ekf-dpacf", args.runs, out, args.workers, scenario=sc)
            E, t = [], None
            for f in sorted(glob.glob(str(out / "runs" / "*.npz"))):
                z = np.load(f)
                E.append(z["err_dpacf_attitude_deg"])
                t = z["t"]
            E = np.array(E)
            first = [
                t[np.flatnonzero(np.isfinite(e))[0]] if np.isfinite(e).any() else np.inf for e in E
            ]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                avail = np.nanmedian(E, axis=0)
            every = np.median(np.where(np.isfinite(E), E, np.inf), axis=0)
            i50, i200 = np.argmin(abs(t - 50.0)), np.argmin(abs(t - 200.0))
            firsts.append(float(np.median(first)))
            below5.append(first_below(t, every, 5.0))
            print(
                f"| {noise:.1e} | {firsts[-1]:g} | {first_below(t, avail, 5.0):g} / {first_below(t, avail, 1.0):g} "
                f"| {below5[-1]:g} / {first_below(t, every, 1.0):g} | {every[i50]:.3g} / {every[i200]:.3g} |",
                flush=True,
            )
    fmt = ",".join
    print(
        f"first_dpacf_s={fmt(f'{x:g}' for x in firsts)} all_runs_below_5deg_s={fmt(f'{x:g}' for x in below5)}"
    )


if __name__ == "__main__":
    main()
