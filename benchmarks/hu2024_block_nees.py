"""Which part of the ekf-dpacf state is over-confident? NEES per block on hu2024 runs.

For each run (same seeds as ``tumblenav montecarlo``), the mean over the steady-state window
of the NEES per degree of freedom of the whole state and of each block (attitude, rate,
inertia ratios, position, velocity, features), and whether the run ended on the DPACF
branch turned by a half turn (attitude error > 90 deg). Prints means over all runs, over the
runs on the right branch, and medians.

Usage: python benchmarks/hu2024_block_nees.py [--runs 40] [--first 0] [--noise 2e-5]
       [--scenario hu2024] [--set key=value ...]  (estimator.tuning overrides, YAML values)
Last line: ``nees_all=<mean NEES/dof, all runs> nees_right_branch=<mean, right-branch runs>
median_run=<median per-run NEES/dof> wrong_branch=<runs> attitude_median_deg=<median RMS>``
"""

from __future__ import annotations

import argparse

import numpy as np
from _tuning import with_tuning  # noqa: I001 (benchmarks/, on sys.path when run)

from tumblenav import evaluation
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import ekf_dpacf as hu
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

BLOCKS = {
    "attitude": slice(0, 3),
    "rate": slice(3, 6),
    "inertia": slice(6, 9),
    "position": slice(9, 12),
    "velocity": slice(12, 15),
    "features": slice(15, None),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="hu2024")
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--first", type=int, default=0, help="index of the first run")
    ap.add_argument("--noise", type=float, default=2e-5, help="angular resolution (rad)")
    ap.add_argument("--batch", type=int, default=20)
    ap.add_argument("--every", type=int, default=5, help="epochs between NEES samples")
    ap.add_argument("--set", action="append", default=[], help="tuning key=value")
    args = ap.parse_args()
    sc = with_tuning(
        load_scenario(args.scenario), args.set, **{"sensor.noise.angular_rad": args.noise}
    )
    t0, t1 = sc.window_s
    rows = []
    last = args.first + args.runs
    for start in range(args.first, last, args.batch):
        ks = range(start, min(last, start + args.batch))
        sims = [simulate(sc, run_seed(sc.montecarlo.seed, k)) for k in ks]
        res = hu.run_filter(sc, [m for _, m in sims], True)
        res["x_true"], res["err"] = evaluation.error_states(
            hu.histories(res, sc), [t for t, _ in sims]
        )
        t = res["t"]
        win = np.flatnonzero((t >= t0) & (t <= t1))[:: args.every]
        for b, k in enumerate(ks):
            e, P = res["err"][b, win], res["P"][b, win]
            ok = np.all(np.isfinite(e), axis=1)
            if not ok.any():
                rows.append({"run": k, "started": False})
                continue
            e, P = e[ok], P[ok]
            row = {"run": k, "started": True}
            d = e.shape[1]
            row["full"] = (
                float(np.mean(np.einsum("ki,ki->k", e, np.linalg.solve(P, e[..., None])[..., 0])))
                / d
            )
            for name, sl in BLOCKS.items():
                eb, Pb = e[:, sl], P[:, sl, sl]
                nb = np.einsum("ki,ki->k", eb, np.linalg.solve(Pb, eb[..., None])[..., 0])
                row[name] = float(np.mean(nb)) / eb.shape[1]
            att = np.degrees(np.linalg.norm(e[:, 0:3], axis=1))
            row["att_deg"] = float(np.sqrt(np.mean(att**2)))
            row["wrong_branch"] = bool(np.mean(att) > 90.0)
            rows.append(row)
            print(
                f"run {k:3d}: "
                + " ".join(f"{n} {row[n]:.3g}" for n in ["full", *BLOCKS])
                + f"  attitude {row['att_deg']:.3g} deg{'  WRONG BRANCH' if row['wrong_branch'] else ''}",
                flush=True,
            )
    started = [r for r in rows if r["started"]]
    right = [r for r in started if not r["wrong_branch"]]
    print(
        f"{len(started)} of {len(rows)} runs started, {len(started) - len(right)} on the wrong branch"
    )
    for name in ["full", *BLOCKS]:
        a = np.array([r[name] for r in started])
        b = np.array([r[name] for r in right])
        print(
            f"{name:9s} mean all {np.mean(a):.3g}  mean right-branch {np.mean(b):.3g}  "
            f"median {np.median(a):.3g}"
        )
    att = np.median([r["att_deg"] for r in started])
    print(
        f"nees_all={np.mean([r['full'] for r in started]):.4g} "
        f"nees_right_branch={np.mean([r['full'] for r in right]):.4g} "
        f"median_run={np.median([r['full'] for r in started]):.4g} "
        f"wrong_branch={len(started) - len(right)} attitude_median_deg={att:.3g}"
    )


if __name__ == "__main__":
    main()
