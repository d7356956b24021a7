"""When should ekf-dpacf start? Accuracy, consistency and start time against the start gate.

For the runs of a scenario (the campaign's seeds) at one noise level: the median over runs
of the per-run attitude RMS in the steady-state window, the inertia ratios' error (median of
the per-run RMS, and the RMS over runs), the mean NEES/dof over runs (every 5th epoch of the
window) and the filter's start time (median, maximum). Compare tunings with ``--set``, e.g.
``--set max_ratio_sigma=0.03`` (the default until the seventh session).

Usage: python benchmarks/hu2024_start_gate.py [--runs 100] [--noise 2e-5]
       [--scenario hu2024|FILE] [--set key=value ...]
Last line: ``attitude_median_deg=<...> inertia_median=<...> inertia_rms=<...>
nees_mean=<...> start_median_s=<...> start_max_s=<...>``
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="hu2024")
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--noise", type=float, default=2e-5, help="angular resolution (rad)")
    ap.add_argument("--batch", type=int, default=20)
    ap.add_argument("--set", action="append", default=[], help="tuning key=value")
    args = ap.parse_args()
    sc = with_tuning(
        load_scenario(args.scenario), args.set, **{"sensor.noise.angular_rad": args.noise}
    )
    t0, t1 = sc.window_s
    att, inert, nees, starts = [], [], [], []
    for s0 in range(0, args.runs, args.batch):
        ks = range(s0, min(args.runs, s0 + args.batch))
        sims = [simulate(sc, run_seed(sc.montecarlo.seed, k)) for k in ks]
        res = hu.run_filter(sc, [m for _, m in sims], True)
        res["x_true"], res["err"] = evaluation.error_states(
            hu.histories(res, sc), [t for t, _ in sims]
        )
        t = res["t"]
        w = np.flatnonzero((t >= t0) & (t <= t1))
        starts += [t[k] if k >= 0 else np.inf for k in res["k0"]]
        for b in range(len(ks)):
            e, P = res["err"][b, w], res["P"][b, w]
            ok = np.all(np.isfinite(e), axis=1)
            if not ok.any():
                continue
            e, P = e[ok], P[ok]
            att.append(np.degrees(np.sqrt(np.mean(np.sum(e[:, 0:3] ** 2, axis=1)))))
            inert.append(np.sqrt(np.mean(np.sum(e[:, 6:9] ** 2, axis=1))))
            ee, PP = e[::5], P[::5]
            q = np.einsum("ki,ki->k", ee, np.linalg.solve(PP, ee[..., None])[..., 0])
            nees.append(float(np.mean(q)) / e.shape[1])
    inert = np.array(inert)
    print(
        f"{args.scenario}, {args.noise:g} rad, {len(att)} of {args.runs} runs with an "
        f"estimate in the window; settings {args.set or 'defaults'}"
    )
    print(
        f"attitude_median_deg={np.median(att):.3g} inertia_median={np.median(inert):.3g} "
        f"inertia_rms={np.sqrt(np.mean(inert**2)):.3g} nees_mean={np.mean(nees):.3g} "
        f"start_median_s={np.median(starts):.3g} start_max_s={np.max(starts):.3g}"
    )


if __name__ == "__main__":
    main()
