"""Why chang2021_close's NIS sits below its bounds, and what a slide model in the state does to
it (fifteenth session, issue 18). Two steps:

1. Cache the rendered runs' image tracks (render + front end, ~47 s a run)::

       python chang_image_nis.py cache CACHE_DIR 0,1,2,3

2. Run ekf-pose on the cached tracks with a copy of slam.py as of 713e9e8 (the
   patches are against it: the later update forms H P from 3-row feature blocks) patched,
   and a tuning::

       git show 713e9e8:src/tumblenav/estimators/chang2021/slam.py > /tmp/slam_diag.py
       patch /tmp/slam_diag.py chang_innovation_hook.patch      # the innovations recorded
       python chang_image_nis.py run CACHE_DIR 0,1 '{}' /tmp/slam_diag.py

       git show 713e9e8:src/tumblenav/estimators/chang2021/slam.py > /tmp/slam_rate.py
       patch /tmp/slam_rate.py chang_slide_rate.patch           # + a slide-rate state per track
       SLIDE_RATE_PX=0.02 SLIDE_RATE_Q=0.00002 WALK_SCALE=0.3 DEPTH_FLOOR=3 \
           python chang_image_nis.py run CACHE_DIR 0,1 '{"measurement_noise_scale": 0.09}' /tmp/slam_rate.py

   slam_rate.py's knobs (environment): SLIDE_RATE_PX the prior 1-sigma of each track's slide
   rate (px per frame, across the left camera's line of sight; DEPTH_FLOOR times that variance
   along it), SLIDE_RATE_Q the rate's random walk (px^2 per frame^3), WALK_SCALE the factor on
   the map walk (slam.StateSteps.map_walk).

Prints per run the NEES/dof of each block over the window 40-120 s, the NIS/dof, attitude and
position RMSE, and per left-camera axis (x, depth, z) the innovations' mean square over the
filter's predicted variance (``nis_xyz``) and the stated noise's share of that variance
(``Rshare``); the last line is the mean over the runs.
"""

import importlib.util
import json
import os
import pickle
import sys
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

import tumblenav.estimators.chang2021 as c21
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate

mode, cache, seeds = sys.argv[1], Path(sys.argv[2]), [int(s) for s in sys.argv[3].split(",")]
# TUMBLENAV_SCENARIO names another scenario, FRONTEND (JSON) the front end's tuning for `cache` (eighteenth session: the built-in chang2021 at 59 m)
sc = load_scenario(os.environ.get("TUMBLENAV_SCENARIO", "chang2021_close"))
est = est_base.get("ekf-pose")
if mode == "cache":
    cache.mkdir(parents=True, exist_ok=True)
    with threadpool_limits(limits=1, user_api="blas"):
        for k in seeds:
            truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
            fe = {**(sc.sensor.images.frontend or {}), **json.loads(os.environ.get("FRONTEND", "{}"))}
            tracks, _ = stages.prepare(meas, tuple(est.consumes), fe)
            pickle.dump((truth, tracks), open(cache / f"run{k}.pkl", "wb"))
            print("cached run", k, flush=True)
    sys.exit(0)
tuning = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
REC: list = []
if len(sys.argv) > 5:  # the patched copy of slam.py replaces the estimator's StateSteps
    spec = importlib.util.spec_from_file_location("slam_copy", sys.argv[5])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["slam_copy"] = mod
    spec.loader.exec_module(mod)
    mod._REC = REC
    c21.StateSteps = mod.StateSteps
if tuning:
    sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tuning}})
rows = []
with threadpool_limits(limits=1, user_api="blas"):
    for k in seeds:
        truth, tracks = pickle.load(open(cache / f"run{k}.pkl", "rb"))
        REC.clear()
        h = est.run(
            context_from_scenario(sc),
            tracks,
            run_streams(run_seed(sc.montecarlo.seed, k))["estimator"],
        )
        dx = h.layout.boxminus(align(truth, h).x, h.x)
        t = h.t
        w0, w1 = sc.window_s
        fin = np.array([h.P[i] is not None and np.all(np.isfinite(h.P[i])) for i in range(len(t))])
        sel = np.flatnonzero((t >= w0) & (t <= w1) & np.all(np.isfinite(dx), axis=1) & fin)
        E = np.arange(h.layout.dim)
        blocks = [(b.name, E[h.layout.err(b.name)]) for b in h.layout.blocks] + [("all", E)]
        out = {
            n: float(
                np.mean(
                    [
                        dx[i, ix] @ np.linalg.solve(h.P[i][np.ix_(ix, ix)], dx[i, ix]) / len(ix)
                        for i in sel
                    ]
                )
            )
            for n, ix in blocks
        }
        nw = (t >= w0) & (t <= w1) & (h.nis_dof > 0) & np.isfinite(h.nis)
        out["NIS"] = float(h.nis[nw].sum() / h.nis_dof[nw].sum())
        out["att_deg"] = float(np.degrees(np.sqrt(np.mean(dx[sel][:, 0:3] ** 2))))
        out["pos_mm"] = float(1e3 * np.sqrt(np.mean(dx[sel][:, 6:9] ** 2)))
        extra = ""
        if REC:  # per left-camera axis: innovation^2 over its predicted variance, R's share
            num, den, rr = np.zeros(3), np.zeros(3), np.zeros(3)
            for kk, nu, S, Sig, ok, R_CL in REC:
                if t[kk] < w0:
                    continue
                M = tracks.rig.left.R_CkC @ R_CL  # L -> left camera
                num += ((nu[ok] @ M.T) ** 2).sum(0)
                den += np.einsum("ij,mjk,ik->i", M, S[ok], M)
                rr += np.einsum("ij,mjk,ik->i", M, Sig[ok], M)
            extra = f" nis_xyz={np.round(num / den, 3)} Rshare={np.round(rr / den, 2)}"
        print(f"run {k}: " + " ".join(f"{n}={v:.3g}" for n, v in out.items()) + extra, flush=True)
        rows.append(out)
print("chang_image_nis " + " ".join(f"{n}={np.mean([r[n] for r in rows]):.3g}" for n in rows[0]))
