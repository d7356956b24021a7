"""ekf-pose's own CPU time per run, as a campaign worker runs it (one BLAS thread).

The scenario is simulated (chang2021_close renders its images and tracks them first: ~47 s a
run that is not timed), then ``ekf-pose`` runs on the tracks and its CPU time
(``time.process_time``) is printed per run; the last line is the mean::

    python benchmarks/chang2021_estimator_speed.py [SCENARIO] [--runs 1]

    chang2021_estimator_speed cpu_s=<mean over runs> runs=<n>
"""

from __future__ import annotations

import argparse
import time

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
            t0 = time.process_time()
            est.run(context_from_scenario(sc), tracks, run_streams(seed)["estimator"])
            cpu.append(time.process_time() - t0)
            print(
                f"run {k}: ekf-pose {cpu[-1]:.1f} s CPU, {tracks.uv.shape[2]} track IDs", flush=True
            )
    print(f"chang2021_estimator_speed cpu_s={sum(cpu) / len(cpu):.1f} runs={len(cpu)}")


if __name__ == "__main__":
    main()
