"""Which part of an estimator's state is over-confident? Mean NEES/dof per block, any estimator.

For each run (the seeds of ``tumblenav montecarlo``: run k of base seed ``--base-seed``), the
scenario is simulated, the measurements go through the front end the estimator consumes (as in
a campaign), and the NEES per degree of freedom of each block of the estimator's error state
(``layout.blocks``) and of the whole state is averaged over the scenario's steady-state window
(the last quarter without one), on up to ~200 epochs evenly spread. The truth is aligned with
the estimate's symmetric frame as the evaluation does (``evaluation.alignment.align``).

Usage::

    python benchmarks/block_nees.py SCENARIO ESTIMATOR [--seeds 0,1,2]
        [--tuning '{"key": value}'] [--series BLOCK] [--at T1,T2,...] [--info KEY]

``--tuning`` updates the scenario's ``estimator.tuning`` (JSON); ``--series BLOCK`` prints that
block's error, 1-sigma and NEES/dof over time for each run; ``--at`` prints, per run and as a
mean over runs, the NEES/dof at the epochs nearest those times (s) of each block, of the blocks
taken jointly ("moving": rate and attitude; "rigid": inertia and features, where the layout
has them) and of the whole state (a joint NEES above its blocks' says the cross-covariances
are wrong); ``--info KEY`` prints the history's ``info[KEY]`` for each run (e.g. ``start``,
``gp``). ``NIS`` is each run's NIS/dof over the window (the sum of NIS over the sum of its
dof, as the campaign's; NaN without an update there). Last line: ``block_nees <block>=<mean
over runs> ... all=<mean> NIS=<mean>``.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from threadpoolctl import threadpool_limits

from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import align
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate


def _groups(layout) -> list[tuple[str, np.ndarray]]:
    """Each block, the moving and the rigid blocks jointly (where present), the whole state."""
    E = np.arange(layout.dim)
    names = [b.name for b in layout.blocks]
    out = [(n, E[layout.err(n)]) for n in names]
    for g, members in (("moving", ("rate", "attitude")), ("rigid", ("inertia", "features"))):
        if all(m in names for m in members):
            out.append((g, np.concatenate([E[layout.err(m)] for m in members])))
    return out + [("all", E)]


def run_blocks(
    sc, est, k: int, series: str | None = None, at=(), info: str | None = None
) -> dict[str, float]:
    """Mean NEES/dof per block of run ``k`` in the scenario's window; with ``at``, the NEES/dof
    at those times under the keys ``"<name>@<time>"`` as well."""
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    images = getattr(sc.sensor, "images", None)
    consumes = tuple(getattr(est, "consumes", ()))
    tracks, _ = stages.prepare(meas, consumes, images.frontend if images else None)
    h = est.run(
        context_from_scenario(sc), tracks, run_streams(run_seed(sc.montecarlo.seed, k))["estimator"]
    )
    dx = h.layout.boxminus(align(truth, h).x, h.x)
    t = h.t
    w0, w1 = sc.window_s if sc.window_s else (0.75 * t[-1], t[-1])
    finite_P = np.array([h.P[i] is not None and np.all(np.isfinite(h.P[i])) for i in range(len(t))])
    ok = np.all(np.isfinite(dx), axis=1) & finite_P
    sel = np.flatnonzero((t >= w0) & (t <= w1) & ok)
    sel = sel[:: max(1, len(sel) // 200)]
    E = np.arange(h.layout.dim)
    blocks = [(b.name, E[h.layout.err(b.name)]) for b in h.layout.blocks] + [("all", E)]

    def nees(i: int, ix: np.ndarray) -> float:
        e = dx[i, ix]
        return float(e @ np.linalg.solve(h.P[i][np.ix_(ix, ix)], e) / len(ix))

    out = {
        name: float(np.mean([nees(i, ix) for i in sel])) if len(sel) else np.nan
        for name, ix in blocks
    }
    nw = (t >= w0) & (t <= w1) & (h.nis_dof > 0) & np.isfinite(h.nis)
    out["NIS"] = float(h.nis[nw].sum() / h.nis_dof[nw].sum()) if nw.any() else np.nan
    for tt in at:
        i = int(np.argmin(np.abs(t - tt)))
        for name, ix in _groups(h.layout):
            out[f"{name}@{tt:g}"] = nees(i, ix) if ok[i] else np.nan
    if info:
        print(f"  info[{info!r}]: {h.info.get(info)}")
    if series:
        ix = E[h.layout.err(series)]
        for i in np.flatnonzero(ok)[:: max(1, int(ok.sum()) // 25)]:
            s = np.sqrt(np.diag(h.P[i])[ix])
            print(
                f"  t={t[i]:8.1f} error {np.round(dx[i, ix], 5)} sigma {np.round(s, 5)} NEES/dof {nees(i, ix):.2f}"
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", help="a built-in name or a YAML path")
    ap.add_argument("estimator")
    ap.add_argument("--seeds", default="0,1,2", help="run numbers, comma-separated")
    ap.add_argument("--tuning", default="{}", help="JSON updating estimator.tuning")
    ap.add_argument("--series", default=None, help="print this block's error over time")
    ap.add_argument("--at", default="", help="times (s), comma-separated: NEES/dof there")
    ap.add_argument("--info", default=None, help="print the history's info[KEY] for each run")
    args = ap.parse_args()
    at = [float(x) for x in args.at.split(",") if x.strip()]
    sc = load_scenario(args.scenario)
    tuning = json.loads(args.tuning)
    if tuning:
        sc = sc.with_updates(**{"estimator.tuning": {**(sc.estimator.tuning or {}), **tuning}})
    est = est_base.get(args.estimator)
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        for k in [int(s) for s in args.seeds.split(",")]:
            r = run_blocks(sc, est, k, args.series, at, args.info)
            print(f"run {k}: " + " ".join(f"{n}={v:.3g}" for n, v in r.items()), flush=True)
            rows.append(r)
    for tt in at:
        keys = [n for n in rows[0] if n.endswith(f"@{tt:g}")]
        print(
            f"mean at {tt:g} s: "
            + " ".join(f"{n.split('@')[0]}={np.nanmean([r[n] for r in rows]):.3g}" for n in keys)
        )
    names = [n for n in rows[0] if "@" not in n]
    print("block_nees " + " ".join(f"{n}={np.nanmean([r[n] for r in rows]):.3g}" for n in names))


if __name__ == "__main__":
    main()
