"""Why does a replayed start at range end over-confident? (twentieth session, issue 18) Per run:
the replay's departure from the batch fit per block (attitude, rate, position, velocity, all
twelve) as a chi-square against the sum of covariances (the fit's first-belief covariance,
``slam.StateSteps._window_noise``, plus the replay's), the same against their difference
(Hausman's test: an efficient and a consistent estimator; ``H`` with the positive
eigen-directions used, ``/dof``), the fit's window-noise ratio, whether the refusal fired,
and the run's NEES/dof over the window (benchmarks/block_nees.py's blocks). "no replay": the
fit was the first belief (ratio at most ``batch_noise_ratio``).

Usage::

    python docs/results/consistency/prototype/chang_replay_refusal.py SCENARIO SEEDS [TUNING]

SEEDS like 0,1,2 or 0-19; TUNING a JSON update of the scenario's ekf-pose tuning.
"""

from __future__ import annotations

import json
import sys

import numpy as np
from threadpoolctl import threadpool_limits

from tumblenav import rotations as rot
from tumblenav.estimators import base as est_base
from tumblenav.estimators.chang2021 import slam
from tumblenav.scenario import load_scenario

sys.path.insert(0, "benchmarks")
from block_nees import run_blocks  # noqa: E402

SEEN: list[dict] = []
_orig = slam.StateSteps._replay_refused


def _spy(self, b, fit, P_fit):
    d_att = rot.log_map(rot.quat_to_matrix(fit.x[0:4]) @ rot.quat_to_matrix(b.x[0:4]).T)
    d = np.concatenate([d_att, fit.x[4:13] - b.x[4:13]])
    C = P_fit[:12, :12] + b.P[:12, :12]
    row = {}
    for name, ix in (("att", slice(0, 3)), ("rate", slice(3, 6)), ("pos", slice(6, 9)),
                     ("vel", slice(9, 12)), ("all", slice(0, 12))):
        row[name] = float(d[ix] @ np.linalg.solve(C[ix, ix], d[ix]))
    # Hausman: the difference of an efficient (the replay, Q carried) and a consistent
    # estimator (the fit with the window's Q) has the difference of their covariances
    Ch = P_fit[:12, :12] - b.P[:12, :12]
    for name, ix in (("h_att", slice(0, 3)), ("h_pos", slice(6, 9)), ("h_all", slice(0, 12))):
        w, V = np.linalg.eigh(Ch[ix, ix])
        pos = w > 1e-9 * w.max()
        y = V[:, pos].T @ d[ix]
        row[name] = float(np.sum(y**2 / w[pos]))
        row[name + "_dof"] = int(pos.sum())
    refused = _orig(self, b, fit, P_fit)
    row["refused"] = refused
    row["ratio"] = b.memo.start.fit_noise_ratio
    SEEN.append(row)
    return refused


slam.StateSteps._replay_refused = _spy


def main() -> None:
    path, seeds = sys.argv[1], sys.argv[2]
    if "-" in seeds:
        a, b = map(int, seeds.split("-"))
        ks = list(range(a, b + 1))
    else:
        ks = [int(s) for s in seeds.split(",")]
    sc = load_scenario(path)
    if len(sys.argv) > 3:
        tun = {**(sc.estimator.tuning or {}), **json.loads(sys.argv[3])}
        sc = sc.with_updates(**{"estimator.tuning": tun})
    est = est_base.get("ekf-pose")
    alls = []
    for k in ks:
        SEEN.clear()
        with threadpool_limits(limits=1, user_api="blas"):
            r = run_blocks(sc, est, k)
        s = SEEN[0] if SEEN else None
        if s is None:
            txt = "no replay"
        else:
            txt = " ".join(f"{n} {s[n]:6.1f}" for n in ("att", "rate", "pos", "vel", "all"))
            txt += " H " + " ".join(
                f"{n} {s[n]:7.1f}/{s[n + '_dof']}" for n in ("h_att", "h_pos", "h_all")
            )
            txt += f" ratio {s['ratio']:.3g} refused {s['refused']}"
        alls.append(r["all"])
        print(f"run {k:2d}: NEES/dof {r['all']:6.2f}  d2 {txt}", flush=True)
    print(f"mean NEES/dof {np.mean(alls):.3f}")


if __name__ == "__main__":
    main()
