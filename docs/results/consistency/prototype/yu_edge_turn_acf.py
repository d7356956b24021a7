"""Scan-to-scan correlation of the edge turn's whitened errors (fourteenth session, issue 18):
for every fix of one run whose turn came from the edges (planes.edge_turn; the true pose as
the prediction, gross fixes left out), per face, the number of fixes, the mean squared
whitened error and its correlation at lags of 1, 2, 5, 10 and 20 scans.

Usage: python yu_edge_turn_acf.py SCENARIO RUN   (e.g. yu2019 0)
"""
import sys

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.runner import run_seed
from tumblenav.frontends.depth_pose import pose_fixes
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, target_model

sc = load_scenario(sys.argv[1])
run = int(sys.argv[2])
model, sigma = target_model(sc), sc.sensor.range_noise_m
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, run))
R_CL, R_LI = rot.quat_to_matrix(meas.q_CL), rot.quat_to_matrix(meas.q_LI)
seq = {}
for k in range(len(meas.t)):
    R_ST = R_CL[k] @ R_LI[k] @ rot.quat_to_matrix(truth.q_TI[k]).T
    pts = meas.points[k][meas.observed[k]]
    fixes = pose_fixes(pts, model, 3 * sigma, np.random.default_rng(k), sigma, R_ST, edge_turn=True)
    for f in fixes[0]:
        if f.turn_var is None:
            continue
        R = f.R_SM @ f.R_MP
        xt = R.T @ (R_ST @ f.R_MP)[:, 0]
        e = np.arctan2(xt[1], xt[0])
        if abs(e) < 0.1:
            seq.setdefault(f.rectangle, {})[k] = e / np.sqrt(f.turn_var)
for name, d in seq.items():
    z = np.array(list(d.values()))
    out = []
    for lag in (1, 2, 5, 10, 20):
        pairs = np.array([(d[k], d[k + lag]) for k in d if k + lag in d])
        if len(pairs) > 5:
            out.append(f"lag{lag} {np.corrcoef(pairs.T)[0, 1]:+.2f}")
    print(name, len(z), "whitened var", round(float(np.mean(z**2)), 2), " ".join(out))
