"""Each rectangle's fix errors against the truth, per model rectangle (thirteenth session,
issue 18): needs the region split of ``yu_split_regions.patch`` (``git apply`` it first), so
that the two coplanar wings come out as two panels. Fixes are made with the true attitude and
origin as the prediction (so equal-attitude panels are told apart as the filter does);
printed per rectangle: whitened variance of the six components against the filter's fix
model (attitude about the short side, long side, normal; centre along them), their mean, and
the raw errors' median and RMS (mrad / mm); "gross": d^2 > 50 on 6 dof.

Usage: SPLIT=0.25 python yu_panel_fix_errors.py SCENARIO RUNS (e.g. 0,1)
"""

import collections
import os
import sys

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.runner import run_seed
from tumblenav.estimators.yu2019.fixes import fix_noise
from tumblenav.frontends.depth_pose import pose_fixes
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, target_model

sc = load_scenario(sys.argv[1])
runs = [int(s) for s in sys.argv[2].split(",")]
gap = float(os.environ.get("SPLIT", "0.25"))
model = target_model(sc)
sigma = sc.sensor.range_noise_m
cen = {r.name: np.asarray(r.centre_M, float) for r in model.rectangles}
A = collections.defaultdict(list)
RAW = collections.defaultdict(list)
NP = collections.defaultdict(list)
for run in runs:
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, run))
    rng = np.random.default_rng(run)
    R_CL, R_LI = rot.quat_to_matrix(meas.q_CL), rot.quat_to_matrix(meas.q_LI)
    b = np.asarray(truth.mass_centre_offset_T)
    for k in range(len(meas.t)):
        R_LT = R_LI[k] @ rot.quat_to_matrix(truth.q_TI[k]).T
        origin_L = truth.r_L[k] - R_LT @ b
        pts = meas.points[k][meas.observed[k]]
        fixes, _ = pose_fixes(
            pts,
            model,
            3 * sigma,
            rng,
            sigma,
            R_CL[k] @ R_LT,
            p_MinS_predicted=R_CL[k] @ origin_L,
            split_gap_sides=gap,
        )
        for fx in fixes:
            c = cen[fx.rectangle]
            nz = fix_noise(fx, sigma, 3 * sigma, centre_M=c, view_S=fx.p_MinS + fx.R_SM @ c)
            q_meas = rot.matrix_to_quat((R_LI[k].T @ R_CL[k].T @ fx.R_SM).T)
            e = fx.R_MP.T @ rot.boxminus(q_meas, truth.q_TI[k])
            R_LP = R_CL[k].T @ fx.R_SM @ fx.R_MP
            ep = R_LP.T @ (R_CL[k].T @ fx.p_MinS - origin_L)
            C = nz.cov() + (lambda F: F @ F.T)(nz.slow_factor())
            z = np.r_[e, ep] / np.sqrt(np.diag(C))
            key = fx.rectangle
            A[key].append(z)
            RAW[key].append(np.r_[e * 1e3, ep * 1e3])
            NP[key].append(fx.n_points)
for key in sorted(A):
    z = np.array(A[key])
    raw = np.array(RAW[key])
    big = np.sum(z**2, axis=1) > 50
    print(
        key,
        len(z),
        "npts med",
        int(np.median(NP[key])),
        "gross",
        big.sum(),
        "whitened var",
        np.round(np.mean(z[~big] ** 2, 0), 2),
        "mean z",
        np.round(np.mean(z[~big], 0), 2),
    )
    print(
        "     raw mrad/mm median",
        np.round(np.median(raw, 0), 2),
        "rms(non-gross)",
        np.round(np.sqrt(np.mean(raw[~big] ** 2, 0)), 2),
    )
