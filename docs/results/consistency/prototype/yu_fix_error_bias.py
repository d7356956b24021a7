"""Session script (eleventh session): per rectangle and run, the mean over the standard
deviation of each fix error component, and the attitude error's mean and spread in T (mrad).
Usage (repo root, venv active): python docs/results/consistency/prototype/yu_fix_error_bias.py
SCENARIO RUNS"""
import sys, numpy as np
sys.path.insert(0, "docs/results/consistency/prototype"); sys.path.insert(0, "benchmarks")
from yu_fix_error_autocorrelation import run, load_scenario
sc = load_scenario(sys.argv[1])
for r in range(int(sys.argv[2])):
    rec = run(sc, r)
    for j, d in sorted(rec.items(), key=lambda kv: str(kv[0])):
        Z = np.array(list(d.values()))
        if len(Z) < 30: continue
        m, s = Z[:, :6].mean(0), Z[:, :6].std(0)
        print(f"run {r} rect {j} n={len(Z)} mean/std att {np.round(m[:3]/s[:3],2)} pos {np.round(m[3:]/s[3:],2)}  att mean mrad(T) {np.round(Z[:,6:].mean(0)*1e3,2)} std {np.round(Z[:,6:].std(0)*1e3,2)}")
