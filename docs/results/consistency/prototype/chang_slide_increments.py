"""The image tracks' error against their first sighting, by age, and frame to frame (fifteenth
session, issue 18), on runs cached by ``chang_image_nis.py cache CACHE_DIR SEEDS``: as
benchmarks/image_track_slide.py (each track's first run of sightings triangulated, taken into T
with the truth's pose, against its first sighting, in px of the left camera at the point's
depth: x, z across the line of sight, depth in the same pixel-equivalent), with the robust
sigma (1.4826 MAD) and the RMS at each age, and the frame-to-frame increments after age 1.

Usage: python chang_slide_increments.py CACHE_DIR 0,1
"""

import pickle
import sys
from pathlib import Path

import numpy as np

from tumblenav import rotations as rot
from tumblenav.estimators.chang2021.measurements import feature_tracks

AGES = (1, 2, 3, 5, 10, 20, 30, 45, 58)
acc: dict[int, list] = {a: [] for a in AGES}
inc = []
for k in [int(s) for s in sys.argv[2].split(",")]:
    truth, tracks = pickle.load(open(Path(sys.argv[1]) / f"run{k}.pkl", "rb"))
    tr = feature_tracks(tracks)
    left = tracks.rig.left
    f, R0, o0 = left.focal_px, left.R_CkC, left.p_CkinC
    p_T = np.einsum("nji,nmj->nmi", truth.R_LT, tr.p - truth.r_L[:, None, :])
    for j in range(tr.ok_p.shape[1]):
        ks = np.flatnonzero(tr.ok_p[:, j])
        if len(ks) < 2:
            continue
        gaps = np.flatnonzero(np.diff(ks) > 1)
        ks = ks[: gaps[0] + 1] if len(gaps) else ks
        dd = []
        for a, kk in enumerate(ks):
            R_CL = rot.quat_to_matrix(tracks.q_CL[kk])
            d0 = R0 @ (R_CL @ (truth.R_LT[kk] @ (p_T[kk, j] - p_T[ks[0], j])))
            depth = R0[1] @ (R_CL @ tr.p[kk, j] - o0)
            dd.append(np.array([d0[0], d0[2], d0[1]]) * f / depth)
            if a in acc:
                acc[a].append(dd[-1])
        if len(dd) > 3:
            inc.append(np.diff(np.array(dd[1:]), axis=0))


def robust(d):
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)


for a in AGES:
    d = np.array(acc[a])
    print(
        f"age {a:2d} ({len(d):5d}): robust sigma x z depth {np.round(robust(d), 3)} px, RMS {np.round(np.sqrt(np.mean(d**2, 0)), 3)}"
    )
d = np.concatenate(inc)
print(
    f"frame to frame after age 1: robust sigma {np.round(robust(d), 3)} px, RMS {np.round(np.sqrt(np.mean(d**2, 0)), 3)}"
)
