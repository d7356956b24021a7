"""ekf-pose's own CPU time per run, as a campaign worker runs it (one BLAS thread).

The scenario is simulated (chang2021_close renders its images and tracks them first: ~47 s a
run that is not timed), then ``ekf-pose`` runs on the tracks and its CPU time
(``time.process_time``) is printed per run; the last line is the mean::

    python benchmarks/chang2021_estimator_speed.py [SCENARIO] [--runs 1] [--save FILE.npz]
        [--profile N]

``--save`` writes the last run's estimates and covariances (``x``, ``P``, ``nis``) to compare two
versions of the code (e.g. ``numpy.abs(a["x"] - b["x"]).max()``); ``--profile N`` runs the
estimator under cProfile and prints its N most expensive functions by cumulative time (the
CPU time printed is then the profiled one).

    chang2021_estimator_speed cpu_s=<mean over runs> runs=<n>
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import numpy as np
from threadpoolctl import threadpool_limits

from tumblenav.campaign.store import run_seed
from tumblenav.estimators.base import get
from tumblenav.estimators.context import context_from_scenario
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="chang2021_close")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--save", default=None, help="write the last run's x, P, nis (npz)")
    ap.add_argument("--profile", type=int, default=0, help="print the N costliest functions")
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    est = get("ekf-pose")
    images = getattr(sc.sensor, "images", None)
    cpu = []
    with threadpool_limits(limits=1, user_api="blas"):
        for k in range(args.runs):
            seed = run_seed(sc.montecarlo.seed, k)
            _, meas = simulate(sc, seed)
            tracks, _ = stages.prepare(meas, est.consumes, images.frontend if images else None)
            prof = cProfile.Profile() if args.profile else None
            t0 = time.process_time()
            if prof is not None:
                prof.enable()
            h = est.run(context_from_scenario(sc), tracks, run_streams(seed)["estimator"])
            if prof is not None:
                prof.disable()
            cpu.append(time.process_time() - t0)
            if prof is not None:
                pstats.Stats(prof).sort_stats("cumulative").print_stats(args.profile)
            print(
                f"run {k}: ekf-pose {cpu[-1]:.1f} s CPU, {tracks.uv.shape[2]} track IDs", flush=True
            )
    if args.save:
        P = np.array([p if p is not None else np.full((12, 12), np.nan) for p in h.P])
        np.savez(args.save, x=h.x, P=P, nis=h.nis)
    print(f"chang2021_estimator_speed cpu_s={sum(cpu) / len(cpu):.1f} runs={len(cpu)}")


if __name__ == "__main__":
    main()
