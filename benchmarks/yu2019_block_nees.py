"""Which part of the ekf-depth state is over-confident? NEES per block on yu2019 runs.

For each run of the 1 cm yu2019 scenario (same seeds as ``tumblenav montecarlo``), the mean
over the window [300, 400] s of the NEES per degree of freedom of the whole state, of the
translation block (position, velocity, mass-centre offset: 9 dof), of the rotation block
(attitude, rate: 6 dof) and of the inertia ratios (5 dof), and the NIS per dof.

Usage: python benchmarks/yu2019_block_nees.py [--runs 6] [--position-scale 4] [--attitude-scale 1.5]
Last line: ``nees_full=<mean> nees_translation=<mean> nees_rotation=<mean> nees_inertia=<mean>
nis=<mean>`` (means over runs).
"""

from __future__ import annotations

import argparse

import numpy as np

from tumblenav.campaign.runner import run_seed, run_streams
from tumblenav.estimators import ekf_depth as D
from tumblenav.evaluation import alignment
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

BLOCKS = {"translation": slice(11, 20), "rotation": slice(0, 6), "inertia": slice(6, 11)}


def block_nees(dx: np.ndarray, P: np.ndarray, sel: slice) -> float:
    return float(dx[sel] @ np.linalg.solve(P[sel, sel], dx[sel]) / (sel.stop - sel.start))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="docs/results/scenarios/yu2019_1cm_noise.yaml")
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--position-scale", type=float, default=None)
    ap.add_argument("--attitude-scale", type=float, default=None)
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    tuning = dict(sc.estimator.tuning)
    if args.position_scale is not None:
        tuning["position_noise_scale"] = args.position_scale
    if args.attitude_scale is not None:
        tuning["attitude_noise_scale"] = args.attitude_scale
    sc = sc.with_updates(**{"estimator.tuning": tuning})
    rows = []
    for run in range(args.runs):
        ss = run_seed(sc.montecarlo.seed, run)
        truth, meas = simulate(sc, ss)
        est = D.DepthEKF()
        hist = est.run(sc, meas, run_streams(ss)["estimator"])
        dx = hist.layout.boxminus(alignment.truth_state(truth, hist), hist.x)
        win = np.flatnonzero((hist.t >= 300.0) & np.all(np.isfinite(dx), axis=1))
        row = {"full": float(np.mean([block_nees(dx[k], hist.P[k], slice(0, 20)) for k in win]))}
        for name, sel in BLOCKS.items():
            row[name] = float(np.mean([block_nees(dx[k], hist.P[k], sel) for k in win]))
        sel_t = hist.t >= 300.0
        row["nis"] = float(np.nansum(hist.nis[sel_t]) / np.sum(hist.nis_dof[sel_t]))
        rows.append(row)
        print(f"run {run}: " + " ".join(f"{k} {v:.2f}" for k, v in row.items()), flush=True)
    m = {k: np.mean([r[k] for r in rows]) for k in rows[0]}
    print(
        f"nees_full={m['full']:.2f} nees_translation={m['translation']:.2f} "
        f"nees_rotation={m['rotation']:.2f} nees_inertia={m['inertia']:.2f} nis={m['nis']:.2f}"
    )


if __name__ == "__main__":
    main()
