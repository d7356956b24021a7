"""Why is ekf-depth over-confident in the inertia ratios under a three-axis tumble? (issue 18)

Per-block NEES/dof (as ``block_nees.py``) of ekf-depth on a scenario's runs, in one of modes:

* ``synthetic``: the front end's rectangle fixes replaced by the truth plus white noise drawn
  from the filter's own fix model (``fixes.fix_noise``), its variance times ``--noise-scale``
  (the filter's R scaled alike through the tuning): is the filter consistent on fixes whose
  errors are exactly what it assumes?
* ``walk``: an inertia-ratio random walk of ``--q-inertia`` per s added to the prediction.

Usage::

    python benchmarks/yu2019_inertia_diagnostics.py SCENARIO synthetic --seeds 0,1,2
        --noise-scale 0.01 [--tuning '{"fix_error_states": false, ...}']
    python benchmarks/yu2019_inertia_diagnostics.py SCENARIO walk --q-inertia 1e-7

Last line: ``block_nees <block>=<mean over runs> ... all=<mean>``. Monkeypatches the filter's
private steps for the diagnosis; not a supported way to run ekf-depth.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import warnings

import numpy as np

import tumblenav.estimators.yu2019.filter as FL
from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.yu2019.fixes import fix_noise
from tumblenav.estimators.yu2019.model import _E_INERTIA
from tumblenav.evaluation.alignment import align
from tumblenav.scenario import load_scenario
from tumblenav.simulation import model_pose_in_rig, run_streams, simulate


def synthetic_fixes(truth, noise_scale: float, rng: np.random.Generator):
    """A replacement for ``DepthSteps._fixes``: each recognised rectangle's pose replaced by
    the truth's (in the symmetric frame the fix chose) plus white noise from its model."""
    R_CM, p_MinC = model_pose_in_rig(truth)
    orig = FL.DepthSteps._fixes

    def fixes(self, k, x):
        out = []
        for fx in orig(self, k, x):
            G = min(self.symmetries, key=lambda G: np.linalg.norm(R_CM[k] @ G - fx.R_SM))
            R_SM = R_CM[k] @ G
            rect = next(r for r in self.model.rectangles if r.name == fx.rectangle)
            fxt = dataclasses.replace(fx, R_SM=R_SM, p_MinS=p_MinC[k])
            view = p_MinC[k] + R_SM @ rect.centre_M
            nz = fix_noise(fxt, self.sigma, 0.03, (0.0,) * 6, 7.0, rect.centre_M, view)
            e = np.sqrt(noise_scale) * np.linalg.cholesky(nz.cov()) @ rng.normal(size=6)
            R_meas = R_SM @ rot.exp_map(-(fx.R_MP @ e[:3]))
            p = p_MinC[k] + (R_SM @ fx.R_MP) @ e[3:]
            out.append(dataclasses.replace(fx, R_SM=R_meas, p_MinS=p, candidates=((R_meas, p),)))
        return out

    return fixes


def inertia_walk(q: float):
    orig = FL._propagate
    i = np.arange(_E_INERTIA.start, _E_INERTIA.stop)

    def propagate(x, P, dt, *a, **kw):
        x, P = orig(x, P, dt, *a, **kw)
        P = P.copy()
        P[i, i] += q * abs(dt)
        return x, P

    return propagate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("mode", choices=["synthetic", "walk"])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--noise-scale", type=float, default=1.0)
    ap.add_argument("--q-inertia", type=float, default=1e-7)
    ap.add_argument("--tuning", default="{}", help="JSON updating estimator.tuning")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    sc = load_scenario(args.scenario)
    tuning = {**(sc.estimator.tuning or {}), **json.loads(args.tuning)}
    if args.mode == "synthetic" and args.noise_scale != 1.0:
        for key in ("attitude_noise_scale", "position_noise_scale"):
            tuning[key] = tuning.get(key, 1.0) * args.noise_scale
    sc = sc.with_updates(**{"estimator.tuning": tuning})
    est = est_base.get("ekf-depth")
    rows = []
    for k in [int(s) for s in args.seeds.split(",")]:
        ss = run_seed(sc.montecarlo.seed, k)
        truth, meas = simulate(sc, ss)
        saved = FL.DepthSteps._fixes, FL._propagate
        try:
            if args.mode == "synthetic":
                rng = np.random.default_rng(1000 + k)
                FL.DepthSteps._fixes = synthetic_fixes(truth, args.noise_scale, rng)
            else:
                FL._propagate = inertia_walk(args.q_inertia)
            h = est.run(context_from_scenario(sc), meas, run_streams(ss)["estimator"])
        finally:
            FL.DepthSteps._fixes, FL._propagate = saved
        dx = h.layout.boxminus(align(truth, h).x, h.x)
        t = h.t
        w0 = sc.window_s[0] if sc.window_s else 0.75 * t[-1]
        sel = np.flatnonzero((t >= w0) & np.all(np.isfinite(dx), axis=1))
        E = np.arange(h.layout.dim)
        row = {}
        for name, ix in [(b.name, E[h.layout.err(b.name)]) for b in h.layout.blocks] + [("all", E)]:
            v = [
                dx[i, ix] @ np.linalg.solve(h.P[i][np.ix_(ix, ix)], dx[i, ix]) / len(ix)
                for i in sel
            ]
            row[name] = float(np.mean(v))
        print(f"run {k}: " + " ".join(f"{n}={v:.3g}" for n, v in row.items()), flush=True)
        rows.append(row)
    print("block_nees " + " ".join(f"{n}={np.mean([r[n] for r in rows]):.3g}" for n in rows[0]))


if __name__ == "__main__":
    main()
