"""Why ekf-pose is over-confident on the built-in chang2021 (59 m) on images: the tracks' error
structure or the filter? (eighteenth session, issue 18)

For each run: render and track (cached under CACHE_DIR), fit every track's best rigid point in
T with the TRUE poses (Gauss-Newton on its pixels in both cameras; the tracks seen 10 times or
more are summarised), print the residuals' structure -- robust sigma, the common mode (the median
residual over the tracks of an epoch: its std over the epochs against what white noise would
give) and the lag-1 autocorrelations -- and run ekf-pose on variants of the same tracks (same
IDs, same sightings):

* ``real``: the front end's tracks;
* ``ideal``: the rigid points' true projections + white noise at the tracks' stated sigmas
  (``noise_px`` at a first sighting, ``track_noise_px`` after);
* ``common``: ``ideal`` + the real residuals' common mode of each epoch (their median over the
  epoch's tracks, the same for every track of the epoch);
* ``pertrack``: the rigid points' projections + the real residuals minus their common mode;
* ``noslip``: the front end's tracks without those with a residual beyond 5 robust sigmas;
* ``minlenN``: the front end's tracks without those shorter than N frames;
* ``nosilhouette`` (with CLASSES=1, which prints each track's class at its first sighting from
  the truth render's depth map): without the tracks whose first neighbourhood shows the
  background;
* ``tnoise=X``: the front end's tracks stating X px for a tracked sighting (``noslip+tnoise=X``
  both); ``slide=X``: stating a slide of X px^2 per frame (``real+slide=X``, ``tnoise=Y+slide=X``);
  ``fnoise=X``: stating X px for a first sighting (``tnoise=Y+fnoise=X``);
* ``realfirst`` / ``realtracked``: the front end's pixels at each track's first sighting only /
  everywhere but there, ``ideal`` elsewhere.

Usage::

    python chang_far_tracks.py CACHE_DIR SEEDS [MODES]       # MODES default real,ideal,common,pertrack,noslip

Environment: TUMBLENAV_SCENARIO (default chang2021), TUNING (JSON, ekf-pose's), UPDATES (JSON of dotted scenario updates,
e.g. '{"sensor.images.supersample": 3}'), FRONTEND (JSON, the front end's tuning), CLASSES, EDGE_M. MODES
``none``: the structure only. The cache
directory is per (scenario, UPDATES, FRONTEND): give each its own.
"""

import dataclasses
import json
import os
import pickle
import sys
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.sensors.stereo import project
from tumblenav.simulation import run_streams, simulate

cache, seeds = Path(sys.argv[1]), [int(s) for s in sys.argv[2].split(",")]
modes = (sys.argv[3] if len(sys.argv) > 3 else "real,ideal,common,pertrack,noslip").split(",")
sc = load_scenario(os.environ.get("TUMBLENAV_SCENARIO", "chang2021"))
upd = json.loads(os.environ.get("UPDATES", "{}"))
if upd:
    sc = sc.with_updates(**upd)
fe = {**(sc.sensor.images.frontend or {}), **json.loads(os.environ.get("FRONTEND", "{}"))}
tun = json.loads(os.environ.get("TUNING", "{}"))  # ekf-pose's tuning (not part of the cache)
if tun:
    sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tun}})
est = est_base.get("ekf-pose")
cache.mkdir(parents=True, exist_ok=True)


def rob(a):
    return 1.4826 * np.nanmedian(np.abs(a - np.nanmedian(a)))


def lag1(r):
    return np.nansum(r[1:] * r[:-1]) / np.nansum(r * r)


def projections(truth, tracks, P):
    n, _, N, _ = tracks.uv.shape
    out = np.empty((n, 2, N, 2))
    for k in range(n):
        R_CL = rot.quat_to_matrix(tracks.q_CL[k])
        out[k] = project(tracks.rig, (truth.r_L[k] + P @ truth.R_LT[k].T) @ R_CL.T)[0]
    return out


def rigid_points(truth, tracks):
    """Each track's least-squares rigid point in T under the true poses (4 Gauss-Newton steps
    from the triangulated first sighting, numerical Jacobians, all tracks at once)."""
    obs = tracks.observed
    n, _, N, _ = tracks.uv.shape
    first = np.argmax(obs[:, 0], 0)
    P = np.zeros((N, 3))
    from tumblenav.estimators.chang2021.measurements import feature_tracks

    ft = feature_tracks(tracks)
    for i in range(N):  # the first sighting's triangulated point, into T
        k = first[i]
        if ft.ok_p[k, i]:
            P[i] = truth.R_LT[k].T @ (ft.p[k, i] - truth.r_L[k])
    for _ in range(4):
        r0 = projections(truth, tracks, P)
        res = np.where(obs[..., None], tracks.uv - r0, 0.0)
        J = np.empty((n, 2, N, 2, 3))
        for a in range(3):
            d = np.zeros(3)
            d[a] = 1e-4
            J[..., a] = (projections(truth, tracks, P + d) - r0) / 1e-4
        J = np.where(obs[..., None, None], J, 0.0)
        A = np.einsum("kcnai,kcnaj->nij", J, J) + 1e-9 * np.eye(3)
        b = np.einsum("kcnai,kcna->ni", J, res)
        P = P + np.linalg.solve(A, b[..., None])[..., 0]
    return P


def track_classes(k, tracks):
    """Each track's class at its first sighting, from the truth render's depth map in a 7 x 7
    px neighbourhood of its left pixel: 0 the background is in it (silhouette), 1 its depth
    spans more than EDGE_M (default 0.1 m: a depth edge), 2 neither; -1 never seen. Printed
    with the counts."""
    _, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    src = meas.source
    obs = tracks.observed[:, 0]
    first = np.argmax(obs, 0)
    cls = np.full(obs.shape[1], -1)
    edge = float(os.environ.get("EDGE_M", "0.1"))
    for kk in np.unique(first[obs.any(0)]):
        sun = src.sun_C[kk]
        out = src.renderer.render(
            src.R_CM[kk],
            src.p_MinC[kk],
            None if np.isnan(sun).any() else sun,
            np.random.default_rng(0),
            truth=True,
        )
        dep = np.asarray(out.depth_m[0])
        for i in np.flatnonzero((first == kk) & obs.any(0)):
            c, r = (int(a) for a in np.floor(tracks.uv[kk, 0, i]))
            patch = dep[max(r - 3, 0) : r + 4, max(c - 3, 0) : c + 4]
            cls[i] = 0 if np.isnan(patch).any() else 1 if np.ptp(patch) > edge else 2
    print(
        f"   track classes (silhouette / depth edge / interior): {(cls == 0).sum()} / "
        f"{(cls == 1).sum()} / {(cls == 2).sum()} of {(cls >= 0).sum()}",
        flush=True,
    )
    return cls


def nees(truth, h):
    dx = h.layout.boxminus(align(truth, h).x, h.x)
    t = h.t
    w0, w1 = sc.window_s
    fin = np.array([h.P[i] is not None and np.all(np.isfinite(h.P[i])) for i in range(len(t))])
    sel = np.flatnonzero((t >= w0) & (t <= w1) & np.all(np.isfinite(dx), axis=1) & fin)
    E = np.arange(h.layout.dim)
    blocks = [(b.name, E[h.layout.err(b.name)]) for b in h.layout.blocks] + [("all", E)]
    out = {
        n: float(
            np.mean([dx[i, ix] @ np.linalg.solve(h.P[i][np.ix_(ix, ix)], dx[i, ix]) for i in sel])
            / len(ix)
        )
        for n, ix in blocks
    }
    nw = (t >= w0) & (t <= w1) & (h.nis_dof > 0) & np.isfinite(h.nis)
    out["NIS"] = float(h.nis[nw].sum() / h.nis_dof[nw].sum())
    out["att_deg"] = float(np.degrees(np.sqrt(np.mean(dx[sel][:, 0:3] ** 2))))
    out["pos_mm"] = float(1e3 * np.sqrt(np.mean(dx[sel][:, 6:9] ** 2)))
    return out


with threadpool_limits(limits=1, user_api="blas"):
    for k in seeds:
        path = cache / f"run{k}.pkl"
        if path.exists():
            truth, tracks, P = pickle.load(open(path, "rb"))
        else:
            truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
            tracks, stats = stages.prepare(meas, tuple(est.consumes), fe)
            print(f"run {k} front end: {stats}", flush=True)  # why the tracks end
            P = rigid_points(truth, tracks)
            pickle.dump((truth, tracks, P), open(path, "wb"))
        obs = tracks.observed
        pr = projections(truth, tracks, P)
        res = np.where(obs[..., None], tracks.uv - pr, np.nan)  # (n, 2, N, 2)
        g = obs[:, 0].sum(0) >= 10
        r = res[:, :, g]
        # the epoch's common mode: the median over its tracks (the mean follows the few slipped
        # tracks' pixel-size residuals, which the filter's slip test and gate remove)
        cm = np.nanmedian(r, 2)  # (n, 2, 2)
        per_epoch = np.isfinite(r[:, 0, :, 0]).sum(1)
        sig = np.array([rob(r[:, c, :, a]) for c in (0, 1) for a in (0, 1)])
        print(
            f"run {k}: {int(g.sum())} tracks (of {obs.shape[2]}), {per_epoch.mean():.0f} an epoch; "
            f"residual robust sigma Lu Lv Ru Rv {sig.round(3)}, disparity "
            f"{rob(r[:, 0, :, 0] - r[:, 1, :, 0]):.3f} px; common mode std "
            f"{np.nanstd(cm, 0).ravel().round(3)} (white: "
            f"{(1.2533 * sig / np.sqrt(per_epoch.mean())).round(3)}), its lag-1 autocorrelation "
            f"{lag1(cm[:, 0, 0] - np.nanmean(cm[:, 0, 0])):.2f}; within a track lag-1 Lu "
            f"{lag1(r[:, 0, :, 0]):.2f}, disparity {lag1(r[:, 0, :, 0] - r[:, 1, :, 0]):.2f}",
            flush=True,
        )
        # tracks that slip: a residual beyond 5 robust sigmas (of the larger axis) anywhere
        big = np.nanmax(np.abs(np.where(obs[..., None], res, 0.0)), axis=(0, 1, 3)) > 5 * sig.max()
        rc = np.where(big[None, None, :, None], np.nan, res)[:, :, g]
        print(
            f"   tracks with a residual beyond 5 sigma: {int(big[g].sum())} of {int(g.sum())} (all "
            f"lengths {int(big.sum())} of {obs.shape[2]}); without them: robust sigma "
            f"{np.array([rob(rc[:, c, :, a]) for c in (0, 1) for a in (0, 1)]).round(3)}, RMS "
            f"{np.sqrt(np.nanmean(rc**2, axis=(0, 2))).ravel().round(3)}, within a track lag-1 Lu "
            f"{lag1(rc[:, 0, :, 0]):.2f}, disparity {lag1(rc[:, 0, :, 0] - rc[:, 1, :, 0]):.2f}",
            flush=True,
        )
        # white sightings keep the change over L frames flat in L; correlated ones grow
        sf = [rob(res[L:, 0, :, 0] - res[:-L, 0, :, 0]) for L in (1, 2, 5, 10, 20, 40)]
        print(
            "   the change's robust sd over 1 / 2 / 5 / 10 / 20 / 40 frames (left u): "
            + " / ".join(f"{v:.3f}" for v in sf),
            flush=True,
        )
        # left-right: the tracked sightings' residuals (and the white part, from the changes
        # over one frame) within 5 robust sigmas, correlated between the two images?
        age = np.cumsum(obs[:, 0], 0)
        for what, a in (("residuals", res), ("changes over one frame", res[1:] - res[:-1])):
            m = (age[1:] > 2) if a.shape[0] < res.shape[0] else (age > 1)
            X = np.stack([a[:, c, :, ax][m] for c in (0, 1) for ax in (0, 1)], 1)
            X = X[np.all(np.isfinite(X), 1)]
            X = X[np.all(np.abs(X - np.median(X, 0)) < 5 * max(rob(X[:, i]) for i in range(4)), 1)]
            C = np.cov(X.T)
            sd = np.sqrt(np.diag(C))
            print(
                f"   tracked sightings' {what} (inliers): sd Lu Lv Ru Rv {sd.round(3)}, robust "
                f"{np.array([rob(X[:, i]) for i in range(4)]).round(3)}; left-right correlation u "
                f"{C[0, 2] / sd[0] / sd[2]:+.2f}, v {C[1, 3] / sd[1] / sd[3]:+.2f}",
                flush=True,
            )
        cls = track_classes(k, tracks) if os.environ.get("CLASSES") else None
        cm_all = np.nanmedian(np.where(g[None, None, :, None], res, np.nan), 2, keepdims=True)
        cm_all = np.nan_to_num(cm_all)
        for mode in [m for m in modes if m != "none"]:
            tr = tracks
            if mode.startswith("minlen") or mode == "nosilhouette":  # tracks left out
                if mode == "nosilhouette":  # needs CLASSES=1
                    keep = cls != 0
                else:  # the tracks shorter than N frames (non-causal)
                    keep = obs[:, 0].sum(0) >= int(mode[6:])
                o2 = obs & keep[None, None, :]
                tr = dataclasses.replace(
                    tracks, observed=o2, uv=np.where(o2[..., None], tracks.uv, np.nan)
                )
                mode_done = True
            else:
                mode_done = False
            parts = [] if mode_done else mode.split("+")  # noslip+tnoise=0.05 combine
            if mode_done:
                pass
            elif parts[0] in ("noslip", "real") or parts[0].startswith(
                ("tnoise=", "slide=", "fnoise=")
            ):
                for part in parts:
                    if part.startswith("tnoise="):  # another stated tracked noise
                        tr = dataclasses.replace(tr, track_noise_px=float(part[7:]))
                    elif part.startswith("fnoise="):  # another stated first-sighting noise
                        tr = dataclasses.replace(tr, noise_px=float(part[7:]))
                    elif part.startswith("slide="):  # another stated slide, px^2 per frame
                        tr = dataclasses.replace(tr, slide_px2_per_frame=float(part[6:]))
                    elif (
                        part == "noslip"
                    ):  # the tracks that slip (above) removed, knowing the truth
                        o2 = obs & ~big[None, None, :]
                        tr = dataclasses.replace(
                            tr, observed=o2, uv=np.where(o2[..., None], tracks.uv, np.nan)
                        )
            else:
                rng = np.random.default_rng(k)
                age = np.cumsum(obs[:, 0], 0)
                s = np.where(age == 1, tracks.noise_px, tracks.track_noise_px)[:, None, :, None]
                white = rng.standard_normal(pr.shape) * s
                first = (age == 1)[:, None, :, None]
                uv = {
                    "realfirst": np.where(first, tracks.uv, pr + white),
                    "realtracked": np.where(first, pr + white, tracks.uv),
                    "ideal": pr + white,
                    "common": pr + white + cm_all,
                    "pertrack": pr + np.nan_to_num(res - cm_all),
                }[mode]
                tr = dataclasses.replace(tracks, uv=np.where(obs[..., None], uv, np.nan))
            h = est.run(
                context_from_scenario(sc),
                tr,
                run_streams(run_seed(sc.montecarlo.seed, k))["estimator"],
            )
            out = nees(truth, h)
            print(
                f"run {k} {mode}: "
                + " ".join(f"{a}={v:.3g}" for a, v in out.items())
                + f" start_fit={h.info.get('start_fit')} ratio={h.info.get('start_fit_noise_ratio')}",
                flush=True,
            )
