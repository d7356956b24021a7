"""The inertia ratios' error split across and along the constraint surface (twenty-second
session, issue 18): per run of SCENARIO, the ratio block's NEES/dof projected on the tangent
plane of c(p) = 0 at the estimate (2 dof), along its normal, and the whole block (3 dof),
averaged over the scenario's window.

Usage::

    python hu_ratio_tangent.py SCENARIO SEEDS ['{"constraint_update": "measurement"}']
"""
import sys, json, numpy as np
from threadpoolctl import threadpool_limits
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.hu2024.model import inertia_constraint
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate
sc = load_scenario(sys.argv[1]); seeds=[int(s) for s in sys.argv[2].split(",")]
tun = json.loads(sys.argv[3]) if len(sys.argv)>3 else {}
if tun: sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tun}})
est = est_base.get(sc.estimator.name)
rows=[]
for k in seeds:
  with threadpool_limits(1,"blas"):
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tracks,_ = stages.prepare(meas, tuple(est.consumes), None)
    h = est.run(context_from_scenario(sc), tracks, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"])
  dx = h.layout.boxminus(align(truth, h).x, h.x)
  E=np.arange(h.layout.dim); ip=E[h.layout.err("inertia")]; sp=h.layout.nom("inertia")
  t=h.t; w0,w1 = sc.window_s if sc.window_s else (0.75*t[-1], t[-1])
  ok = np.array([h.P[i] is not None and np.all(np.isfinite(h.P[i])) for i in range(len(t))]) & np.all(np.isfinite(dx),axis=1)
  sel = np.flatnonzero((t>=w0)&(t<=w1)&ok)
  if not len(sel): print(k,"no start"); continue
  nt=[]; nn=[]; en=[]; sn=[]
  for i in sel:
    e = dx[i, ip]; P = h.P[i][np.ix_(ip,ip)]
    _, g = inertia_constraint(h.x[i, sp][None], jac=True); n = g[0]/np.linalg.norm(g[0])
    T = np.eye(3) - np.outer(n,n)
    et = T@e; Pt = T@P@T
    nt.append(et@np.linalg.pinv(Pt, rcond=1e-10, hermitian=True)@et/2)
    en.append(n@e); sn.append(np.sqrt(n@P@n))
    nn.append((n@e)**2/(n@P@n))
  full = np.mean([dx[i,ip]@np.linalg.solve(h.P[i][np.ix_(ip,ip)], dx[i,ip])/3 for i in sel])
  r = dict(full=full, tangent=np.mean(nt), normal=np.mean(nn), e_n=np.sqrt(np.mean(np.square(en))), s_n=np.mean(sn))
  rows.append(r); print(k, " ".join(f"{a}={b:.3g}" for a,b in r.items()), flush=True)
print("mean", " ".join(f"{a}={np.mean([r[a] for r in rows]):.3g}" for a in rows[0]))
