"""The grid's phase drift along each side that planes.edge_turn's variance uses (fourteenth
session, issue 18): for every SCANS-th scan of one run, per (side, grid direction) group of
edge points, the drift in periods over the side's extent (``kappa`` x the spread of the
points along it) and the median bracket. Opposite sides of one face share the drift (equal
magnitude, opposite sign); taken from the noisy returns (the code at e0fc77c, `git checkout
e0fc77c -- src`) they did not (yu2019 run 0 scan 180: 1.07 and -0.11 periods; from the rays
-0.24 and +0.24).

Usage: python yu_edge_drift.py SCENARIO RUN SCANS   (e.g. yu2019 0 20)
"""
import sys

import numpy as np

import tumblenav.frontends.depth_pose as dp
from tumblenav import rotations as rot
from tumblenav.campaign.runner import run_seed
from tumblenav.frontends import planes as pl
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, target_model

sc = load_scenario(sys.argv[1])
run, every = int(sys.argv[2]), int(sys.argv[3])
model, sigma = target_model(sc), sc.sensor.range_noise_m
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, run))
R_CL, R_LI = rot.quat_to_matrix(meas.q_CL), rot.quat_to_matrix(meas.q_LI)
captured = {}
variance = pl._sawtooth_turn_variance


def capture(along, L, w, side, fam, step, other, long_side, sn):
    captured["groups"] = (along, L, side, fam, step, other, long_side)
    return variance(along, L, w, side, fam, step, other, long_side, sn)


pl._sawtooth_turn_variance = capture
for k in range(0, len(meas.t), every):
    R_ST = R_CL[k] @ R_LI[k] @ rot.quat_to_matrix(truth.q_TI[k]).T
    captured.clear()
    dp.pose_fixes(
        meas.points[k][meas.observed[k]], model, 3 * sigma, np.random.default_rng(k), sigma,
        R_ST, edge_turn=True,
    )
    if "groups" not in captured:
        continue
    along, L, side, fam, step, other, long_side = captured["groups"]
    for s in range(4):
        for f in range(4):
            m = (side == s) & (fam == f)
            if m.sum() < 4:
                continue
            nrm = np.array([1.0, 0.0]) if long_side[m][0] else np.array([0.0, 1.0])
            tng = np.array([-nrm[1], nrm[0]])
            g, go = np.median(step[m], axis=0), np.median(other[m], axis=0)
            drift = -(nrm @ go) / (nrm @ g)
            advance = tng @ go + drift * (tng @ g)
            periods = drift / advance * np.ptp(along[m]) if abs(advance) > 1e-12 else 0.0
            print(f"scan {k:3d} side {s} direction {f} n={m.sum():3d} drift {periods:+.2f} "
                  f"periods, bracket {1e3 * np.median(L[m]):.1f} mm")
