"""Cost per run of the batched ekf-dpacf campaign path against the chunk size (runs per
``run_batch`` call), in one process: chooses ``tumblenav.campaign.runner.BATCH_CHUNK``.

Usage: python benchmarks/campaign_chunk_size.py [--runs 64] [--chunks 128 64 16 8 4]
Last line: ``best_chunk=<runs> per_run_ms=<ms per run at that chunk>``
"""

from __future__ import annotations

import argparse
import time

from tumblenav.campaign.runner import evaluate_runs
from tumblenav.scenario import load_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=64)
    ap.add_argument("--chunks", type=int, nargs="+", default=[128, 64, 16, 8, 4])
    args = ap.parse_args()
    sc = load_scenario("hu2024")
    evaluate_runs(sc, "ekf-dpacf", 1, [0])  # compilation cache, imports
    cost = {}
    for c in args.chunks:
        n = max(args.runs, c)
        t0 = time.perf_counter()
        for j in range(0, n, c):
            evaluate_runs(sc, "ekf-dpacf", 1, list(range(j, j + c)))
        cost[c] = (time.perf_counter() - t0) / n * 1e3
        print(f"chunk {c:4d}: {cost[c]:.1f} ms per run", flush=True)
    best = min(cost, key=cost.get)
    print(f"best_chunk={best} per_run_ms={cost[best]:.1f}")


if __name__ == "__main__":
    main()
