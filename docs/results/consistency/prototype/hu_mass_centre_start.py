"""ekf-dpacf started with its mass centre moved (twenty-second session, issue 18): the start's
position set to the truth's and its features shifted so that the mass centre is OFF metres
off along (1, 1, 1) (OFF=0: the true mass centre), the start's covariance as built; prints
per run the blocks' NEES/dof over the window and the position's RMSE (SERIES=1: the mass
centre's error in T over time).

Usage::

    OFF=0.1 [SERIES=1] python hu_mass_centre_start.py SCENARIO SEEDS ['{"refine_start": false}']
"""
import sys, json, numpy as np
from threadpoolctl import threadpool_limits
from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
import tumblenav.estimators.hu2024.filter as F
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate
sc = load_scenario(sys.argv[1]); seeds=[int(s) for s in sys.argv[2].split(",")]
tun = json.loads(sys.argv[3]) if len(sys.argv)>3 else {}
if tun: sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tun}})
est = est_base.get(sc.estimator.name)
TR={}
import os
OFF=float(os.environ.get("OFF","0"))
orig = F._initial_state
def wrap(*a, **k):
    out = orig(*a, **k); lay=a[3]; T=TR['t']
    for b in range(len(out.k0)):
        k0=out.k0[b]
        if k0<0: continue
        x=out.x0[b]; rL=x[lay.nom("position")]; d = T.r_L[k0]-rL
        q=x[lay.nom("attitude")]; R_LI = rot.quat_to_matrix(T.q_LI[k0]); R_TI = rot.quat_to_matrix(q)
        R_LT = R_LI @ R_TI.T
        dc = R_LT.T @ d - OFF*np.array([0.577,0.577,0.577])
        x[lay.nom("position")] = rL + d
        f = x[lay.nom("features")].reshape(-1,3); kn = np.any(f!=0,axis=1)
        f[kn] -= dc; x[lay.nom("features")] = f.ravel()
        print("moved CM by", np.round(dc,3))
    return out
F._initial_state = wrap
for k in seeds:
  with threadpool_limits(1,"blas"):
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k)); TR['t']=truth
    tracks,_ = stages.prepare(meas, tuple(est.consumes), None)
    h = est.run(context_from_scenario(sc), tracks, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"])
  dx = h.layout.boxminus(align(truth, h).x, h.x)
  t=h.t; w0,w1=sc.window_s
  ok = np.array([h.P[i] is not None and np.all(np.isfinite(h.P[i])) for i in range(len(t))]) & np.all(np.isfinite(dx),axis=1)
  sel=np.flatnonzero((t>=w0)&(t<=w1)&ok); E=np.arange(h.layout.dim)
  out={}
  for bname in ["attitude","position","velocity","features"]:
    ix=E[h.layout.err(bname)]
    out[bname]=np.mean([dx[i,ix]@np.linalg.solve(h.P[i][np.ix_(ix,ix)],dx[i,ix])/len(ix) for i in sel])
  out['pos_err_m']=np.sqrt(np.mean(np.sum(dx[sel][:,E[h.layout.err("position")]]**2,1)))
  print(k, " ".join(f"{a}={b:.3g}" for a,b in out.items()))
  if os.environ.get("SERIES"):
    ip=E[h.layout.err("position")]
    for i in sel[::max(1,len(sel)//10)].tolist() + []:
        pass
    okk=np.flatnonzero(ok)
    for i in okk[::max(1,len(okk)//15)]:
        q=h.x[i, h.layout.nom("attitude")]; R_LT = rot.quat_to_matrix(truth.q_LI[i]) @ rot.quat_to_matrix(q).T
        eT = R_LT.T @ dx[i, ip]; sT = np.sqrt(np.diag(R_LT.T @ h.P[i][np.ix_(ip,ip)] @ R_LT))
        print(f"   t={t[i]:6.1f} CM err in T {np.round(eT*1e3,1)} mm  sigma(T) {np.round(sT*1e3,1)}")
