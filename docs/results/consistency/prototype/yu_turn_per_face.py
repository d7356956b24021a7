"""Each rectangle's turn about its normal per run (thirteenth session, issue 18): the fixes of
runs 0..RUNS-1 against the truth (benchmarks/yu2019_fix_errors.fix_errors, gross fixes left
out), per run and rectangle the turn's median, mean and standard deviation (mrad), its
autocorrelation at lags 1, 10, 100 scans, and the two tilts' spread and mean.

Usage: python yu_turn_per_face.py SCENARIO RUNS (e.g. yu2019 4)
"""
import sys, numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[4] / "benchmarks"))
from yu2019_fix_errors import fix_errors, gross
from tumblenav.scenario import load_scenario
sc = load_scenario(sys.argv[1]); runs = int(sys.argv[2])
for run in range(runs):
    per = {}
    for k, fx, za, zp, ea in fix_errors(sc, run):
        if gross(za, zp): continue
        en = (fx.R_MP.T @ ea)  # in P: short, long, normal (rad)
        per.setdefault(fx.rectangle, []).append((k, en, fx.R_MP[:, 2]))
    for r, v in per.items():
        ks = np.array([a[0] for a in v]); e = np.array([a[1] for a in v]); nrm = v[0][2]
        en = e[:, 2]
        def ac(x, lag):
            m = {kk: i for i, kk in enumerate(ks)}
            pairs = [(i, m[kk+lag]) for i, kk in enumerate(ks) if kk+lag in m]
            if len(pairs) < 10: return np.nan
            a = np.array(pairs); xx = x - x.mean()
            return np.corrcoef(xx[a[:,0]], xx[a[:,1]])[0,1]
        print(f"run {run} rect {r} normal_M {np.round(nrm,2)} n={len(en)} turn-about-normal median {np.median(en)*1e3:.2f} mean {en.mean()*1e3:.2f} mrad std {en.std()*1e3:.2f}; ac lag1 {ac(en,1):.2f} lag10 {ac(en,10):.2f} lag100 {ac(en,100):.2f}; tilts std {e[:,0].std()*1e3:.2f} {e[:,1].std()*1e3:.2f} mean {e[:,0].mean()*1e3:.2f} {e[:,1].mean()*1e3:.2f}")
