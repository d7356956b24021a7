"""Why chang2021_close's NIS sits below its bounds on images (nineteenth session, issue 18):
the parts of each update's per-feature innovation covariance, on tracks cached by
chang_far_tracks.py, and two variants that were tried and not kept.

For each run: ekf-pose (the default tuning, the tracks stating ``TNOISE`` px after their first
sighting) with a copy of slam.py whose update records, in the window 40-120 s, each feature's
innovation, its S block, its R block and its age; prints the per-feature NIS/3 (all, and by
the track's age in sightings), the share gated out, and for tracks seen 30 times or more the
median of diag(S) / diag(R) in the left camera's axes (x, y = the optical axis, z). Then the
window's NEES/dof, NIS and attitude RMSE. ``STUDENT=nu`` divides each feature's R by the
Student-t weight (nu + 3) / (nu + d^2) before the gate (one iteration; ``CAP=1``: the weight at
most 1, inflation only). Also, per run, the tracked sightings' error change since the first
sighting against their rigid points' image displacement since it (pooled slopes per camera
and axis: a lag of the tracks behind the motion would be negative).

Usage::

    TUMBLENAV_SCENARIO=chang2021_close python chang_nis_parts.py CACHE_DIR SEEDS [TNOISE]

CACHE_DIR as chang_far_tracks.py writes it (run it first with the same scenario).
"""

import dataclasses
import importlib.util
import os
import pickle
import sys
from pathlib import Path

import numpy as np

import tumblenav.estimators.chang2021.slam as slam_mod

cache_dir, seeds = Path(sys.argv[1]), [int(x) for x in sys.argv[2].split(",")]
tnoise = float(sys.argv[3]) if len(sys.argv) > 3 else 0.06

# a copy of slam.py with a hook in the update (after the per-feature gate)
src = Path(slam_mod.__file__).read_text()
anchor = "            ok = d2 <= chi2.ppf(tun.feature_gate_probability, 3)\n"
assert anchor in src, "slam.py's update changed: move the hook"
hook = anchor + (
    "            if _NU:\n"
    "                w = (_NU + 3.0) / (_NU + d2)\n"
    "                w = np.minimum(w, 1.0) if _CAP else w\n"
    "                Sig = Sig / w[:, None, None]\n"
    "                S_blk = S_all[rows[:, :, None], rows[:, None, :]] + Sig\n"
    "                d2 = np.einsum('mi,mij,mj->m', nu, np.linalg.inv(S_blk), nu)\n"
    "                ok = d2 <= chi2.ppf(tun.feature_gate_probability, 3)\n"
    "            if self.meas.t[k] >= 40.0:\n"
    "                DIAG.append((nu, S_blk, Sig, rot.quat_to_matrix(self.meas.q_CL[k]), ok,"
    " self.age[k, ids]))\n"
)
src = src.replace(anchor, hook, 1)
src = src.replace(
    "Array = NDArray[np.float64]\n",
    "Array = NDArray[np.float64]\nDIAG: list = []\n"
    f"_NU = float({os.environ.get('STUDENT', '0')!r})\n_CAP = {bool(os.environ.get('CAP'))}\n",
    1,
)
spec = importlib.util.spec_from_loader("tumblenav.estimators.chang2021.slam_parts", loader=None)
diag = importlib.util.module_from_spec(spec)
sys.modules[spec.name] = diag
exec(compile(src, "slam_parts", "exec"), diag.__dict__)
slam_mod.StateSteps.update = diag.StateSteps.update

# chang_far_tracks.py's helpers (everything before its run loop), with its arguments
sys.argv = [sys.argv[0], str(cache_dir), "0", "none"]
far = Path(__file__).with_name("chang_far_tracks.py").read_text()
exec(compile(far[: far.index("with threadpool_limits")], "chang_far_tracks", "exec"))

for k in seeds:
    truth, tracks, P = pickle.load(open(cache_dir / f"run{k}.pkl", "rb"))
    tr = dataclasses.replace(tracks, track_noise_px=tnoise)
    diag.DIAG.clear()
    h = est.run(  # noqa: F821 (chang_far_tracks.py's)
        context_from_scenario(sc),  # noqa: F821
        tr,
        run_streams(run_seed(sc.montecarlo.seed, k))["estimator"],  # noqa: F821
    )
    d2_all, dof, gated, n_all, by_age, ratios = 0.0, 0, 0, 0, {}, []
    for nu, S, Sig, R, ok, age in diag.DIAG:
        d2 = np.einsum("mi,mij,mj->m", nu[ok], np.linalg.inv(S[ok]), nu[ok])
        d2_all, dof = d2_all + d2.sum(), dof + 3 * int(ok.sum())
        gated, n_all = gated + int((~ok).sum()), n_all + len(ok)
        for a, v in zip(age[ok], d2, strict=True):
            by_age.setdefault(min(int(a), 30) // 5, []).append(v / 3)
        o = ok & (age >= 30)
        if o.any():
            dS = np.einsum("mii->mi", np.einsum("ij,mjk,lk->mil", R, S[o], R))
            dR = np.einsum("mii->mi", np.einsum("ij,mjk,lk->mil", R, Sig[o], R))
            ratios.append(dS / dR)
    out = nees(truth, h)  # noqa: F821
    print(
        f"run {k} tracked noise {tnoise} px: per-feature NIS/3 {d2_all / dof:.3f}, gated "
        f"{gated / n_all:.1%}; by age (sightings) "
        + " ".join(f"{b * 5}+: {np.mean(v):.2f}" for b, v in sorted(by_age.items()))
        + "; tracks seen 30+ times, median diag(S)/diag(R) (x, y, z of the left camera) "
        f"{np.median(np.concatenate(ratios), axis=0).round(2)}",
        flush=True,
    )
    print(
        f"   window: NEES/dof {out['all']:.3g}, NIS {out['NIS']:.3g}, attitude "
        f"{out['att_deg']:.3g} deg",
        flush=True,
    )
    # a lag of the tracks behind the motion: error change since the first sighting against the
    # rigid point's image displacement since then
    obs = tracks.observed
    pr = projections(truth, tracks, P)  # noqa: F821
    first = np.argmax(obs[:, 0], 0)
    idx = np.arange(obs.shape[2])
    e0 = (tracks.uv[first, :, idx] - pr[first, :, idx]).transpose(1, 0, 2)[None]  # (1, 2, N, 2)
    d0 = pr[first, :, idx].transpose(1, 0, 2)[None]
    e, d = tracks.uv - pr - e0, pr - d0
    later = obs & (np.cumsum(obs[:, 0], 0) > 1)[:, None, :]
    slopes = []
    for c in (0, 1):
        for a in (0, 1):
            m = later[:, c] & np.isfinite(e[:, c, :, a]) & (np.abs(e[:, c, :, a]) < 2.0)
            x, y = d[:, c, :, a][m], e[:, c, :, a][m]
            slopes.append(float(np.sum(x * y) / np.sum(x * x)))
    print(
        "   error change / displacement since the first sighting, pooled (Lu Lv Ru Rv): "
        + " ".join(f"{v:+.4f}" for v in slopes),
        flush=True,
    )
