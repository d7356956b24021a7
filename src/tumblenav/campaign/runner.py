"""Monte Carlo campaigns: N seeded runs on local processes or a Dask cluster, resumable.

Each finished run is stored at once (see :mod:`tumblenav.campaign.store`); running the same
campaign again into the same folder keeps the finished runs and does only the missing ones.
A run that raises is recorded as failed with its seed and error, and the campaign goes on.
Estimators that offer ``run_batch`` get chunks of runs to vectorise over.
"""

from __future__ import annotations

import hashlib
import os
import traceback
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from tumblenav import io, metrics
from tumblenav.campaign.store import CampaignStore, run_seed
from tumblenav.errors import InputError
from tumblenav.estimators import base as est_base
from tumblenav.scenario import Scenario, scenario_to_yaml
from tumblenav.simulation import run_streams, simulate


def evaluate_runs(
    scenario: Scenario, estimator_name: str, base_seed: int, ks: Sequence[int]
) -> list[tuple[int, Any, str | None]]:
    """Simulate, estimate and evaluate runs ``ks``; returns (k, RunErrors | None, error)."""
    est = est_base.get(estimator_name)
    sims, out = [], []
    for k in ks:
        try:
            ss = run_seed(base_seed, k)
            truth, meas = simulate(scenario, ss)
            sims.append((k, truth, meas, run_streams(ss)["estimator"]))
        except Exception as exc:  # noqa: BLE001 - a failed run is recorded, not fatal
            out.append((k, None, _short(exc)))
    batch = getattr(est, "run_batch", None)
    if batch is not None and sims:
        try:
            res = batch(scenario, [s[2] for s in sims], [s[3] for s in sims], [s[1] for s in sims])
            out.extend((k, r, None) for (k, *_), r in zip(sims, res, strict=True))
            return out
        except Exception:  # noqa: BLE001 - fall back to one run at a time to isolate failures
            pass
    for k, truth, meas, rng in sims:
        try:
            hist = est.run(scenario, meas, rng)
            r = metrics.run_errors(hist, est.truth_state(truth, hist))
            out.append((k, (r, hist.skipped), None))
        except Exception as exc:  # noqa: BLE001
            out.append((k, None, _short(exc)))
    return out


def _store_results(store: CampaignStore, base_seed: int, results) -> list[int]:
    """Write each run of ``results`` (from :func:`evaluate_runs`) to the store at once;
    returns their indices."""
    for k, res, error in results:
        if res is None:
            store.save_failure(k, base_seed, error or "unknown error")
        else:
            r, skipped = res
            store.save_run(k, base_seed, r, {f"skipped_{n}": c for n, c in skipped.items()})
    return [k for k, _, _ in results]


def evaluate_and_store(
    scenario: Scenario, estimator_name: str, base_seed: int, ks: Sequence[int], root: str
) -> list[int]:
    """:func:`evaluate_runs`, then store the runs from where they were computed (a local
    worker process), so that compressing and writing them is spread over the workers instead
    of queueing in the parent; returns the stored run indices."""
    results = evaluate_runs(scenario, estimator_name, base_seed, ks)
    return _store_results(CampaignStore(Path(root)), base_seed, results)


def _warm_up(scenario: Scenario, estimator_name: str, base_seed: int) -> None:
    """Run one short run in this process before forking the workers, so that they inherit
    what it loaded (compiled kernels from numba's cache, lazily imported modules) instead of
    each loading it again for every campaign. Best effort: a failure here changes nothing."""
    try:
        short = min(scenario.duration_s, 5.0)
        sc = scenario.with_updates(duration_s=short, steady_state_window_s=[0.0, short])
        evaluate_runs(sc, estimator_name, base_seed, [0])
    except Exception:  # noqa: BLE001 - only a warm-up
        pass


def _short(exc: BaseException) -> str:
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
    return f"{exc.__class__.__name__}: {exc}{where}"


def _chunks(ks: list[int], size: int) -> Iterable[list[int]]:
    for i in range(0, len(ks), size):
        yield ks[i : i + size]


def scenario_hash(scenario: Scenario) -> str:
    return hashlib.sha256(scenario_to_yaml(scenario).encode()).hexdigest()[:16]


def run_campaign(
    scenario: Scenario,
    estimator_name: str,
    runs: int,
    out_dir: Path,
    workers: int | None = None,
    scheduler: str | None = None,
    console: Console | None = None,
    chunk_size: int | None = None,
    base_seed: int | None = None,
) -> dict[str, Any]:
    """Run (or resume) a campaign and write summary.json; returns the summary."""
    est = est_base.get(estimator_name)
    if runs < 1:
        raise InputError("--runs must be at least 1")
    base_seed = scenario.montecarlo.seed if base_seed is None else base_seed
    store = CampaignStore(Path(out_dir))
    store.open(
        {
            "scenario": scenario.name,
            "scenario_hash": scenario_hash(scenario),
            "estimator": estimator_name,
            "base_seed": base_seed,
            "runs_requested": runs,
        }
    )
    io.atomic_write(
        store.root / "scenario.yaml",
        lambda tmp: tmp.write_text(scenario_to_yaml(scenario), encoding="utf-8"),
    )
    todo = sorted(set(range(runs)) - store.done())
    workers = max(1, workers or os.cpu_count() or 1)
    con = console or Console(stderr=True)
    if runs - len(todo) > 0:
        con.print(
            f"resuming {store.root}: {runs - len(todo)} of {runs} runs already stored, "
            f"{len(todo)} to do"
        )
    if todo:
        if chunk_size is None:
            batched = hasattr(est, "run_batch")
            chunk_size = max(1, min(128, -(-len(todo) // workers))) if batched else 1
        chunks = list(_chunks(todo, chunk_size))
        if getattr(est, "compiled", False) and workers > 1 and len(chunks) > 1 and not scheduler:
            _warm_up(scenario, estimator_name, base_seed)
        _execute(
            scenario,
            estimator_name,
            base_seed,
            chunks,
            store,
            workers,
            scheduler,
            con,
            total=runs,
            already=runs - len(todo),
        )
    summary = summarise(store, scenario, estimator_name, runs)
    io.write_json(summary, store.root / "summary.json")
    return summary


def _execute(
    scenario,
    estimator_name,
    base_seed,
    chunks,
    store,
    workers,
    scheduler,
    con,
    total: int,
    already: int,
) -> None:
    columns = (
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=con, transient=False) as prog:
        task = prog.add_task(f"{scenario.name} / {estimator_name}", total=total, completed=already)

        def record(results) -> None:  # results computed elsewhere (Dask): store them here
            prog.advance(task, len(_store_results(store, base_seed, results)))

        root = str(store.root.resolve())
        if scheduler:
            _execute_dask(scenario, estimator_name, base_seed, chunks, scheduler, record)
        elif workers == 1 or len(chunks) == 1:
            for ks in chunks:
                done = evaluate_and_store(scenario, estimator_name, base_seed, ks, root)
                prog.advance(task, len(done))
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                pending = {
                    pool.submit(evaluate_and_store, scenario, estimator_name, base_seed, ks, root)
                    for ks in chunks
                }
                while pending:
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in finished:
                        prog.advance(task, len(f.result()))


def _execute_dask(
    scenario, estimator_name, base_seed, chunks, address: str, record: Callable
) -> None:
    try:
        from dask.distributed import Client, as_completed
    except ImportError:
        raise InputError(
            "--scheduler needs dask.distributed: pip install 'tumblenav[cluster]'"
        ) from None
    try:
        client = Client(address, timeout="5s")
    except OSError as exc:
        raise InputError(f"cannot reach the Dask scheduler ({exc})", address) from None
    with client:
        futures = [
            client.submit(evaluate_runs, scenario, estimator_name, base_seed, ks, pure=False)
            for ks in chunks
        ]
        for fut in as_completed(futures):
            record(fut.result())


def collect(store: CampaignStore, runs: int) -> tuple[np.ndarray, dict[str, np.ndarray], dict]:
    """Stack the finished runs: t, errors (runs, n) per quantity, NEES and NIS arrays."""
    ks = sorted(k for k in store.done() if k < runs)
    if not ks:
        return np.zeros(0), {}, {}
    rs = [store.load_run(k) for k in ks]
    t = rs[0].t
    errs = {key: np.stack([r.errors[key] for r in rs]) for key in rs[0].errors}
    cons = {
        "nees": np.stack([r.nees for r in rs]),
        "nees_dof": rs[0].nees_dof,
        "nis": np.stack([r.nis for r in rs]),
        "nis_dof": np.stack([r.nis_dof for r in rs]),
        "runs": ks,
    }
    return t, errs, cons


def summarise(store: CampaignStore, scenario: Scenario, estimator_name: str, runs: int) -> dict:
    """summary.json of a campaign (keys of docs/formats.md / shared design)."""
    t, errs, cons = collect(store, runs)
    window = scenario.window_s
    failures = [f for f in store.failures() if f["run"] < runs]
    summary: dict[str, Any] = {
        "scenario": scenario.name,
        "estimator": estimator_name,
        "runs": len(cons.get("runs", [])),
        "runs_failed": len(failures),
        "window_s": list(window),
    }
    if errs:
        first = next(iter(errs.values()))
        in_window = metrics.window_mask(t, window)
        # runs that produced no estimate in the window are excluded from the RMSE: say so
        summary["runs_without_estimate"] = int(
            np.sum(~np.any(np.isfinite(first[:, in_window]), axis=1))
        )
        summary["rmse"] = {
            key: metrics.rmse_over_time(metrics.rmse_over_runs(e), t, window)
            for key, e in errs.items()
        }
        # RMSE over runs is dominated by the worst runs; the spread of the per-run RMS in
        # the window tells the typical run from the outliers
        per_run = {
            k: np.sqrt(metrics.nanmean_quiet(e[:, in_window] ** 2, axis=1)) for k, e in errs.items()
        }
        summary["per_run"] = {
            k: {
                "median": float(np.nanmedian(v)),
                "p90": float(np.nanpercentile(v, 90)),
                "max": float(np.nanmax(v)),
            }
            for k, v in per_run.items()
            if np.isfinite(v).any()
        }
        summary["nees"] = metrics.consistency(cons["nees"], cons["nees_dof"], t, window)
        summary["nis"] = metrics.consistency(cons["nis"], cons["nis_dof"], t, window)
    if failures:
        summary["failed"] = failures[:20]
    return summary
