"""Monte Carlo campaigns: N seeded runs on local processes or a Dask cluster, resumable.

Each finished run is stored at once by the process that computed it (on a Dask cluster, by
the command's own process as each chunk returns: the workers may share no filesystem; see
:mod:`tumblenav.campaign.store`); running the same campaign again into the same folder keeps
the finished runs and does only the missing ones. A run that raises is recorded as failed with
its seed and error, and the campaign goes on.

Estimators that offer ``run_batch`` get chunks of :data:`BATCH_CHUNK` runs to vectorise over.
Chunks are fixed by run index (runs 0-15, 16-31, ...), whatever the number of workers or what
an earlier, interrupted campaign finished, so a run's arithmetic, and hence its stored result,
does not depend on how the campaign was scheduled or resumed.

Local runs are computed in worker processes (even with one worker): the parent only schedules,
shows progress and stays responsive, so an interrupt (SIGINT/SIGTERM) stops the campaign within
about a second (:func:`_stop_pool` terminates the workers; at most the chunks in flight are
lost). A worker that dies (killed, out of memory) is replaced and its chunk redone; runs
already stored are never recomputed into the store.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import signal
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
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
from threadpoolctl import threadpool_limits

from tumblenav import evaluation, io
from tumblenav.campaign.store import CampaignStore, code_fingerprint, run_seed
from tumblenav.errors import InputError, Interrupted
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation import metrics
from tumblenav.numba_cache import kernels_compiled
from tumblenav.scenario import Scenario, scenario_to_yaml
from tumblenav.simulation import run_streams, simulate, with_track_truth

BATCH_CHUNK = 16  # runs per run_batch call: as fast per run as 128 (cache-friendlier), and
# an interrupt loses at most this many runs per worker (benchmarks/hu2024_campaign.py)
MAX_POOL_RESTARTS = 3  # worker pools that may break in a row, storing nothing, before giving up


def evaluate_runs(
    scenario: Scenario, estimator_name: str, base_seed: int, ks: Sequence[int]
) -> list[tuple[int, Any, str | None]]:
    """Simulate, estimate and evaluate runs ``ks``; returns (k, RunErrors | None, error).
    BLAS runs on one thread meanwhile: the filters' matrices are small, a campaign has one
    worker per core already, and OpenBLAS's spinning threads made one ekf-pose run cost 152 s
    of CPU instead of 26 s (measured, docs/results/chang2021.md)."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _evaluate_runs(scenario, estimator_name, base_seed, ks)


def _evaluate_runs(
    scenario: Scenario, estimator_name: str, base_seed: int, ks: Sequence[int]
) -> list[tuple[int, Any, str | None]]:
    from tumblenav.frontends import stages

    est = est_base.get(estimator_name)
    context = context_from_scenario(scenario)  # what the estimator may know: no truth
    consumes = tuple(getattr(est, "consumes", ()))
    images = getattr(scenario.sensor, "images", None)
    sims = []
    out: list[tuple[int, Any, str | None]] = []
    for k in ks:
        try:
            ss = run_seed(base_seed, k)
            truth, meas = simulate(scenario, ss)
            # image pairs: found and tracked features (the image front end), else as they are
            tracks, _ = stages.prepare(meas, consumes, images.frontend if images else None)
            judge: Any = truth
            if tracks is not meas:  # the tracks' own points, for estimators of features
                judge = _TrackTruth(truth, meas, tracks)
            sims.append((k, judge, tracks, run_streams(ss)["estimator"]))
        except Exception as exc:  # noqa: BLE001 - a failed run is recorded, not fatal
            out.append((k, None, _short(exc)))
    batch = getattr(est, "run_batch", None)
    if batch is not None and sims:
        try:
            p_every = evaluation.nees_every(sims[0][2].t)  # the covariance where NEES needs it
            hists = batch(context, [s[2] for s in sims], [s[3] for s in sims], p_every=p_every)
            for (k, truth, *_), h in zip(sims, hists, strict=True):
                out.append((k, _evaluated(h, truth, scenario), None))
            return out
        except Exception:  # noqa: BLE001 - fall back to one run at a time to isolate failures
            out = [o for o in out if o[1] is None]
    for k, truth, meas, rng in sims:
        try:
            hist = est.run(context, meas, rng)
            out.append((k, _evaluated(hist, truth, scenario), None))
        except Exception as exc:  # noqa: BLE001
            out.append((k, None, _short(exc)))
    return out


@dataclass(frozen=True)
class _TrackTruth:
    """The truth of a run on images, and what is needed to find its tracks' true points."""

    truth: Any
    images: Any
    tracks: Any


def _evaluated(hist, truth, scenario: Scenario) -> tuple[Any, dict[str, Any]]:
    """A run's errors and the scalars stored with them: skipped updates by reason, per-axis
    error moments over the steady-state window (``summary.json`` ``per_axis``), the branch
    (``summary.json`` ``branches``)."""
    if isinstance(truth, _TrackTruth):  # only estimators of features need the tracks' points
        t = truth
        need = "features" in hist.layout.names()
        truth = with_track_truth(t.truth, t.images, t.tracks) if need else t.truth
    r = evaluation.evaluate_run(hist, truth)
    extras: dict[str, Any] = {f"skipped_{n}": c for n, c in hist.skipped.items()}
    extras["branch"] = r.branch
    notes = [str(w) for w in hist.info.get("warnings", []) or []]
    if notes:  # what the estimator said about its own run (tuning far from the scenario, ...)
        extras["warnings"] = notes
    return r, {**extras, **metrics.axis_moments(r, scenario.window_s)}


def _store_results(store: CampaignStore, base_seed: int, results) -> list[int]:
    """Write each run of ``results`` (from :func:`evaluate_runs`) to the store at once, except
    runs already stored (a chunk redone after an interrupt keeps what it had); returns their
    indices."""
    done = store.done()
    for k, res, error in results:
        if k in done:
            continue
        if res is None:
            store.save_failure(k, base_seed, error or "unknown error")
        else:
            r, extras = res
            store.save_run(k, base_seed, r, extras)
    return [k for k, _, _ in results]


def evaluate_and_store(
    scenario: Scenario, estimator_name: str, base_seed: int, ks: Sequence[int], root: str
) -> list[int]:
    """:func:`evaluate_runs`, then store the runs from where they were computed (a local
    worker process), so that compressing and writing them is spread over the workers instead
    of queueing in the parent; returns the stored run indices."""
    results = evaluate_runs(scenario, estimator_name, base_seed, ks)
    return _store_results(CampaignStore(Path(root)), base_seed, results)


def _warm_up(
    scenario: Scenario, estimator_name: str, base_seed: int, con: Console | None = None
) -> None:
    """Run one short run in this process before forking the workers, so that they inherit
    what it loaded (compiled kernels from numba's cache, lazily imported modules) instead of
    each loading it again for every campaign. Says so when the kernels must be compiled first
    (about 30 s, once per installation). Best effort: a failure here changes nothing."""
    if con is not None and not kernels_compiled():
        con.print("compiling the numerical kernels (first run after installing: about 30 s, once)")
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


def _chunks(todo: Iterable[int], size: int) -> list[list[int]]:
    """Fixed chunks of ``size`` run indices (``[0..size-1], [size..2 size-1], ...``) that hold
    a run still to do. A chunk is computed whole even if some of its runs are stored (they are
    not written again), so a run always shares its batch with the same runs."""
    todo = list(todo)
    if not todo:
        return []
    end = max(todo) + 1
    firsts = sorted({k - k % size for k in todo})
    return [list(range(f, min(f + size, end))) for f in firsts]


def _worker_init() -> None:
    """Workers leave interrupts to the parent: Ctrl-C reaches the whole process group, and
    the parent stops them itself (:func:`_stop_pool`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # one worker per core already: a renderer's second thread would only contend
    os.environ.setdefault("TUMBLENAV_RENDER_THREADS", "1")
    warnings.showwarning = _show_warning


def _show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: Any = None,
    line: str | None = None,
) -> None:
    """A worker's warnings (an estimator's "no usable GP ...") as the command prints its own,
    ``warning: message`` on one line, not Python's ``path:line: UserWarning:`` and the source
    line beneath it."""
    print(f"warning: {message}", file=sys.stderr if file is None else file, flush=True)


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel what has not started and terminate the workers now (SIGTERM, then SIGKILL
    after 1 s): runs in flight are lost, stored runs are whole (written atomically)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    manager = getattr(pool, "_executor_manager_thread", None)  # shutdown() drops it
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    deadline = time.monotonic() + 1.0
    for proc in procs:
        proc.join(max(0.0, deadline - time.monotonic()))
        if proc.is_alive():
            proc.kill()
            proc.join(1.0)
    # The pool's manager thread closes its wake-up pipe as it ends; the interpreter's exit
    # hook (concurrent.futures.process._python_exit) writes to that pipe unlocked, so on
    # CPython < 3.12 an exit while the thread is still ending printed "Exception ignored
    # ... OSError: [Errno 9] Bad file descriptor" after Ctrl-C (cpython gh-125451 added
    # the lock). With its workers gone the thread ends at once: wait for it.
    if manager is not None:
        manager.join(2.0)


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
    """Run (or resume) a campaign and write summary.json; returns the summary.

    The estimator is checked against the scenario before anything runs (InputError). On an
    interrupt (:class:`Interrupted` or ``KeyboardInterrupt``) the workers are stopped, the
    finished runs stay stored, and :class:`Interrupted` carries in ``kept`` what was kept and
    how to resume. One command at a time writes a campaign folder
    (:meth:`CampaignStore.exclusive`).
    """
    est = est_base.get_for(estimator_name, scenario)
    if runs < 1:
        raise InputError("--runs must be at least 1")
    with CampaignStore(Path(out_dir)).exclusive():
        return _run_campaign(
            scenario, est, estimator_name, runs, out_dir, workers, scheduler, console,
            chunk_size, base_seed,
        )  # fmt: skip


def _run_campaign(
    scenario: Scenario,
    est: Any,
    estimator_name: str,
    runs: int,
    out_dir: Path,
    workers: int | None,
    scheduler: str | None,
    console: Console | None,
    chunk_size: int | None,
    base_seed: int | None,
) -> dict[str, Any]:
    """:func:`run_campaign`'s work, under its lock."""
    base_seed = scenario.montecarlo.seed if base_seed is None else base_seed
    store = CampaignStore(Path(out_dir))
    damaged = store.open(
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
    if damaged:
        con.print(
            f"[bold yellow]warning:[/] {len(damaged)} stored run(s) in {store.runs_dir} could "
            f"not be read ({', '.join(damaged[:3])}{', ...' if len(damaged) > 3 else ''}): set "
            "aside as *.damaged and computed again",
            highlight=False,
        )
    if runs - len(todo) > 0:
        con.print(
            f"resuming {store.root}: {runs - len(todo)} of {runs} runs already stored, "
            f"{len(todo)} to do"
        )
    if todo:
        if chunk_size is None:
            chunk_size = BATCH_CHUNK if hasattr(est, "run_batch") else 1
        chunks = _chunks(todo, chunk_size)
        try:
            if getattr(est, "compiled", False) and not scheduler:
                _warm_up(scenario, estimator_name, base_seed, con)
            _execute(
                scenario, estimator_name, base_seed, chunks, store, workers, scheduler, con, runs
            )
        except (Interrupted, KeyboardInterrupt) as exc:
            n = len({k for k in store.done() if k < runs})
            kept = (
                f"{n} of {runs} runs are stored in {store.root}; run the same command again "
                "to finish the campaign (stored runs are kept, not redone)"
            )
            if isinstance(exc, Interrupted):
                exc.kept = kept
                raise
            raise Interrupted(signal.SIGINT, kept) from exc
    summary = summarise(store, scenario, estimator_name, runs)
    io.write_json(summary, store.root / "summary.json")
    return summary


def _execute(
    scenario, estimator_name, base_seed, chunks, store, workers, scheduler, con, runs: int
) -> None:
    columns = (
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )

    def finished() -> int:  # stored or failed runs of this campaign
        return len({k for k in store.done() if k < runs}) + sum(
            1 for f in store.failures() if f["run"] < runs and f["run"] not in store.done()
        )

    with Progress(*columns, console=con, transient=False) as prog:
        task = prog.add_task(
            f"{scenario.name} / {estimator_name}", total=runs, completed=finished()
        )

        def record(results) -> None:  # results computed elsewhere (Dask): store them here
            _store_results(store, base_seed, results)
            prog.update(task, completed=finished())

        if scheduler:
            _execute_dask(scenario, estimator_name, base_seed, chunks, scheduler, record, con)
        else:
            _execute_local(
                scenario,
                estimator_name,
                base_seed,
                chunks,
                store,
                workers,
                lambda: prog.update(task, completed=finished()),
                con,
            )


def _execute_local(
    scenario, estimator_name, base_seed, chunks, store, workers, progress: Callable, con
) -> None:
    """Compute ``chunks`` in worker processes, each storing its runs; replace a broken pool
    (a worker killed) and redo its unfinished chunks, up to MAX_POOL_RESTARTS times in a row
    without progress."""
    root = str(store.root.resolve())
    pending = list(chunks)
    breaks = 0
    while pending:
        pool = ProcessPoolExecutor(
            max_workers=max(1, min(workers, len(pending))), initializer=_worker_init
        )
        futures: dict[Future, list[int]] = {}
        try:
            for ks in pending:
                futures[
                    pool.submit(evaluate_and_store, scenario, estimator_name, base_seed, ks, root)
                ] = ks
            while futures:
                # a short timeout keeps the parent responsive to signals
                done, _ = wait(futures, timeout=0.2, return_when=FIRST_COMPLETED)
                for f in done:
                    ks = futures.pop(f)
                    f.result()  # BrokenProcessPool if its worker died
                    pending.remove(ks)
                    breaks = 0
                    progress()
        except BrokenProcessPool:
            breaks += 1
            stored = store.done()
            pending = [ks for ks in pending if not set(ks) <= stored]
            progress()
            con.print(
                "a worker process died (killed, or out of memory): stored runs are kept, "
                f"{sum(len(set(ks) - stored) for ks in pending)} runs still to do"
            )
            if breaks > MAX_POOL_RESTARTS:
                raise RuntimeError(
                    f"worker processes died {breaks} times in a row without storing a run "
                    "(out of memory?); the stored runs are kept: run the same command again "
                    "to resume, or use fewer --workers"
                ) from None
            continue
        finally:
            _stop_pool(pool)
            store.remove_partial()


def _dask_chunk(
    scenario: Scenario, estimator_name: str, base_seed: int, ks: Sequence[int]
) -> tuple[str, list[tuple[int, Any, str | None]]]:
    """A Dask task: :func:`evaluate_runs` on a worker, returned with the worker's
    :func:`~tumblenav.campaign.store.code_fingerprint` so that the parent stores only what
    its own code would have computed."""
    # one worker per core (dask worker --nthreads 1): a renderer's second thread would contend
    os.environ.setdefault("TUMBLENAV_RENDER_THREADS", "1")
    return code_fingerprint(), evaluate_runs(scenario, estimator_name, base_seed, ks)


def _other_code(worker: str, theirs: object) -> InputError:
    return InputError(
        f"Dask worker {worker} runs other tumblenav code ({theirs}, here {code_fingerprint()}): "
        "install the same tumblenav on every machine; stored runs are kept",
        "--scheduler",
    )


def _check_workers(client: Any) -> None:
    """Refuse the workers connected now that cannot import tumblenav or run other code than
    this process (their results could differ from the stored runs'). Workers that connect
    later are checked on each result (:func:`_dask_chunk`)."""
    try:
        theirs = client.run(code_fingerprint, on_error="return")
    except Exception as exc:  # noqa: BLE001 - the scheduler went away: say so, in one line
        raise InputError(
            f"cannot ask the Dask workers their version ({exc})", "--scheduler"
        ) from None
    for worker, fp in sorted(theirs.items()):
        if isinstance(fp, BaseException):
            raise InputError(
                f"Dask worker {worker} cannot run tumblenav ({fp.__class__.__name__}: {fp}): "
                "install the same tumblenav on every machine",
                "--scheduler",
            )
        if fp != code_fingerprint():
            raise _other_code(worker, fp)


def _execute_dask(
    scenario, estimator_name, base_seed, chunks, address: str, record: Callable, con: Console
) -> None:
    """Compute ``chunks`` as Dask tasks (one per chunk, the local runner's chunks) and
    ``record`` (store, here in the parent) each chunk's runs as it comes back: workers need no
    shared filesystem, and only a result that reached the parent is a finished run.

    A worker that dies is Dask's to handle: the scheduler reschedules its chunk on another
    worker (a chunk whose workers died ``distributed.scheduler.allowed-failures`` + 1 times,
    default 4, stops the campaign); chunks already stored are never resubmitted, and a chunk's
    future is released as soon as it is stored so that losing the worker that held it does not
    recompute it. On an interrupt (or any error) the chunks not yet stored are cancelled.
    """
    try:
        from dask.distributed import Client, KilledWorker, as_completed
    except ImportError:
        raise InputError(
            "--scheduler needs dask.distributed: pip install 'tumblenav[cluster]'"
        ) from None
    try:
        client = Client(address, timeout="5s")
    except (OSError, ValueError, TypeError) as exc:  # unreachable, or not an address at all
        raise InputError(f"cannot reach the Dask scheduler ({exc})", address) from None
    with client:
        _check_workers(client)
        if not client.scheduler_info().get("workers"):
            con.print(f"no Dask worker at {address} yet: the runs start when one connects")
        tag = secrets.token_hex(4)  # keys readable on the dashboard, unique to this submit
        futures = {
            client.submit(
                _dask_chunk,
                scenario,
                estimator_name,
                base_seed,
                ks,
                key=f"tumblenav-{estimator_name}-runs-{ks[0]}-{ks[-1]}-{tag}",
                priority=-i,  # in run order, as the local runner
            ): ks
            for i, ks in enumerate(chunks)
        }
        try:
            for fut in as_completed(list(futures)):
                ks = futures.pop(fut)
                try:
                    fp, results = fut.result()
                except CancelledError:  # not by us: the scheduler went away
                    raise InputError(
                        "lost the Dask scheduler (or it cancelled the runs); the stored runs "
                        "are kept: run the same command again to resume",
                        address,
                    ) from None
                except KilledWorker as exc:
                    raise RuntimeError(
                        f"Dask workers died computing runs {ks[0]}-{ks[-1]} ({exc}; out of "
                        "memory?): the stored runs are kept: run the same command again to "
                        "resume"
                    ) from None
                if fp != code_fingerprint():  # a worker that connected after the check
                    raise _other_code(", ".join(client.who_has(fut).get(fut.key, ())), fp)
                fut.release()  # the scheduler forgets it: a lost worker does not recompute it
                record(results)
        finally:
            if futures:  # interrupted or failed: nothing more is computed for this campaign
                client.cancel(list(futures), force=True)


def collect(store: CampaignStore, runs: int) -> tuple[np.ndarray, dict[str, np.ndarray], dict]:
    """Stack the finished runs: t, errors (runs, n) per quantity, NEES and NIS arrays."""
    ks = sorted(k for k in store.done() if k < runs)
    if not ks:
        return np.zeros(0), {}, {}
    loaded = [store.load(k) for k in ks]
    rs = [r for r, _ in loaded]
    t = rs[0].t
    # every quantity any run stored (in the order first seen); a run without it (stored by an
    # estimator path that does not compute it) is NaN there, never a KeyError
    keys = list(dict.fromkeys(key for r in rs for key in r.errors))
    nan = np.full(len(t), np.nan)
    errs = {key: np.stack([r.errors.get(key, nan) for r in rs]) for key in keys}
    cons = {
        "nees": np.stack([r.nees for r in rs]),
        "nees_dof": rs[0].nees_dof,
        "nis": np.stack([r.nis for r in rs]),
        "nis_dof": np.stack([r.nis_dof for r in rs]),
        "runs": ks,
        "diverged": np.array([bool(x.get("skipped_diverged", 0)) for _, x in loaded]),
        "extras": [x for _, x in loaded],
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
        per_axis = metrics.axis_statistics(cons["extras"])
        if per_axis:  # mean and spread of each error component over runs and window epochs
            summary["per_axis"] = per_axis
        summary["runs_diverged"] = int(cons["diverged"].sum())
        # runs that lost track and started again from the measurements (the estimator says so
        # in its skipped counts), and runs whose innovations failed the lost-track alarm
        for key, name in (("reinitialised", "runs_reinitialised"), ("nis_alarm", "runs_nis_alarm")):
            summary[name] = int(sum(bool(x.get(f"skipped_{key}", 0)) for x in cons["extras"]))
        summary["nees"] = metrics.consistency(cons["nees"], cons["nees_dof"], t, window)
        summary["nis"] = metrics.consistency(cons["nis"], cons["nis_dof"], t, window)
        # runs per symmetric frame the truth was compared in (evaluation.alignment.align)
        summary["branches"] = metrics.branch_counts(
            str(x.get("branch", metrics.NOMINAL)) for x in cons["extras"]
        )
        said: dict[str, int] = {}
        for x in cons["extras"]:
            for w in dict.fromkeys(str(v) for v in np.atleast_1d(x.get("warnings", []))):
                said[w] = said.get(w, 0) + 1
        if said:  # each distinct line once, with the number of runs that said it
            summary["estimator_warnings"] = [
                f"{w} ({n} of {summary['runs']} runs)" for w, n in said.items()
            ]
        note = metrics.branch_warning(summary["branches"])
        if note:  # pipeline.assess writes the warnings again: it repeats this line
            summary["warnings"] = [note]
    if failures:
        summary["failed"] = failures[:20]
    return summary
