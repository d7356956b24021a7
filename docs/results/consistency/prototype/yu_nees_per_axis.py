"""Per-axis NEES of each block (thirteenth session, issue 18): for each run, the mean over the
scenario's window of ``e_i^2 / P_ii`` per component of every block of the estimator's state,
and for the attitude, rate, position, offset and velocity the error's RMS and the mean
1-sigma per axis (as benchmarks/block_nees.py, whose per-block NEES uses the full block
covariance). The optional JSON updates ``estimator.tuning``.

Usage: python yu_nees_per_axis.py SCENARIO ESTIMATOR SEEDS [TUNING_JSON]
   e.g. python yu_nees_per_axis.py yu2019 ekf-depth 0,1,2,3 '{"fix_noise_learnt": [true, true, true, true, true, true]}'
"""
import sys, json, numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[4] / "benchmarks"))
from threadpoolctl import threadpool_limits
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate
import block_nees as bn
scen, name = sys.argv[1], sys.argv[2]
seeds = [int(s) for s in sys.argv[3].split(",")]
tun = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
sc = load_scenario(scen)
if tun:
    d = sc.model_dump(); d["estimator"]["tuning"].update(tun); sc = type(sc).model_validate(d)
res = {}
for k in seeds:
    with threadpool_limits(1):
        est = est_base.get(name)
        truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
        consumes = tuple(getattr(est, "consumes", ()))
        tracks, _ = stages.prepare(meas, consumes, None)
        h = est.run(context_from_scenario(sc), tracks, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"])
    dx = h.layout.boxminus(align(truth, h).x, h.x)
    t = h.t; w0, w1 = sc.window_s if sc.window_s else (0.75*t[-1], t[-1])
    sel = np.flatnonzero((t >= w0) & (t <= w1))
    out = {}
    for b in h.layout.blocks:
        ix = np.arange(h.layout.dim)[h.layout.err(b.name)]
        e = dx[sel][:, ix]; v = np.array([np.diag(h.P[i])[ix] for i in sel])
        out[b.name] = (np.mean(e**2/v, axis=0).round(2).tolist(), np.sqrt(np.mean(e**2, axis=0)).tolist(), np.sqrt(np.mean(v, axis=0)).tolist())
    print(k, {n: v[0] for n, v in out.items()})
    for n in ("attitude", "rate", "position", "offset", "velocity"):
        print("   ", n, "rms", np.array(out[n][1]).round(6), "sig", np.array(out[n][2]).round(6))
