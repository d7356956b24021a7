"""The triangulated points' error along the line of sight on a point-track scenario, and its
stated sigma (eighteenth session, issue 18: chang_points59's velocity)::

    python chang_points59_depth.py docs/results/scenarios/consistency/chang_points59.yaml 0,1,2

Per run, over every stereo-observed sighting: the mean error along the line of sight (cm,
with its standard error), the scatter against the stated sigma (measurements.feature_tracks:
the first-order covariance at the triangulated point), and the mean of error / stated sigma
(nonzero when the stated sigma, evaluated at the noisy point, correlates with the error).
"""

import sys

import numpy as np

from tumblenav.campaign.store import run_seed
from tumblenav.estimators.chang2021.measurements import feature_tracks
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

sc = load_scenario(sys.argv[1])
for k in [int(s) for s in sys.argv[2].split(",")]:
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tr = feature_tracks(meas)
    los = truth.r_L / np.linalg.norm(truth.r_L, axis=1)[:, None]
    pts = truth.r_L[:, None, :] + truth.features_T[None] @ np.swapaxes(truth.R_LT, 1, 2)
    along = np.einsum("knj,kj->kn", tr.p - pts, los)[tr.ok_p]
    sd = np.sqrt(np.einsum("knij,ki,kj->kn", tr.P, los, los))[tr.ok_p]
    print(
        f"run {k}: along the line of sight mean {100 * along.mean():.2f} cm (standard error "
        f"{100 * along.std() / np.sqrt(along.size):.2f}), std {100 * along.std():.1f} cm, stated "
        f"sigma mean {100 * sd.mean():.1f} cm; mean error/sigma {np.mean(along / sd):.4f}"
    )
