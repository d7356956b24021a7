"""How is a fix's turn about its rectangle's normal distributed? (thirteenth session, issue
18.) For each fix of the given runs (benchmarks/yu2019_fix_errors.fix_errors; gross fixes
left out), the attitude error in the rectangle frame whitened by the filter's fix model at
scale 1 (fixes.fix_noise, white and slow parts): the turn's variance, its robust variance
(MAD), a Student-t fit (location 0) and the lag autocorrelation of the clipped (3 robust
sigma) turns per rectangle; the tilts' variances for comparison.

Usage: python yu_turn_distribution.py SCENARIO RUNS (e.g. yu2019 0,1,2)
"""

import sys

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[4] / "benchmarks"))
from scipy import stats
from yu2019_fix_errors import fix_errors, gross

from tumblenav.estimators.yu2019.fixes import fix_noise
from tumblenav.scenario import load_scenario
from tumblenav.simulation import target_model

sc = load_scenario(sys.argv[1])
runs = [int(s) for s in sys.argv[2].split(",")]
model = target_model(sc)
sigma = sc.sensor.range_noise_m
cen = {r.name: np.asarray(r.centre_M, float) for r in model.rectangles}
Z = []
AC = {1: [], 5: [], 20: [], 80: []}
for run in runs:
    per = {}
    for k, fx, za, zp, ea in fix_errors(sc, run):
        if gross(za, zp):
            continue
        c = cen.get(fx.rectangle, np.zeros(3))
        nz = fix_noise(fx, sigma, 3 * sigma, centre_M=c, view_S=fx.p_MinS + fx.R_SM @ c)
        e = fx.R_MP.T @ ea
        z = e / np.sqrt(np.diag(nz.base)[:3])
        Z.append(z)
        per.setdefault(fx.rectangle, []).append((k, z[2]))
    for r, v in per.items():
        ks = np.array([a[0] for a in v])
        z = np.array([a[1] for a in v])
        rs = 1.4826 * np.median(np.abs(z))
        zc = np.clip(z, -3 * rs, 3 * rs)
        m = {kk: i for i, kk in enumerate(ks)}
        for lag in AC:
            pr = np.array([(i, m[kk + lag]) for i, kk in enumerate(ks) if kk + lag in m])
            if len(pr) > 20:
                AC[lag].append(np.mean(zc[pr[:, 0]] * zc[pr[:, 1]]) / np.mean(zc**2))
Z = np.array(Z)
z = Z[:, 2]
rs = 1.4826 * np.median(np.abs(z - np.median(z)))
df, loc, scale = stats.t.fit(z, floc=0)
print(
    f"{sys.argv[1].split('/')[-1]}: n={len(z)} normal var {np.mean(z**2):.3f} robust^2 {rs**2:.3f} t df {df:.2f} scale^2 {scale**2:.3f}; clipped ac "
    + " ".join(f"lag{l} {np.mean(a):.2f}" for l, a in AC.items())
    + f" | tilts var {np.mean(Z[:, 0] ** 2):.2f} {np.mean(Z[:, 1] ** 2):.2f}"
)
