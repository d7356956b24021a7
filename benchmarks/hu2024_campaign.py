"""Speed of the Hu 2024 Monte Carlo campaign: 500 runs x 4 noise levels of ekf-dpacf.

It runs the full campaign (simulation, front end, filter, evaluation, storage) with the
campaign runner on all cores, then times a plain one-run-at-a-time loop of the same filter
(B = 1, no vectorisation across runs, one process, the filter's numpy loop) on a few runs and
extrapolates it to 2000 runs; the same loop with the compiled filter is printed too.

Usage: python benchmarks/hu2024_campaign.py [--runs 500] [--workers N] [--loop-runs 4]
Last line: ``campaign_s=<wall s> per_step_us=<us per filter step> ratio=<speed-up>``
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from tumblenav.campaign.runner import evaluate_runs, run_campaign
from tumblenav.estimators.hu2024 import filter as hu_filter
from tumblenav.scenario import load_scenario

NOISE_RAD = (0.1e-5, 0.5e-5, 2e-5, 5e-5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=500, help="runs per noise level")
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--loop-runs", type=int, default=4, help="runs timed one at a time")
    args = ap.parse_args()
    base = load_scenario("hu2024")
    steps = len(base.times)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        for noise in NOISE_RAD:
            sc = base.with_updates(**{"sensor.noise.angular_rad": noise})
            s = run_campaign(
                sc, "ekf-dpacf", args.runs, Path(tmp) / f"{noise:.1e}", workers=args.workers
            )
            print(
                f"noise {noise:.1e} rad: {s['runs']} runs, {s['runs_failed']} failed, "
                f"attitude RMSE {s['rmse']['attitude_deg']:.3g} deg"
            )
        wall = time.perf_counter() - t0
    total_runs = args.runs * len(NOISE_RAD)
    # the same filter, one run at a time (no batching), single process: with the filter's
    # plain numpy loop (the reference of `ratio`), and with its compiled loop
    sc = base.with_updates(**{"sensor.noise.angular_rad": 2e-5})
    per_run = {}
    for engine in ("numpy", "compiled"):
        hu_filter.ENGINE = engine
        evaluate_runs(sc, "ekf-dpacf", 99, [0])  # warm-up (compilation cache, imports)
        t1 = time.perf_counter()
        for k in range(args.loop_runs):
            evaluate_runs(sc, "ekf-dpacf", 99, [k])
        per_run[engine] = (time.perf_counter() - t1) / args.loop_runs
        print(f"one-run-at-a-time loop, {engine} filter: {per_run[engine]:.3f} s per run")
    hu_filter.ENGINE = "auto"
    loop_per_run = per_run["numpy"]
    per_step_us = wall / (total_runs * steps) * 1e6
    ratio = loop_per_run * total_runs / wall
    print(f"campaign_s={wall:.1f} per_step_us={per_step_us:.2f} ratio={ratio:.1f}")


if __name__ == "__main__":
    main()
