"""Which planes of a run's clouds become fixes, and why the others are skipped (thirteenth
session, issue 18): every fifth scan of run 0, the true pose as the prediction; printed: the
count of fixes per rectangle and of skipped planes per reason, and one example of each reason.
On main as it is (no region split); with ``yu_split_regions.patch`` applied, ``SPLIT=0``
turns the split off and ``SPLIT=0.25`` is its default.

Usage: [SPLIT=0.25] python yu_plane_skips.py SCENARIO
"""
import collections
import os
import sys

import numpy as np
from tumblenav import rotations as rot
from tumblenav.campaign.runner import run_seed
from tumblenav.frontends.depth_pose import pose_fixes
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, target_model
sc = load_scenario(sys.argv[1]); model = target_model(sc); sigma = sc.sensor.range_noise_m
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, 0))
rng = np.random.default_rng(0)
R_CL, R_LI = rot.quat_to_matrix(meas.q_CL), rot.quat_to_matrix(meas.q_LI)
cnt = collections.Counter(); ex = {}
for k in range(0, len(meas.t), 5):
    R_LT = R_LI[k] @ rot.quat_to_matrix(truth.q_TI[k]).T
    pts = meas.points[k][meas.observed[k]]
    kw = {"split_gap_sides": float(os.environ["SPLIT"])} if "SPLIT" in os.environ else {}
    fixes, skipped = pose_fixes(pts, model, 3 * sigma, rng, sigma, R_CL[k] @ R_LT, **kw)
    for f in fixes: cnt[f.rectangle] += 1
    for s in skipped:
        key = s.split(",")[0].split(" spread")[0][:30] if "spread" in s else s.split(":")[-1]
        cnt["skip:" + key] += 1; ex.setdefault("skip:" + key, s)
print(cnt.most_common()); 
for k, v in ex.items(): print(k, "|", v)
