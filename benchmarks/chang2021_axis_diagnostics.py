"""Where is ekf-pose's mass centre over-confident? Its error along and across the rotation axis.

The mass centre's shift along the target's rotation axis is observable only through the
axis's own motion in the body (nutation): features that rotate about a fixed axis fit any
centre on it. For each run (the seeds of ``tumblenav montecarlo``) this prints, every ~2 s,
the position error along the estimated rotation axis (in L) with its 1-sigma, the error across
it with its 1-sigma, and the angle between the estimated and the true rate; then the mean
NEES along (1 dof) and across (2 dof) over the scenario's window, and the mean error along
the line of sight with its NEES (a common depth bias shows there). On a spherical target (no
nutation; docs/results/scenarios/consistency/chang_range20_sphere.yaml) the shift along the
axis is unobservable and a consistent filter keeps its sigma.

Usage::

    python benchmarks/chang2021_axis_diagnostics.py SCENARIO [--seeds 0,1] [--tuning JSON]
        [--until SECONDS] [--quiet]

Last line: ``chang2021_axis along=<mean NEES> across=<mean NEES/dof>``.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from threadpoolctl import threadpool_limits

from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate


def run_axis(sc, k: int, until: float, quiet: bool) -> tuple[float, float, float, float]:
    est = est_base.get("ekf-pose")
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    images = getattr(sc.sensor, "images", None)
    tracks, _ = stages.prepare(meas, est.consumes, images.frontend if images else None)
    h = est.run(
        context_from_scenario(sc), tracks, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"]
    )
    tr = align(truth, h)
    dx = h.layout.boxminus(tr.x, h.x)
    t = h.t
    w0, w1 = sc.window_s if sc.window_s else (0.75 * t[-1], t[-1])
    step = max(1, int(round(2.0 / float(np.median(np.diff(t))))))
    along, across, los, nlos = [], [], [], []
    for i in range(len(t)):
        if h.P[i] is None or not np.all(np.isfinite(h.x[i])) or not np.all(np.isfinite(dx[i])):
            continue
        w = h.x[i, 4:7]
        u = rot.quat_to_matrix(h.x[i, 0:4]).T @ (w / np.linalg.norm(w))  # the axis in L
        e, P = dx[i, 6:9], h.P[i][6:9, 6:9]
        B = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]  # across the axis
        ea, sa2 = float(e @ u), float(u @ P @ u)
        ep, Pp = B.T @ e, B.T @ P @ B
        if w0 <= t[i] <= w1:
            along.append(ea**2 / sa2)
            across.append(float(ep @ np.linalg.solve(Pp, ep)) / 2)
            # along the line of sight (the chaser at L's origin): estimate minus truth
            ul = h.x[i, 7:10] / np.linalg.norm(h.x[i, 7:10])
            los.append(-float(e @ ul))
            nlos.append(float(e @ ul) ** 2 / float(ul @ P @ ul))
        if not quiet and t[i] <= until and i % step == 0:
            wt = tr.x[i, 4:7]
            c = float(w @ wt / np.linalg.norm(w) / np.linalg.norm(wt))
            ang = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
            print(
                f"  t={t[i]:6.1f} along {ea * 1e3:8.1f} +- {np.sqrt(sa2) * 1e3:6.1f} mm  across "
                f"{np.round(ep * 1e3, 1)} +- {np.round(np.sqrt(np.diag(Pp)) * 1e3, 1)} mm  "
                f"rate direction off {ang:5.2f} deg"
            )
    return float(np.mean(along)), float(np.mean(across)), float(np.mean(los)), float(np.mean(nlos))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", help="a built-in name or a YAML path (estimator ekf-pose)")
    ap.add_argument("--seeds", default="0", help="run numbers, comma-separated")
    ap.add_argument("--tuning", default="{}", help="JSON updating estimator.tuning")
    ap.add_argument("--until", type=float, default=100.0, help="print the series up to here (s)")
    ap.add_argument("--quiet", action="store_true", help="only the per-run means")
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    tuning = json.loads(args.tuning)
    if tuning:
        sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tuning}})
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        for k in [int(s) for s in args.seeds.split(",")]:
            a, c, los, nlos = run_axis(sc, k, args.until, args.quiet)
            print(
                f"run {k}: NEES along the axis {a:.3g}, across (per dof) {c:.3g}; along the "
                f"line of sight: mean error {los * 1e3:.3g} mm (estimate - truth), NEES {nlos:.3g}",
                flush=True,
            )
            rows.append((a, c))
    m = np.mean(rows, axis=0)
    print(f"chang2021_axis along={m[0]:.3g} across={m[1]:.3g}")


if __name__ == "__main__":
    main()
