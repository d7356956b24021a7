"""Why the ukf's NIS sits at ~0.91 on every Kabir case while the features are seen
(twenty-first session, issue 18): each update's innovation per measurement component, nu^2
over its S diagonal, averaged over the scenario's window.

Records ``nu`` and ``diag(S)`` inside ``kabir2025.filter._UKFModel.update`` (a copy of its
source with one line added, exec'd in the module's namespace), runs the estimator on runs
SEEDS of SCENARIO and prints the mean per component (u_R, v_R, u_L, v_L, disparity, the four
flows; a component the filter does not use prints 0).

Usage::

    [TUNING='{"sigma_flow_rad_s": 1.0}'] python kabir_nis_components.py SCENARIO ESTIMATOR SEEDS
"""
import inspect, textwrap, sys, numpy as np
from tumblenav.estimators.kabir2025 import filter as kf
src = textwrap.dedent(inspect.getsource(kf._UKFModel.update))
src = src.replace("    sol = np.linalg.solve(S,", "    _REC.append((k, rows.copy(), nu.copy(), np.diagonal(S, axis1=1, axis2=2).copy()))\n    sol = np.linalg.solve(S,")
assert "_REC.append" in src
ns = dict(vars(kf)); _REC = []; ns["_REC"] = _REC
exec(src, ns)
kf._UKFModel.update = ns["update"]
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate
import json, os
sc = load_scenario(sys.argv[1]); est = est_base.get(sys.argv[2])
tun = json.loads(os.environ.get("TUNING", "{}"))
if tun:
    sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tun}})
w0, w1 = sc.window_s
for k in [int(a) for a in sys.argv[3].split(",")]:
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tracks, _ = stages.prepare(meas, tuple(est.consumes), None)
    _REC.clear()
    h = est.run(context_from_scenario(sc), tracks, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"])
    t = h.t
    acc = np.zeros(9); cnt = np.zeros(9)
    for (kk, rows, nu, sd) in _REC:
        if not (w0 <= t[kk] <= w1): continue
        r = rows[0]; z2 = np.where(r, nu[0] ** 2 / np.where(r, sd[0], 1.0), 0.0)
        comp = np.arange(len(r)) % 9
        np.add.at(acc, comp[r], z2[r]); np.add.at(cnt, comp[r], 1)
    print(f"run {k}: per-component mean nu^2/S_ii (u_R v_R u_L v_L disp flow...):", np.round(acc / np.maximum(cnt, 1), 3), "counts", cnt.astype(int))
