"""ekf-pose at Chang's printed 59 m on point tracks (fifteenth session, issue 18): where does the
over-confidence come from? One run, with a copy of slam.py as of 713e9e8 patched by
chang_far_fej.patch::

    python -c "import yaml; d = yaml.safe_load(open('src/tumblenav/scenarios/chang2021.yaml')); \
        del d['sensor']['images']; d['name'] = 'chang2021_points59'; \
        yaml.safe_dump(d, open('/tmp/c59pt.yaml', 'w'), sort_keys=False)"
    git show 713e9e8:src/tumblenav/estimators/chang2021/slam.py > /tmp/slam_fej.py
    patch /tmp/slam_fej.py docs/results/consistency/prototype/chang_far_fej.patch
    python chang_far_fej.py /tmp/slam_fej.py /tmp/c59pt.yaml 0 '{"check_lag_frames": 0}' [--true-fej]

``--true-fej`` evaluates every map point's first-estimate Jacobian (the attitude columns
``R_LThat [s]x``) at the truth's point (a diagnostic: the truth's features in That, which is L
at the frame epoch 0) instead of its first triangulation; the environment's FEJ_DELAY=K
takes it from a K-frame triangulation with the filter's own poses (new tracks wait K frames),
FEJ_REFRESH=K re-evaluates it once at the map's estimate after K frames. ``--check`` prints
every increment check's d^2 (``slam.increment_check``) and the 1-sigma per axis (deg) of the
q-method increment's first-order covariance inside it. Prints the skipped
epochs, then every ~5 s the attitude and position error against their 1-sigma and the whole
state's NEES/dof.
"""

import importlib.util
import json
import sys

import numpy as np

import tumblenav.estimators.chang2021 as c21
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate

args = [a for a in sys.argv[1:] if a not in ("--true-fej", "--check")]
spec = importlib.util.spec_from_file_location("slam_copy", args[0])
mod = importlib.util.module_from_spec(spec)
sys.modules["slam_copy"] = mod
spec.loader.exec_module(mod)
c21.StateSteps = mod.StateSteps
if "--check" in sys.argv:
    import tumblenav.estimators.chang2021.qmethod as qm

    q_cov, check = qm.q_method_covariance, mod.increment_check
    inside = []

    def q_cov_shown(*a, **kw):
        P, H = q_cov(*a, **kw)
        if inside:
            print(f"  q-method increment sigma deg {np.round(np.degrees(np.sqrt(np.diag(P))), 2)}")
        return P, H

    def check_shown(tracks, a, k, *rest, **kw):
        inside.append(1)
        d2 = check(tracks, a, k, *rest, **kw)
        inside.pop()
        print(f"check epochs {a}-{k}: d2 {d2}")
        return d2

    qm.q_method_covariance, mod.increment_check = q_cov_shown, check_shown
sc, k = load_scenario(args[1]), int(args[2])
tun = json.loads(args[3]) if len(args) > 3 else {}
if tun:
    sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tun}})
est = est_base.get("ekf-pose")
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
if "--true-fej" in sys.argv:
    mod.TRUE_S = truth.features_T @ truth.R_LT[0].T  # R_LT(0) f_T: the features in That
tracks, _ = stages.prepare(meas, tuple(est.consumes), None)
h = est.run(
    context_from_scenario(sc), tracks, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"]
)
print(
    "skipped", {a: b for a, b in h.skipped.items() if b}, "frame_epoch", h.info.get("frame_epoch")
)
dx = h.layout.boxminus(align(truth, h).x, h.x)
for i in range(0, len(h.t), max(1, len(h.t) // 24)):
    if h.P[i] is None or not np.all(np.isfinite(dx[i])):
        continue
    s, e = np.sqrt(np.diag(h.P[i])), dx[i]
    print(
        f"t={h.t[i]:6.1f} attitude {np.degrees(np.linalg.norm(e[0:3])):7.2f} deg (sigma "
        f"{np.degrees(np.linalg.norm(s[0:3])):5.2f}) position {np.linalg.norm(e[6:9]):6.3f} m (sigma "
        f"{np.linalg.norm(s[6:9]):5.3f}) NEES/dof {e @ np.linalg.solve(h.P[i], e) / len(e):9.2f}"
    )
