"""The turn about a fix's normal from the second moments (as shipped) against the one from
the edges (planes.edge_turn: each grid row's last return and the next ray bracket the edge;
fourteenth session, issue 18). For each fix of the given runs (the true pose as the
prediction, gross fixes left out), the turn's error against the truth; printed per run and
face: the median and RMS (mrad) of both, and the edge turn's error whitened by its own
variance.

Usage: python yu_edge_turn.py SCENARIO RUNS [EVERY]   (e.g. yu2019 0,1 5: every 5th scan)
"""
import sys
from collections import defaultdict

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.runner import run_seed
from tumblenav.frontends.depth_pose import pose_fixes
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, target_model

sc = load_scenario(sys.argv[1])
runs = [int(s) for s in sys.argv[2].split(",")]
every = int(sys.argv[3]) if len(sys.argv) > 3 else 1
model, sigma = target_model(sc), sc.sensor.range_noise_m
centre = {r.name: np.asarray(r.centre_M, float) for r in model.rectangles}
allm, alle, allz, allc = [], [], [], []
for run in runs:
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, run))
    R_CL, R_LI = rot.quat_to_matrix(meas.q_CL), rot.quat_to_matrix(meas.q_LI)
    per = defaultdict(lambda: ([], [], []))
    for k in range(0, len(meas.t), every):
        R_LT = R_LI[k] @ rot.quat_to_matrix(truth.q_TI[k]).T
        pts = meas.points[k][meas.observed[k]]
        out = []
        for edge in (False, True):
            fixes, _ = pose_fixes(
                pts, model, 3 * sigma, np.random.default_rng(k), sigma, R_CL[k] @ R_LT,
                edge_turn=edge,
            )
            out.append({f.rectangle: f for f in fixes})
        for name, f0 in out[0].items():
            f1 = out[1].get(name)
            if f1 is None or f1.turn_var is None:
                continue
            e = []
            for f in (f0, f1):
                q_meas = rot.matrix_to_quat((R_LI[k].T @ R_CL[k].T @ f.R_SM).T)
                e.append(f.R_MP.T @ rot.boxminus(q_meas, truth.q_TI[k]))
            if np.abs(e[0]).max() > 0.1 or np.abs(e[1]).max() > 0.1:
                continue
            per[name][0].append(e[0][2]), per[name][1].append(e[1][2])
            per[name][2].append(e[1][2] / np.sqrt(f1.turn_var))
            normal = f1.R_SM @ f1.R_MP[:, 2]
            view = f1.p_MinS + f1.R_SM @ centre[name]
            allc.append(abs(normal @ view) / np.linalg.norm(view))
    for name, (m, g, z) in sorted(per.items()):
        m, g, z = (np.array(v) for v in (m, g, z))
        allm += list(m); alle += list(g); allz += list(z)
        print(
            f"run {run} {name:10s} n={len(m):4d}  moments median {1e3*np.median(m):+6.2f} RMS "
            f"{1e3*np.sqrt(np.mean(m**2)):5.2f} mrad | edges median {1e3*np.median(g):+6.2f} RMS "
            f"{1e3*np.sqrt(np.mean(g**2)):5.2f} mrad, whitened var {np.mean(z**2):.2f}"
        )
allm, alle, allz, allc = map(np.array, (allm, alle, allz, allc))
for lo, hi in ((0.8, 1.01), (0.5, 0.8), (0.0, 0.5)):
    m = (allc >= lo) & (allc < hi)
    if m.any():
        print(
            f"cos(incidence) {lo:.1f}-{hi:.1f}: n={m.sum():4d} edges RMS "
            f"{1e3*np.sqrt(np.mean(alle[m]**2)):.2f} mrad, whitened var {np.mean(allz[m]**2):.2f}"
        )
print(
    f"all: n={len(allm)} moments RMS {1e3*np.sqrt(np.mean(allm**2)):.2f} mrad, edges RMS "
    f"{1e3*np.sqrt(np.mean(alle**2)):.2f} mrad, edges whitened var {np.mean(allz**2):.2f} "
    f"(|z| quantiles 50/90/99 %: {np.round(np.quantile(np.abs(allz), [0.5, 0.9, 0.99]), 2)}; "
    "Gaussian 0.67/1.64/2.58)"
)
