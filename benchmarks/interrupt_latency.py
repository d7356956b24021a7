"""How fast a campaign stops on SIGINT / SIGTERM, and what it keeps.

Starts ``tumblenav montecarlo hu2024 --runs 5000`` in its own process group, waits until some
runs are stored plus ``--after`` seconds, sends the signal to the group (as a terminal does for
Ctrl-C) and measures the time until the command has exited, with its exit status and the runs
it kept (tests/test_interrupts.py checks that resuming recomputes none of them).

Usage: python benchmarks/interrupt_latency.py [--after 3] [--workers 2]
Last line: ``sigint_s=<stop time> sigterm_s=<stop time> codes=<SIGINT>,<SIGTERM>``
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def stop_time(sig: int, out: Path, after: float, workers: int) -> tuple[float, int, int, str]:
    cmd = [
        sys.executable,
        "-m",
        "tumblenav.cli",
        "montecarlo",
        "hu2024",
        "--runs",
        "5000",
        "--workers",
        str(workers),
        "--no-plots",
        "-o",
        str(out),
    ]
    proc = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, start_new_session=True
    )
    runs = out / "runs"
    while not (runs.is_dir() and any(runs.glob("run_*.npz"))):
        if proc.poll() is not None:
            raise SystemExit(proc.stderr.read())
        time.sleep(0.05)
    time.sleep(after)
    os.killpg(proc.pid, sig)
    t0 = time.perf_counter()
    _, err = proc.communicate()
    dt = time.perf_counter() - t0
    kept = len(list(runs.glob("run_*.npz")))
    return dt, proc.returncode, kept, " ".join(err.split()[-30:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--after", type=float, default=3.0)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for sig in (signal.SIGINT, signal.SIGTERM):
            out = Path(tmp) / sig.name
            dt, code, kept, msg = stop_time(sig, out, args.after, args.workers)
            print(
                f"{sig.name}: stopped {dt:.2f} s after the signal, exit {code}, {kept} runs "
                f"kept; said: ...{msg[-160:]}"
            )
            res[sig.name] = (dt, code)
    print(
        f"sigint_s={res['SIGINT'][0]:.2f} sigterm_s={res['SIGTERM'][0]:.2f} "
        f"codes={res['SIGINT'][1]},{res['SIGTERM'][1]}"
    )


if __name__ == "__main__":
    main()
