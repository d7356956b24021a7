"""Fault injection: campaigns interrupted at random points and resumed.

A campaign stopped by SIGINT, SIGTERM or the SIGKILL of a worker process, then resumed, gives
exactly the summary.json of an uninterrupted campaign; the runs stored before the interrupt
are neither lost nor recomputed; no temporary file is left behind; the command exits 130/143
and says what it kept.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tumblenav import cli
from tumblenav.campaign import runner
from tumblenav.campaign.store import CampaignStore
from tumblenav.cli import main
from tumblenav.scenario import load_scenario, scenario_to_yaml

RUNS = 48


@pytest.fixture(scope="module")
def scenario_file(tmp_path_factory) -> Path:
    """hu2024 shortened to 40 s: a run takes a few ms, a campaign a few seconds."""
    s = load_scenario("hu2024").with_updates(
        duration_s=40.0,
        steady_state_window_s=[30.0, 40.0],
        occlusion={"windows": [{"start_s": 20.0, "end_s": 25.0}]},
    )
    p = tmp_path_factory.mktemp("sc") / "short.yaml"
    p.write_text(scenario_to_yaml(s))
    return p


def _args(scenario: Path, out: Path) -> list[str]:
    return [
        "montecarlo",
        str(scenario),
        "-e",
        "ekf-dpacf",
        "--runs",
        str(RUNS),
        "--workers",
        "2",
        "--no-plots",
        "-o",
        str(out),
    ]


def _cli(args: list[str], capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as ei:
        main(args)
    return int(ei.value.code), " ".join(capsys.readouterr().err.split())


CHUNK = 4  # small chunks: a campaign of 48 runs has 12 chunks, done one after another


@pytest.fixture(scope="module")
def reference(scenario_file, tmp_path_factory) -> dict:
    """The uninterrupted campaign's summary.json."""
    out = tmp_path_factory.mktemp("ref") / "mc"
    chunk, runner.BATCH_CHUNK = runner.BATCH_CHUNK, CHUNK
    try:
        with pytest.raises(SystemExit) as ei:
            main(_args(scenario_file, out))
    finally:
        runner.BATCH_CHUNK = chunk
    assert ei.value.code == 0
    return _results(out)


def _results(out: Path) -> dict:
    """summary.json without the command line that made it (its output folder differs)."""
    s = json.loads((out / "summary.json").read_text())
    s.pop("command", None)
    return s


def _children(pid: int) -> list[int]:
    """Child process ids (Linux /proc), without the helpers a test run may have left: the
    multiprocessing resource tracker or forkserver (a Dask LocalCluster's spawn context starts
    one, and it outlives the cluster) is not a campaign worker."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        out.extend(int(x) for x in text)

    def helper(kid: int) -> bool:
        try:
            cmd = Path(f"/proc/{kid}/cmdline").read_bytes()
        except OSError:
            return True  # gone already
        return b"resource_tracker" in cmd or b"forkserver" in cmd

    return [k for k in out if not helper(k)]


def _inject(runs_dir: Path, after: int, fault: str, stop: threading.Event) -> None:
    """Once ``after`` runs are stored, deliver ``fault``: a signal to this process, or the
    SIGKILL of one worker process."""
    while not stop.is_set():
        n = len(list(runs_dir.glob("run_*.npz"))) if runs_dir.is_dir() else 0
        if n >= after:
            if fault == "kill-worker":
                kids = _children(os.getpid())
                if kids:
                    os.kill(kids[0], signal.SIGKILL)
                    return
            else:
                os.kill(os.getpid(), getattr(signal, fault))
                return
        time.sleep(0.002)


def _tmp_files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.name.endswith(".tmp")]


@pytest.mark.parametrize("seed", range(6))
def test_interrupted_campaign_resumes_to_the_same_summary(
    seed, scenario_file, reference, tmp_path, capsys, monkeypatch
):
    monkeypatch.setattr(runner, "BATCH_CHUNK", CHUNK)
    rng = np.random.default_rng(seed)
    fault = ("SIGINT", "SIGTERM", "kill-worker")[seed % 3]
    after = int(rng.integers(1, RUNS - 8))
    out = tmp_path / "mc"
    stop = threading.Event()
    th = threading.Thread(target=_inject, args=(out / "runs", after, fault, stop), daemon=True)
    th.start()
    code, err = _cli(_args(scenario_file, out), capsys)
    stop.set()
    th.join()
    store = CampaignStore(out)
    kept = {k: store.run_path(k).stat().st_mtime_ns for k in store.done()}
    assert not _tmp_files(out), "a half-written file was left behind"
    if fault == "kill-worker":
        # the broken pool is replaced, its chunk redone: the campaign completes by itself
        assert code == 0, err
        assert "a worker process died" in err
        assert len(kept) == RUNS
    else:
        assert code == {"SIGINT": 130, "SIGTERM": 143}[fault], err
        assert f"{len(kept)} of {RUNS} runs are stored" in err
        assert "run the same command again" in err
        assert not (out / "summary.json").exists()
        assert len(kept) >= after  # nothing stored before the interrupt was lost
        code, err = _cli(_args(scenario_file, out), capsys)
        assert code == 0, err
        assert f"{len(kept)} of {RUNS} runs already stored" in err
    # stored runs were not recomputed, and the result is the uninterrupted one, exactly
    assert {k: store.run_path(k).stat().st_mtime_ns for k in kept} == kept
    assert _results(out) == reference


def test_ctrl_c_from_a_terminal_stops_the_command_and_its_workers(scenario_file, tmp_path):
    """SIGINT to the whole process group, as a terminal sends it: exit 130, the message says
    what was kept, no worker is left running."""
    out = tmp_path / "mc"
    args = _args(scenario_file, out)
    args[args.index(str(RUNS))] = "5000"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tumblenav.cli", *args],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # its own process group, like a terminal's foreground job
    )
    try:
        deadline = time.monotonic() + 120
        while not list((out / "runs").glob("run_*.npz")) if (out / "runs").is_dir() else True:
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "no run stored in 120 s"
            time.sleep(0.05)
        workers = _children(proc.pid)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "interrupted (SIGINT)" in err and "runs are stored in" in err
    assert "Traceback" not in err
    for pid in workers:
        assert not Path(f"/proc/{pid}").exists() or "zombie" in _state(pid)
    assert not _tmp_files(out)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split("\n")[0].lower()
    except (OSError, IndexError):
        return "gone"


def test_a_workers_warnings_are_printed_as_the_command_prints_its_own(capsys):
    # a worker process's warnings (e.g. ukf-gp's "no usable GP ...") as one line, without
    # Python's "path:line: UserWarning:" and the source line beneath it
    import warnings

    previous = warnings.showwarning
    try:
        warnings.showwarning = runner._show_warning
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.warn("no usable GP for feature(s) [1, 2]: pure propagation", stacklevel=1)
    finally:
        warnings.showwarning = previous
    err = capsys.readouterr().err
    assert err == "warning: no usable GP for feature(s) [1, 2]: pure propagation\n"


def test_an_exit_that_hangs_after_the_interruption_still_ends_with_its_status():
    """After an interruption the command's exit may wait on a pool's thread without a time
    limit (concurrent.futures' exit hook); the watchdog ends the process with the interrupted
    status instead. Here a thread that never ends stands for it."""
    code = (
        "import threading, time\n"
        "from tumblenav import cli\n"
        "threading.Thread(target=time.sleep, args=(3600,)).start()  # not a daemon: exit waits\n"
        "cli._exit_within(0.5, 130)\n"
        "raise SystemExit(130)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130, proc.stderr


_TWICE = (
    "import os, signal, sys, time\n"
    "from tumblenav import cli\n"
    "from tumblenav.errors import Interrupted\n"
    "cli._install_signal_handlers()\n"
    "try:\n"
    "    os.kill(os.getpid(), signal.SIGINT)\n"
    "    time.sleep(5)\n"
    "except Interrupted:\n"
    "    pass\n"
    "time.sleep({gap})\n"
    "os.kill(os.getpid(), signal.SIGINT)\n"
    "time.sleep(0.2)\n"
    "print('cleanup finished', flush=True)\n"
    "raise SystemExit(130)\n"
)


def test_one_interruption_delivered_twice_still_runs_the_cleanup():
    """GNU timeout signals the process, then its process group (the process again): the copy,
    microseconds later, is the same interruption, so the cleanup runs and prints its message
    (it used to end the process at once, silently, in 2 of 6 tries)."""
    proc = subprocess.run(
        [sys.executable, "-c", _TWICE.format(gap=0.0)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 130, proc.stderr
    assert "cleanup finished" in proc.stdout
    assert "interrupted again" not in proc.stderr


def test_a_second_interruption_ends_the_process_at_once_and_says_so():
    proc = subprocess.run(
        [sys.executable, "-c", _TWICE.format(gap=2 * cli.SAME_INTERRUPTION_S)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 130, proc.stderr
    assert "cleanup finished" not in proc.stdout
    assert "interrupted again (SIGINT): stopping at once" in proc.stderr
