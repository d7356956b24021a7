"""Is a face's turn bias the front end's or the sampling's? (thirteenth session, issue 18.) For
each fix of rectangle NAME in run RUN: the turn about the true normal (mod pi, mrad) of the
fix, and of the principal axes of the face's true points (the cloud's points within 3 sigma of
the true face and inside its sides, selected with the truth; footprint-weighted and plain).

Usage: python yu_turn_true_points.py SCENARIO RUN NAME (e.g. yu2019 1 bus-y)
"""
import sys, numpy as np, collections
from tumblenav import rotations as rot
from tumblenav.campaign.runner import run_seed
from tumblenav.frontends.depth_pose import pose_fixes
from tumblenav.frontends.planes import distribution_matrix, ray_footprint_weights, rectangle_frame, RECTANGLE_SYMMETRIES
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, target_model
sc = load_scenario(sys.argv[1]); run = int(sys.argv[2]); want = sys.argv[3]
model = target_model(sc); sigma = sc.sensor.range_noise_m
rect = [r for r in model.rectangles if r.name == want][0]
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, run))
rng = np.random.default_rng(run)
R_CL, R_LI = rot.quat_to_matrix(meas.q_CL), rot.quat_to_matrix(meas.q_LI)
b_off = np.asarray(truth.mass_centre_offset_T)
res = collections.defaultdict(list)
def turn(R_SP_est, R_SP_true):
    """The turn about the true normal from the true short axis to the estimate's (mod pi)."""
    n = R_SP_true[:, 2]; xt = R_SP_true[:, 0]; xe = R_SP_est[:, 0]
    xe = xe - (xe @ n) * n
    a = np.arctan2(np.cross(xt, xe) @ n, xt @ xe)
    return (a + np.pi / 2) % np.pi - np.pi / 2
for k in range(len(meas.t)):
    R_LT = R_LI[k] @ rot.quat_to_matrix(truth.q_TI[k]).T
    R_ST = R_CL[k] @ R_LT
    origin_S = R_CL[k] @ (truth.r_L[k] - R_LT @ b_off)
    pts = meas.points[k][meas.observed[k]]
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    fixes, _ = pose_fixes(pts, model, 3 * sigma, rng, sigma, R_ST, p_MinS_predicted=origin_S)
    R_SP_true = R_ST @ rect.R_MP
    for fx in fixes:
        if fx.rectangle != want: continue
        t_fix = turn(fx.R_SM @ fx.R_MP, R_SP_true)
        # the true face points: within 3 sigma of the face plane and inside its sides
        pT = (pts - origin_S) @ R_ST  # in M (model frame = T here up to the offset convention)
        c = np.asarray(rect.centre_M); q = (pT - c) @ rect.R_MP  # in P
        bb, aa = rect.sides_m
        on = (np.abs(q[:, 2]) < 3 * sigma) & (np.abs(q[:, 0]) <= bb / 2 + 3*sigma) & (np.abs(q[:, 1]) <= aa / 2 + 3*sigma)
        if on.sum() < 50: continue
        sel = pts[on]
        n_S = R_SP_true[:, 2]
        for name, w in (("weighted", ray_footprint_weights(sel, n_S)), ("plain", None)):
            d = distribution_matrix(sel, w)
            res[name].append(turn(rectangle_frame(d), R_SP_true))
        # noise-free: project the true face points onto the plane (remove range noise along rays)
        res["fix"].append(t_fix); res["n_fix"].append(fx.n_points); res["n_true"].append(on.sum())
for kk in ("fix", "weighted", "plain"):
    v = np.array(res[kk]) * 1e3
    print(f"{kk:9s} n={len(v)} median {np.median(v):6.2f} mean {v.mean():6.2f} rms {np.sqrt(np.mean(v**2)):6.2f} mrad")
print("points: fix median", np.median(res["n_fix"]), "true-face median", np.median(res["n_true"]))
