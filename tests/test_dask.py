"""Campaigns on a Dask cluster (``--scheduler ADDRESS``) against a LocalCluster on loopback:
two worker processes, as on two machines that share nothing but the network.

The same stored runs and summary.json as the local runner; a worker killed mid-campaign loses
no finished run and redoes none; a second submit computes only the missing chunks; an
interrupt cancels the chunks in flight and keeps the stored runs; workers that run other
tumblenav code are refused.
"""

from __future__ import annotations

import io
import json
import os
import signal
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from tumblenav.campaign import runner
from tumblenav.campaign.store import CampaignStore
from tumblenav.cli import main
from tumblenav.errors import InputError
from tumblenav.scenario import Scenario, load_scenario, scenario_to_yaml

distributed = pytest.importorskip("distributed")


class _Log(distributed.diagnostics.plugin.SchedulerPlugin):
    """Every task transition the scheduler makes: which chunks were computed, and how often."""

    def __init__(self) -> None:
        self.events: list[tuple[str, str, str]] = []

    def transition(self, key, start, finish, *args, **kwargs) -> None:
        self.events.append((str(key), start, finish))

    def computed(self) -> Counter:
        """Chunk ``(first, last)`` -> times it went to memory (a result computed)."""
        return Counter(_runs(k) for k, _, f in self.events if f == "memory")

    def started(self, key: str) -> int:
        return sum(1 for k, _, f in self.events if k == key and f == "processing")


def _runs(key: str) -> tuple[int, int]:
    """``tumblenav-ESTIMATOR-runs-FIRST-LAST-TAG`` -> (FIRST, LAST)."""
    first, last = key.rsplit("-runs-", 1)[1].split("-")[:2]
    return int(first), int(last)


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        silence_logs=40,  # the killed worker's errors are expected
    ) as c:
        yield c


@pytest.fixture
def log(cluster):
    plugin = _Log()
    cluster.scheduler.add_plugin(plugin, name="tumblenav-test-log")
    yield plugin
    cluster.scheduler.remove_plugin(name="tumblenav-test-log")


def _short() -> Scenario:
    """hu2024 shortened to 70 s (occlusion 40-50 s): a run takes about 25 ms."""
    return load_scenario("hu2024").with_updates(
        duration_s=70.0,
        steady_state_window_s=[60.0, 70.0],
        occlusion={"windows": [{"start_s": 40.0, "end_s": 50.0}]},
    )


def _stored(out: Path) -> dict[int, int]:
    """Stored run -> its file's mtime (ns)."""
    store = CampaignStore(out)
    return {k: store.run_path(k).stat().st_mtime_ns for k in store.done()}


def _quiet() -> Console:
    return Console(file=io.StringIO(), width=120)


def _assert_close(a, b, path: str = "summary") -> None:
    """Equal structure and strings; numbers equal to 1e-7 relative (NaN equal to NaN)."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            _assert_close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) or isinstance(b, float):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-15, err_msg=path)
    else:
        assert a == b, path


def test_same_runs_and_summary_as_the_local_runner(cluster, log, tmp_path):
    """The same chunks (2 runs each, over 2 worker processes) give the same arithmetic: every
    stored array and the summary equal the local runner's to 1e-7 (relative). Not to the bit:
    the local workers fork from a parent that compiled the numba kernels, the Dask workers
    (spawned) load or compile them themselves, and a freshly compiled kernel and a cached one
    differ at rounding level: measured in a fresh clone 1e-12 relative on per-axis error means
    and 1.2e-9 on a NEES (it goes through the inverse covariance); a per-axis error sum is
    compared against its summands' magnitude (it cancels); in a warm working tree the two
    are equal to the bit."""
    sc = _short()
    con = _quiet()
    d = runner.run_campaign(
        sc, "ekf-dpacf", 6, tmp_path / "dask", scheduler=cluster.scheduler_address,
        console=con, chunk_size=2,
    )  # fmt: skip
    loc = runner.run_campaign(
        sc, "ekf-dpacf", 6, tmp_path / "local", workers=2, console=_quiet(), chunk_size=2
    )
    assert d["runs"] == 6 and d["runs_failed"] == 0
    _assert_close(d, loc)
    assert log.computed() == {(0, 1): 1, (2, 3): 1, (4, 5): 1}
    for k in range(6):
        with (
            np.load(CampaignStore(tmp_path / "dask").run_path(k)) as a,
            np.load(CampaignStore(tmp_path / "local").run_path(k)) as b,
        ):
            assert a.files == b.files
            for name in a.files:
                if a[name].dtype.kind in "USO":  # text (the branch, warnings): the same
                    assert np.array_equal(a[name], b[name]), f"run {k} {name}"
                    continue
                # float32 arrays (per-axis errors) round a 1e-12 difference up to one ulp
                rtol = 1e-6 if a[name].dtype == np.float32 else 1e-7
                atol = 1e-12
                stem = name[: -len("_sum")]
                if name.endswith("_sum") and f"{stem}_sq" in a.files and f"{stem}_n" in a.files:
                    # a signed sum cancels: its rounding is relative to the summands'
                    # magnitude, sqrt(n sum e^2) >= sum |e|, not to the sum (a fresh clone
                    # measured 4.4e-12 on a sum of -3.3e-5, 1.3e-7 of it, twenty-second
                    # session, after ekf-dpacf's constraint by projection)
                    atol = rtol * float(np.sqrt(b[f"{stem}_n"] * b[f"{stem}_sq"]))
                np.testing.assert_allclose(
                    a[name], b[name], rtol=rtol, atol=atol, err_msg=f"run {k} {name}"
                )
    # the local runner's progress bar, filled
    assert "hu2024 / ekf-dpacf" in con.file.getvalue() and "6/6" in con.file.getvalue()


def test_second_submit_computes_only_the_missing_chunks(cluster, log, tmp_path):
    sc = _short()
    out = tmp_path / "mc"
    first = runner.run_campaign(
        sc, "ekf-dpacf", 8, out, scheduler=cluster.scheduler_address, console=_quiet(),
        chunk_size=2,
    )  # fmt: skip
    store = CampaignStore(out)
    for k in (4, 5):  # a chunk that an interrupted campaign did not finish
        store.run_path(k).unlink()
    kept = _stored(out)
    log.events.clear()
    con = _quiet()
    again = runner.run_campaign(
        sc, "ekf-dpacf", 8, out, scheduler=cluster.scheduler_address, console=con,
        chunk_size=2,
    )  # fmt: skip
    assert "6 of 8 runs already stored, 2 to do" in " ".join(con.file.getvalue().split())
    assert log.computed() == {(4, 5): 1}
    assert {k: v for k, v in _stored(out).items() if k in kept} == kept
    assert again == first


def _kill_a_busy_worker(cluster, out: Path, pids: dict, stop: threading.Event, seen: dict):
    """Once a run is stored, SIGKILL a worker process while it has chunks to compute;
    ``seen`` gets the stored runs' mtimes just before and the keys of those chunks."""
    while not stop.is_set():
        if _stored(out):
            try:  # the scheduler's state, read from another thread: retry if it changed
                workers = [(a, [ts.key for ts in ws.processing]) for a, ws in
                           list(cluster.scheduler.workers.items())]  # fmt: skip
            except RuntimeError:
                continue
            for addr, busy in workers:
                if busy and addr in pids:
                    seen.update(stored=_stored(out), keys=set(busy))
                    os.kill(pids[addr], signal.SIGKILL)
                    return
        time.sleep(0.002)


def test_killed_worker_loses_no_finished_run_and_redoes_none(cluster, log, tmp_path, monkeypatch):
    """SIGKILL of a worker process mid-campaign: Dask reschedules its chunk, the campaign
    completes; the runs stored before keep their files, every run is written once."""
    sc = load_scenario("hu2024")  # 200 s: a chunk of 8 runs takes about 0.3 s
    out = tmp_path / "mc"
    writes: Counter = Counter()
    save = runner.CampaignStore.save_run

    def counted(self, k, *args, **kwargs):
        writes[k] += 1
        return save(self, k, *args, **kwargs)

    monkeypatch.setattr(runner.CampaignStore, "save_run", counted)
    with distributed.Client(cluster) as client:
        pids = client.run(os.getpid)
    stop, seen = threading.Event(), {}
    th = threading.Thread(
        target=_kill_a_busy_worker, args=(cluster, out, pids, stop, seen), daemon=True
    )
    th.start()
    try:
        s = runner.run_campaign(
            sc, "ekf-dpacf", 64, out, scheduler=cluster.scheduler_address, console=_quiet(),
            chunk_size=8,
        )  # fmt: skip
    finally:
        stop.set()
        th.join()
    assert seen, "no worker was killed"
    assert s["runs"] == 64 and s["runs_failed"] == 0
    assert {k: v for k, v in _stored(out).items() if k in seen["stored"]} == seen["stored"]
    assert writes == Counter(range(64))  # each run written once, by the parent
    # the chunks the dead worker held were rescheduled; none whose runs were all stored
    # before the kill was computed again. Which other chunks were redone is a race, not
    # asserted: the scheduler may just have handed the dead worker another chunk, or the
    # worker may have finished one whose result died with it before the command fetched it
    # (seen in a fresh clone: chunk 0-7 computed twice, stored once)
    restarted = {k for k, _, _ in log.events if log.started(k) > 1}
    assert restarted & seen["keys"]
    redone = {_runs(k) for k in restarted} | {r for r, c in log.computed().items() if c > 1}
    for first, last in redone:
        assert not all(k in seen["stored"] for k in range(first, last + 1)), (first, last)
    assert set(log.computed()) == {(f, f + 7) for f in range(0, 64, 8)}
    assert not [p for p in out.rglob("*.tmp")]


def test_ctrl_c_cancels_the_chunks_and_keeps_the_stored_runs(cluster, log, tmp_path, capsys):
    """SIGINT during ``montecarlo --scheduler``: exit 130 with the local runner's message,
    the chunks not stored are cancelled on the cluster, the stored runs stay; the same
    command again finishes the campaign without recomputing them."""
    sc = tmp_path / "short.yaml"
    sc.write_text(scenario_to_yaml(_short()))
    out = tmp_path / "mc"
    args = [
        "montecarlo", str(sc), "-e", "ekf-dpacf", "--runs", "160", "--no-plots",
        "--scheduler", cluster.scheduler_address, "-o", str(out),
    ]  # fmt: skip

    def interrupt() -> None:  # once a chunk (16 runs) is stored
        while len(_stored(out)) < 16:
            time.sleep(0.002)
        os.kill(os.getpid(), signal.SIGINT)

    th = threading.Thread(target=interrupt, daemon=True)
    th.start()
    with pytest.raises(SystemExit) as ei:
        main(args)
    th.join()
    err = " ".join(capsys.readouterr().err.split())
    kept = _stored(out)
    assert ei.value.code == 130, err
    assert f"interrupted (SIGINT): {len(kept)} of 160 runs are stored in {out}" in err
    assert "run the same command again" in err and "Traceback" not in err
    assert 0 < len(kept) < 160 and not (out / "summary.json").exists()
    deadline = time.monotonic() + 10  # cancelled: the scheduler forgets every chunk
    while any("tumblenav-" in str(k) for k in cluster.scheduler.tasks):
        assert time.monotonic() < deadline, list(cluster.scheduler.tasks)
        time.sleep(0.05)
    log.events.clear()
    with pytest.raises(SystemExit) as ei:
        main(args)
    err = " ".join(capsys.readouterr().err.split())
    assert ei.value.code == 0, err
    assert f"{len(kept)} of 160 runs already stored" in err
    assert {k: v for k, v in _stored(out).items() if k in kept} == kept
    # chunks stored whole are not computed again (one stored in part, when the interrupt
    # came while the parent wrote it, is redone whole and its stored runs are not rewritten)
    whole = {f for f in range(0, 160, 16) if set(range(f, f + 16)) <= set(kept)}
    assert whole and not whole & {first for first, _ in log.computed()}
    assert len(log.computed()) == 10 - len(whole)
    assert json.loads((out / "summary.json").read_text())["runs"] == 160


@pytest.mark.parametrize("when", ["connected", "joined later"])
def test_workers_with_other_code_are_refused(cluster, tmp_path, monkeypatch, when):
    """A worker whose tumblenav differs (code_fingerprint) is refused before any run is stored:
    at the start for the workers connected then, at its first result for one that connects
    later."""
    if when == "joined later":  # skip the check at the start: the results are checked too
        monkeypatch.setattr(runner, "_check_workers", lambda client: None)
    set_fp = "import tumblenav.campaign.store as s; s._FINGERPRINT[:] = {}"
    with distributed.Client(cluster) as client:
        client.run(exec, set_fp.format("['0.0-other+000000000000']"))
        try:
            with pytest.raises(InputError, match="runs other tumblenav code .0.0-other"):
                runner.run_campaign(
                    _short(), "ekf-dpacf", 4, tmp_path / "mc",
                    scheduler=cluster.scheduler_address, console=_quiet(), chunk_size=2,
                )  # fmt: skip
        finally:
            client.run(exec, set_fp.format("[]"))
    assert not CampaignStore(tmp_path / "mc").done()


def test_lost_scheduler_is_one_line_and_keeps_the_stored_runs(tmp_path):
    """The scheduler goes away mid-campaign: a one-line error (exit 2 from the CLI) saying
    that the stored runs are kept, instead of Dask's cancelled futures."""
    import dask

    out = tmp_path / "mc"
    with (
        dask.config.set({"distributed.comm.timeouts.connect": "1s"}),
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, host="127.0.0.1",
            protocol="tcp://", silence_logs=50,
            # its HTTP server (there even without a dashboard) on any port: the module's
            # cluster has the default one
            dashboard_address=":0", worker_dashboard_address=None,
        ) as c,
    ):  # fmt: skip

        def close() -> None:
            while not _stored(out):
                time.sleep(0.002)
            c.close()

        th = threading.Thread(target=close, daemon=True)
        th.start()
        with pytest.raises(InputError, match="lost the Dask scheduler.*stored runs are kept"):
            runner.run_campaign(
                _short(), "ekf-dpacf", 64, out, scheduler=c.scheduler_address,
                console=_quiet(), chunk_size=2,
            )  # fmt: skip
        th.join()
    assert 0 < len(_stored(out)) < 64
