"""A first-order theory of the turn about a face's normal against the measured one (thirteenth
session, issue 18; not kept): each edge's excess points rho h (phi(y) - 1/2) with the grid's
phase phi drifting r times along the edge, the turn J_xy / (lambda_long - lambda_short); the
variance over a uniform phase, v(r), is tabulated and summed over both lattice families and
both edge pairs for each fix; printed: v(r) at a few r, and the observed squared turn over the
predicted one in octiles of the prediction.

Usage: python yu_turn_theory.py SCENARIO RUNS (e.g. yu2019 0,1,2,3)
"""
import sys, numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[4] / "benchmarks"))
from yu2019_fix_errors import fix_errors, gross
from tumblenav.scenario import load_scenario
from tumblenav.simulation import target_model
from tumblenav.estimators.yu2019.fixes import fix_noise
u = (np.arange(4000) + 0.5) / 4000 - 0.5
ph = (np.arange(256) + 0.5) / 256
def v(r):
    f = np.mod(ph[:, None] + r * (u[None, :] + 0.5), 1.0) - 0.5
    I = (f * u[None, :]).mean(axis=1)
    return I.var()
rs = np.r_[0, np.geomspace(0.01, 200, 120)]
vt = np.array([v(r) for r in rs])
for r in (0.1, 0.25, 0.5, 1, 1.5, 2, 3, 5, 10, 30, 100): print(f"v({r}) = {np.interp(r, rs, vt):.5f}")
def vv(r): return np.interp(r, rs, vt)
sc = load_scenario(sys.argv[1]); runs = [int(s) for s in sys.argv[2].split(",")]
model = target_model(sc); sigma = sc.sensor.range_noise_m
cen = {r.name: np.asarray(r.centre_M, float) for r in model.rectangles}
PRED, OBS, MOD = [], [], []
for run in runs:
    for k, fx, za, zp, ea in fix_errors(sc, run):
        if gross(za, zp): continue
        c = cen.get(fx.rectangle, np.zeros(3))
        view = fx.p_MinS + fx.R_SM @ c
        nz = fix_noise(fx, sigma, 3*sigma, centre_M=c, view_S=view)
        C = nz.cov() + (lambda F: F @ F.T)(nz.slow_factor())
        e = fx.R_MP.T @ ea
        R_SP = fx.R_SM @ fx.R_MP
        n = R_SP[:, 2]; d = view / np.linalg.norm(view)
        b, a = fx.sides_m
        e1 = np.cross(d, [0, 0, 1.0]); e1 /= np.linalg.norm(e1); e2 = np.cross(e1, d)
        S = []
        for ax in (e1, e2):
            s = ax - (n @ ax) / (n @ d) * d
            S.append((R_SP.T @ s)[:2])
        S = np.array(S)
        scale = np.sqrt(a * b / max(fx.n_points, 3) / abs(np.linalg.det(S)))
        S = S * scale
        K = np.linalg.inv(S).T
        # family i: lines of constant k_i . p, spacing 1/|k_i|; wraps along the long edge: a |k_i . y|
        pred = 0.0
        for i in range(2):
            hp = 1 / np.linalg.norm(K[i])
            rl = a * abs(K[i] @ [0, 1.0]); rsh = b * abs(K[i] @ [1.0, 0])
            pred += 72 * hp**2 * (a**2 * vv(rl) + b**2 * vv(rsh)) / (a**2 - b**2) ** 2
        PRED.append(pred); OBS.append(e[2] ** 2); MOD.append(C[2, 2])
PRED, OBS, MOD = map(np.array, (PRED, OBS, MOD))
print("overall obs/pred", OBS.mean() / PRED.mean(), "obs/model", OBS.mean() / MOD.mean())
q = np.quantile(PRED, np.linspace(0, 1, 9))
for lo, hi in zip(q[:-1], q[1:]):
    m = (PRED >= lo) & (PRED <= hi)
    print(f"pred sd {np.sqrt(lo)*1e3:7.2f}-{np.sqrt(hi)*1e3:7.2f} mrad n={m.sum():4d} obs rms {np.sqrt(OBS[m].mean())*1e3:7.2f} mrad obs/pred {OBS[m].mean()/PRED[m].mean():.2f} obs/model {OBS[m].mean()/MOD[m].mean():.2f}")
