"""How fast do the image front end's tracks slide over the surface? The number behind
``sensor.images.frontend.track_slide_px2_per_frame`` (the tracks' ``slide_px2_per_frame``).

For each run (the seeds of ``tumblenav montecarlo``: run k of base seed ``--base-seed``) the
scenario is simulated with its rendered images and the image front end tracks them. Each
track's first run of consecutive sightings is triangulated, taken into the target frame T with
the truth's pose, and compared with its first sighting: the difference, at the track's age a,
is expressed in pixels of the left camera at the point's depth, along the camera's x and z
(across the line of sight) and along its optical axis (depth, in the same pixel-equivalent).
Printed per age: the robust sigma (1.4826 MAD) of each. The slide as a random walk is the
growth of the lateral variance over a track's first ``--lag`` frames, averaged over x and z:
``(sigma^2(1 + lag) - sigma^2(1)) / lag``.

Usage::

    python benchmarks/image_track_slide.py [SCENARIO] [--runs 2] [--lag 9]

Last line: ``image_track_slide px2_per_frame=<the walk> x=<x axis> z=<z axis>``.
"""

from __future__ import annotations

import argparse

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators.chang2021.measurements import feature_tracks
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

AGES = (1, 2, 5, 10, 20, 30, 45, 58)


def slides(sc, k: int, ages: tuple[int, ...]) -> dict[int, list]:
    """Per age: the (x, z, depth) differences (px) of run ``k``'s tracks against their first
    sighting."""
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tracks, _ = stages.prepare(meas, ("stereo_tracks",), sc.sensor.images.frontend)
    tr = feature_tracks(tracks)
    left = tracks.rig.left
    f, R0, o0 = left.focal_px, left.R_CkC, left.p_CkinC
    p_T = np.einsum("nji,nmj->nmi", truth.R_LT, tr.p - truth.r_L[:, None, :])  # R_TL (p - r)
    out: dict[int, list] = {a: [] for a in ages}
    for j in range(tr.ok_p.shape[1]):
        ks = np.flatnonzero(tr.ok_p[:, j])
        if len(ks) < 2:
            continue
        gaps = np.flatnonzero(np.diff(ks) > 1)
        ks = ks[: gaps[0] + 1] if len(gaps) else ks  # the first run of sightings
        for a in ages:
            if a < len(ks):
                kk = ks[a]
                R_CL = rot.quat_to_matrix(tracks.q_CL[kk])
                d_C = R_CL @ (truth.R_LT[kk] @ (p_T[kk, j] - p_T[ks[0], j]))
                d0 = R0 @ d_C  # in the left camera
                depth = R0[1] @ (R_CL @ tr.p[kk, j] - o0)
                out[a].append(np.array([d0[0], d0[2], d0[1]]) * f / depth)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="chang2021_close")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--lag", type=int, default=9, help="frames after age 1 for the walk")
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    if getattr(sc.sensor, "images", None) is None:
        raise SystemExit(f"{args.scenario} has no sensor.images: nothing to track")
    ages = tuple(sorted(set(AGES) | {1, 1 + args.lag}))
    acc: dict[int, list] = {a: [] for a in ages}
    for k in range(args.runs):
        for a, v in slides(sc, k, ages).items():
            acc[a] += v
    sig = {}
    for a in ages:
        d = np.array(acc[a])
        if len(d) < 20:
            continue
        sig[a] = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
        print(
            f"age {a:3d} ({len(d):6d} sightings): robust sigma x {sig[a][0]:.3f} z "
            f"{sig[a][1]:.3f} px, depth {sig[a][2]:.2f} px-equivalent"
        )
    a1 = 1 + args.lag
    q = (sig[a1] ** 2 - sig[1] ** 2) / args.lag
    print(f"image_track_slide px2_per_frame={np.mean(q[:2]):.4f} x={q[0]:.4f} z={q[1]:.4f}")


if __name__ == "__main__":
    main()
