"""Session script (eleventh session): autocorrelation of each rectangle fix's whitened errors
(attitude about the short side, long side, normal; centre along them) at lags of 1-100 scans,
and same-epoch correlation between rectangles. Usage (repo root, venv active): python
docs/results/consistency/prototype/yu_fix_error_autocorrelation.py SCENARIO RUNS"""
import sys, numpy as np
sys.path.insert(0, "benchmarks")
from yu2019_fix_errors import fix_errors, gross
from tumblenav.scenario import load_scenario

def run(sc, r):
    rec = {}
    for k, fx, za, zp, ea in fix_errors(sc, r):  # benchmarks/yu2019_fix_errors.py
        if gross(za, zp): continue
        rec.setdefault(fx.rectangle, {})[k] = np.r_[za, zp, ea]
    return rec

if __name__ == "__main__":
  sc = load_scenario(sys.argv[1])
  lags = [1,3,10,30,100]
  acc = {l: [] for l in lags}; cross = []; ea_all = []
  for r in range(int(sys.argv[2])):
      rec = run(sc, r)
      for j, d in rec.items():
          ks = sorted(d)
          if len(ks) < 20: continue
          for l in lags:
              prs = [(d[k], d[k+l]) for k in ks if k+l in d]
              if len(prs) < 10: continue
              a = np.array([p[0][:6] for p in prs]); b_ = np.array([p[1][:6] for p in prs])
              acc[l].append((a*b_).mean(0)/np.sqrt((a**2).mean(0)*(b_**2).mean(0)))
      # cross-rectangle correlation of the attitude error in T (same epoch)
      js = list(rec)
      for i1 in range(len(js)):
          for i2 in range(i1+1, len(js)):
              common = sorted(set(rec[js[i1]]) & set(rec[js[i2]]))
              if len(common) < 20: continue
              a = np.array([rec[js[i1]][k][6:] for k in common]); b_ = np.array([rec[js[i2]][k][6:] for k in common])
              cross.append(((a*b_).mean(0)/np.sqrt((a**2).mean(0)*(b_**2).mean(0)), len(common)))
  print("components: att short,long,normal, pos short,long,normal")
  for l in lags:
      if acc[l]: print("lag", l, np.round(np.mean(acc[l], 0), 2))
  for c, n in cross: print("cross att (T axes)", np.round(c, 2), n)
