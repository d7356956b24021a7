"""Where a reported covariance is not positive semi-definite (twenty-third session, issue 18):
run RUN of SCENARIO with ESTIMATOR (default ekf-dpacf), and print the epochs after T0 (default
140 s) whose covariance has a negative eigenvalue or whose NEES is negative, with the state
components of that eigenvector; then the smallest eigenvalue over the scenario's window.

Usage::

    python hu_negative_nees.py SCENARIO RUN [ESTIMATOR] [T0]

hu_occ30 run 19 on 673847d: 222 of 601 epochs, eigenvalues to -1.8e-6 (NEES -4.5e3 at 157 s);
after the cross terms' statistical linearisation: none.
"""

import sys

import numpy as np
from threadpoolctl import threadpool_limits

from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation import metrics
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate

sc = load_scenario(sys.argv[1])
k = int(sys.argv[2])
est = est_base.get(sys.argv[3] if len(sys.argv) > 3 else "ekf-dpacf")
t0 = float(sys.argv[4]) if len(sys.argv) > 4 else 140.0
with threadpool_limits(1):
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tracks, _ = stages.prepare(meas, tuple(est.consumes), None)
    streams = run_streams(run_seed(sc.montecarlo.seed, k))["estimator"]
    h = est.run(context_from_scenario(sc), tracks, streams)
dx = h.layout.boxminus(align(truth, h).x, h.x)
bad = []
for i in np.flatnonzero(h.t >= t0):
    P = h.P[i]
    if P is None or not np.all(np.isfinite(P)) or not np.all(np.isfinite(dx[i])):
        continue
    w, V = np.linalg.eigh(P)
    n = metrics.nees(dx[i][None], P[None])[0]
    if n < 0 or w[0] <= 0:
        bad.append(i)
        if len(bad) <= 5:
            top = np.argsort(-abs(V[:, 0]))[:5]
            print(f"t={h.t[i]:.1f} NEES={n:.3g} smallest eigenvalues {w[:3]} along {top}")
print("epochs not positive definite or with a negative NEES:", len(bad), "of", int(np.sum(h.t >= t0)))
w0, w1 = sc.window_s if sc.window_s else (0.75 * h.t[-1], h.t[-1])
mins = [
    np.linalg.eigvalsh(h.P[j])[0]
    for j in np.flatnonzero((h.t >= w0) & (h.t <= w1))
    if h.P[j] is not None and np.all(np.isfinite(h.P[j]))
]
print("smallest eigenvalue over the window:", np.min(mins) if mins else None)
