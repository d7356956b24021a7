"""ekf-pose on the point-sensor stereo tracks of chang2021_close (or another scenario): per-axis
error mean and std in the steady-state window over seeded runs (Chang 2021 Table 2's form),
RMSE, NEES/dof against its 95 % bounds (and per block), runs flagged diverged.

    .venv/bin/python benchmarks/chang2021_estimator.py [--images] [SCENARIO] [RUNS] [KEY=VALUE ...]

(KEY=VALUE: estimator.tuning keys, values as Python literals.) ``--images``: render the
scenario's images and run the image front end (its default settings) instead of the point
sensor (minutes per run: the renderer).
"""

from __future__ import annotations

import ast
import sys
import time

import numpy as np

from tumblenav.estimators.base import get
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import truth_state
from tumblenav.evaluation.metrics import chi2_bounds
from tumblenav.frontends.stages import prepare
from tumblenav.measurements import STEREO_TRACKS
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

TABLE2_STD = {  # Chang 2021 Table 2 (100 runs), per axis
    "attitude_deg": (0.4482, 0.5480, 0.5298),
    "rate_deg_s": (0.5400, 0.6336, 0.2833),
    "position_m": (0.1146, 0.1157, 0.1161),
    "velocity_m_s": (0.0298, 0.0308, 0.0309),
}


def main() -> None:
    argv = [a for a in sys.argv[1:] if a != "--images"]
    images = len(argv) < len(sys.argv) - 1
    name = argv[0] if len(argv) > 0 else "chang2021_close"
    runs = int(argv[1]) if len(argv) > 1 else 5
    tuning = {k: ast.literal_eval(v) for k, v in (a.split("=", 1) for a in argv[2:])}
    sc = load_scenario(name)
    if getattr(sc.sensor, "images", None) is not None and not images:
        sc = sc.with_updates(**{"sensor.images": None})  # the point sensor's tracks
    sc = sc.with_updates(**{"estimator.tuning": tuning})
    lo, hi = sc.steady_state_window_s or (0.75 * sc.duration_s, sc.duration_s)
    errs, nees, blocks, secs, div = [], [], [], [], 0
    for seed in range(runs):
        truth, meas = simulate(sc, seed)
        if images:
            meas, _ = prepare(meas, (STEREO_TRACKS,))  # the image front end's tracks
        t0 = time.perf_counter()
        h = get("ekf-pose").run(context_from_scenario(sc), meas, np.random.default_rng(seed))
        secs.append(time.perf_counter() - t0)
        div += int(h.info.get("diverged", False))
        dx = h.layout.boxminus(truth_state(truth, h), h.x)
        m = (h.t >= lo - 1e-9) & (h.t <= hi + 1e-9) & np.all(np.isfinite(dx), axis=1)
        errs.append(dx[m])
        nees.append(np.einsum("ni,nij,nj->n", dx[m], np.linalg.inv(h.P[m]), dx[m]))
        blocks.append(
            [
                np.einsum("ni,nij,nj->n", dx[m][:, b], np.linalg.inv(h.P[m][:, b, b]), dx[m][:, b])
                for b in (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12))
            ]
        )
    e = np.concatenate(errs)
    scale = {"attitude_deg": np.degrees(1), "rate_deg_s": np.degrees(1)}
    print(
        f"{name}: {runs} runs, window {lo:g}-{hi:g} s, {np.mean(secs):.2f} s/run, tuning {tuning}"
    )
    for i, key in enumerate(("attitude_deg", "rate_deg_s", "position_m", "velocity_m_s")):
        ek = e[:, 3 * i : 3 * i + 3] * scale.get(key, 1.0)
        print(
            f"  {key:13s} mean {np.round(ek.mean(0), 4)} std {np.round(ek.std(0), 4)} "
            f"rmse {np.round(np.sqrt((ek**2).mean(0)), 4)}  (Table 2 std {TABLE2_STD[key]})"
        )
    if e.shape[1] > 12:  # map 'registered': the offset block
        eo = e[:, 12:15]
        print(f"  offset_m      rmse {np.round(np.sqrt((eo**2).mean(0)), 4)}")
    dof = e.shape[1]
    lo95, hi95 = chi2_bounds(dof, runs)
    print(
        f"  NEES/dof {np.mean(np.concatenate(nees)) / dof:.2f} (95 % bounds for {runs} runs: "
        f"{lo95:.2f}-{hi95:.2f}); diverged runs: {div}"
    )
    per_block = [np.mean(np.concatenate([b[i] for b in blocks])) / 3 for i in range(4)]
    print("  NEES/3 per block (attitude, rate, position, velocity):", np.round(per_block, 2))


if __name__ == "__main__":
    main()
