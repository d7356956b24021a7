"""Which part of the tracked sightings' error makes ekf-pose over-confident at 59 m on
images? (twenty-first session, issue 18)

On tracks cached by chang_far_tracks.py (same CACHE layout, same TUMBLENAV_SCENARIO, UPDATES,
FRONTEND, TUNING environment): each track's residuals about its best rigid point under the
TRUE poses are split and recombined, the first sightings kept as the front end gave them, and
ekf-pose is run on the result. Modes (the tracked sightings, i.e. all but each track's first):

* ``real``: as the front end gave them;
* ``flip``: each track's residuals times a random sign (the same in both cameras and over the
  track): the same magnitudes and correlation in time, but no common direction across tracks;
* ``shuffle``: the tracked residuals permuted over all tracked sightings (white in time);
* ``mean``: each track's tracked residuals replaced by their mean over the track (a constant
  offset per track, which the map can absorb);
* ``detrend``: each track's tracked residuals less that mean (the part that moves);
* ``across`` / ``along``: each track's residuals without their component along the major /
  minor direction of the track's own left residual scatter (non-causal; applied in both
  cameras).

Usage::

    python chang_far_decompose.py CACHE SEEDS MODES     # MODES e.g. real,flip,shuffle,mean,detrend

Prints NEES/dof per block over the scenario's window, NIS, the attitude and position RMSE and
the inertia's principal ratios at the end (chang2021's truth: 1 / 0.833 / 0.667).
"""

import dataclasses
import pickle
import sys
from pathlib import Path

import numpy as np

_proto = Path(__file__).with_name("chang_far_tracks.py").read_text()
_argv, sys.argv = sys.argv, [sys.argv[0], sys.argv[1], sys.argv[2], "none"]
exec(_proto.split("with threadpool_limits")[0])  # the shared helpers, without the main loop
sys.argv = _argv
modes = sys.argv[3].split(",")

for k in [int(a) for a in sys.argv[2].split(",")]:
    path = cache / f"run{k}.pkl"
    if not path.exists():
        sys.exit(f"{path} missing: cache it first with chang_far_tracks.py {cache} {k} none")
    truth, tracks, P = pickle.load(open(path, "rb"))
    obs = tracks.observed
    pr = projections(truth, tracks, P)
    res = np.where(obs[..., None], tracks.uv - pr, np.nan)  # (n, 2, N, 2)
    age = np.cumsum(obs[:, 0], 0)
    first = (age == 1)[:, None, :, None]
    tracked = obs[:, 0] & (age > 1)  # (n, N)
    N = obs.shape[2]
    rng = np.random.default_rng(100 + k)
    mu = np.nanmean(np.where(tracked[:, None, :, None], res, np.nan), 0, keepdims=True)
    for mode in modes:
        if mode == "flip":
            r2 = res * rng.choice([-1.0, 1.0], N)[None, None, :, None]
        elif mode == "shuffle":
            r2 = res.copy()
            idx = np.argwhere(tracked)
            src = idx[rng.permutation(len(idx))]
            r2[idx[:, 0], :, idx[:, 1]] = res[src[:, 0], :, src[:, 1]]
        elif mode == "mean":
            r2 = np.where(tracked[:, None, :, None], np.broadcast_to(mu, res.shape), res)
        elif mode == "detrend":
            r2 = np.where(tracked[:, None, :, None], res - mu, res)
        elif mode in ("across", "along"):
            r2 = res.copy()
            for i in np.flatnonzero(tracked.sum(0) >= 3):
                e = res[tracked[:, i], 0, i]
                e = e[np.all(np.isfinite(e), 1)]
                if len(e) < 3:
                    continue
                _, V = np.linalg.eigh(np.cov((e - e.mean(0)).T))
                v = V[:, 1] if mode == "across" else V[:, 0]  # the direction removed
                for c in (0, 1):
                    x = res[tracked[:, i], c, i]
                    r2[tracked[:, i], c, i] = x - np.outer(x @ v, v)
        elif mode == "real":
            r2 = res
        else:
            sys.exit(f"unknown mode {mode}")
        with np.errstate(invalid="ignore"):
            uv = np.where(first, tracks.uv, pr + np.nan_to_num(r2))
        tr = dataclasses.replace(tracks, uv=np.where(obs[..., None], uv, np.nan))
        h = est.run(
            context_from_scenario(sc), tr, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"]
        )
        out = nees(truth, h)
        ratios = np.round(h.info.get("inertia_principal_ratios", [np.nan] * 3), 3)
        print(
            f"run {k} {mode}: " + " ".join(f"{a}={v:.3g}" for a, v in out.items())
            + f" inertia_ratios={ratios.tolist()}",
            flush=True,
        )
