"""Time of the stereo-points front end (ekf-dpacf's and ekf-baseline's) on 16 runs of the
built-in hu2024 at once, as a campaign chunk computes them: simulation and track preparation
outside the timing, one warm-up call (numba loads or compiles its kernels), then REPS timed
calls. To compare two versions on one machine, run it from each checkout (e.g. ``git
worktree add OLD REV`` and ``PYTHONPATH=OLD/src python benchmarks/hu2024_frontend_speed.py``),
alternating.

Usage::

    python benchmarks/hu2024_frontend_speed.py [REPS]

Last line: ``frontend_16_runs_s=<median of the timed calls>``.
"""

import statistics
import sys
import time

from tumblenav.campaign.store import run_seed
from tumblenav.estimators.hu2024 import filter as F
from tumblenav.estimators.hu2024.tuning import parse_tuning
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

reps = int(sys.argv[1]) if len(sys.argv) > 1 else 4
sc = load_scenario("hu2024")
tracks = []
for k in range(16):
    _, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tracks.append(stages.prepare(meas, ("stereo_points",), None)[0])
tun = parse_tuning(sc.estimator.tuning, True)
q_r = sc.process_noise.rotational_rad2_s4 if sc.process_noise else 0.0
F.frontend(tracks[:2], tun, q_r)  # load or compile the kernels
times = []
for _ in range(reps):
    t0 = time.perf_counter()
    F.frontend(tracks, tun, q_r)
    times.append(time.perf_counter() - t0)
    print(f"front end, 16 runs: {times[-1]:.2f} s")
print(f"frontend_16_runs_s={statistics.median(times):.2f}")
