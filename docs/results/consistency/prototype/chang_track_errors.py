"""The image tracks' errors against the renderer's surface points (sixteenth session, issue 18).

For run K of chang2021_close (rendered, the campaign's seeds) every track's sightings are
triangulated as the front end does and compared with the renderer's hit point under the
track's first left corner (``simulation.with_track_truth``), in the left camera: px across
the line of sight (x, z) and px-equivalent along it (depth), at the point's depth. Printed, over
the tracks seen ten times or more: the robust sigma (1.4826 MAD) and RMS of each track's mean
error (what persists over a track's life) and of the sightings' scatter about it, and of the
frame-to-frame increments::

    python chang_track_errors.py K          # the front end as shipped
    python chang_track_errors.py K --lk     # LK and the NCC match alone (no affine refinement)
"""

import json
import os
import sys

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators.chang2021.measurements import feature_tracks
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, with_track_truth

k = int(sys.argv[1])
# TUMBLENAV_SCENARIO another scenario, FRONTEND (JSON) front-end tuning (eighteenth session)
sc = load_scenario(os.environ.get("TUMBLENAV_SCENARIO", "chang2021_close"))
fe = {**(sc.sensor.images.frontend or {}), **json.loads(os.environ.get("FRONTEND", "{}"))}
if "--lk" in sys.argv:
    fe = {**(fe or {}), "template_refine": False, "affine_match_refine": False}
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
tracks, _ = stages.prepare(meas, ("stereo_tracks",), fe)
sT = with_track_truth(truth, meas, tracks).features_T  # (N, 3)
tr = feature_tracks(tracks)
left = tracks.rig.left
f, R0, o0 = left.focal_px, left.R_CkC, left.p_CkinC
n, N = tr.ok_p.shape
E = np.full((n, N, 3), np.nan)
for kk in range(n):
    js = np.flatnonzero(tr.ok_p[kk] & np.all(np.isfinite(sT), axis=1))
    if not len(js):
        continue
    R_CL = rot.quat_to_matrix(tracks.q_CL[kk])
    d = (tr.p[kk, js] - truth.r_L[kk] - sT[js] @ truth.R_LT[kk].T) @ R_CL.T @ R0.T
    depth = ((R_CL @ tr.p[kk, js].T).T - o0) @ R0[1]
    E[kk, js] = np.stack([d[:, 0], d[:, 2], d[:, 1]], 1) * (f / depth)[:, None]
good = np.sum(np.isfinite(E[..., 0]), 0) >= 10
M = np.nanmean(E[:, good], 0)
D = (E[:, good] - M).reshape(-1, 3)


def rob(a):
    return 1.4826 * np.nanmedian(np.abs(a - np.nanmedian(a, 0)), 0)


def rms(a):
    return np.sqrt(np.nanmean(a**2, 0))


inc = np.diff(E, axis=0).reshape(-1, 3)
print(f"run {k}, {good.sum()} tracks; robust sigma / RMS, (x, z, depth) px")
print("  per-track mean", rob(M).round(3), rms(M).round(3))
print("  scatter about it", rob(D).round(3), rms(D).round(3))
print("  frame to frame", rob(inc).round(3))
# the error's change from each track's first sightings, by age (what a rigid map point cannot absorb)
age = np.cumsum(np.isfinite(E[..., 0]), 0)
first = np.nanmean(np.where((age <= 3)[..., None], E, np.nan), 0)
for a in (5, 10, 20, 40, 60):
    sel = (age == a) & good[None, :] if False else (age == a)
    dd = E[sel] - np.broadcast_to(first, E.shape)[sel]
    dd = dd[np.all(np.isfinite(dd), 1)]
    if len(dd):
        print(f"  change since the first sightings at age {a}: n={len(dd)} robust", rob(dd).round(3),
              "median", np.median(dd, 0).round(3))
