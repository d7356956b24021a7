"""Session script (eleventh session, not a benchmark): ekf-depth on synthetic fixes, the truth's
pose plus white noise drawn from the filter's own white fix model, to separate the filter
from the fix error model. Usage (from the repo root, venv active): python
docs/results/consistency/prototype/yu_synthetic_fixes.py SCENARIO SEEDS [NOISE_SCALE [TUNING_JSON]];
SERIES=inertia prints that block over time. Applies to the code of commit 34fd2ce and later."""
import json
import sys
from dataclasses import replace

import numpy as np

sys.path.insert(0, "benchmarks")
import block_nees as bn
from tumblenav import rotations as rot
import tumblenav.estimators.yu2019.filter as F
from tumblenav.estimators.yu2019.tuning import plane_threshold

TR = {}
orig = F.DepthSteps._fixes
def fake(self, k, x):
    fixes = orig(self, k, x)
    tr = TR["truth"]; rng = TR["rng"]
    R_CL = rot.quat_to_matrix(tr.q_CL[k]); R_LI = rot.quat_to_matrix(tr.q_LI[k])
    R_TI = rot.quat_to_matrix(tr.q_TI[k]); R_LT = R_LI @ R_TI.T
    origin_L = tr.r_L[k] - R_LT @ np.asarray(tr.mass_centre_offset_T)
    R_SM_true = R_CL @ R_LT
    out = []
    thr = plane_threshold(self.tun, self.sigma)
    for fx in fixes:
        # the symmetric frame nearest the real fix
        best = None
        for G in [np.eye(3), np.diag([1., -1, -1]), np.diag([-1., 1, -1]), np.diag([-1., -1, 1])]:
            Rc = R_SM_true @ G
            ang = np.linalg.norm(rot.matrix_to_rotvec(Rc.T @ fx.R_SM)) if hasattr(rot, "matrix_to_rotvec") else np.arccos(np.clip((np.trace(Rc.T @ fx.R_SM) - 1) / 2, -1, 1))
            if best is None or ang < best[0]:
                best = (ang, Rc, G)
        _, Rc, G = best
        centre_M = self._rect_centre.get(fx.rectangle)
        noise = F.fix_noise(fx, self.sigma, thr, (0.0,) * 6, 7.0, centre_M,
                            fx.p_MinS + fx.R_SM @ (centre_M if centre_M is not None else np.zeros(3)),
                            self.tun.attitude_noise_scale, self.tun.position_noise_scale, 0.0, 0.0)
        C = noise.cov(None) * TR["scale"]
        e = np.linalg.cholesky(C + 1e-30 * np.eye(6)) @ rng.normal(size=6)
        R_TP = fx.R_MP if fx.R_MP is not None else np.eye(3)
        R_LS = R_CL.T
        # truth in the symmetric frame: R_TI' = G^T R_TI (M = G-turned T)
        R_TIc = (R_LI.T @ R_LS @ Rc).T
        q_true = rot.matrix_to_quat(R_TIc)
        q_meas = rot.boxplus(q_true, R_TP @ e[:3])
        R_TIm = rot.quat_to_matrix(q_meas)
        R_SM = R_LS.T @ R_LI @ R_TIm.T
        R_LP = R_LS @ fx.R_SM @ fx.R_MP if fx.R_MP is not None else np.eye(3)
        p_ML = origin_L + R_LP @ e[3:]
        out.append(replace(fx, R_SM=R_SM, p_MinS=R_LS.T @ p_ML))
    return out
F.DepthSteps._fixes = fake
F.TRUTH = TR

_run_orig = bn.run_blocks
_sim = bn.simulate
def sim(sc, seed):
    tr, meas = _sim(sc, seed)
    TR["truth"] = tr; TR["rng"] = np.random.default_rng(seed.spawn(1)[0]) if hasattr(seed, "spawn") else np.random.default_rng(seed)
    return tr, meas
bn.simulate = sim
TR["scale"] = float(sys.argv[3]) if len(sys.argv) > 3 else 1.0
sc = bn.load_scenario(sys.argv[1])
tun = {"fix_error_states": False, "fix_noise_adaptive": False, "fix_range_bias_spacings": 0.0}
if len(sys.argv) > 4: tun.update(json.loads(sys.argv[4]))
sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tun}})
est = bn.est_base.get("ekf-depth")
rows = []
for k in [int(s) for s in sys.argv[2].split(",")]:
    import os
    r = bn.run_blocks(sc, est, k, os.environ.get("SERIES"))
    print(f"run {k}: " + " ".join(f"{n}={v:.3g}" for n, v in r.items()), flush=True)
    rows.append(r)
print("mean " + " ".join(f"{n}={np.nanmean([r[n] for r in rows]):.3g}" for n in rows[0]))
