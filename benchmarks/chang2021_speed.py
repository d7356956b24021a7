"""Chang 2021 speed targets in one line: rendering (stereo pairs/s on both cores, 1024 x 1024,
the target filling most of the view at 3 m) and the image front end (ms per pair on one core,
120 features, and the OpenCV calls alone).

Runs the two benchmarks that measure each part (benchmarks/render_speed.py and
benchmarks/image_frontend.py, see them for the details and options) and ends with

    render_pairs_s=<pairs per s, 2 cores> frontend_ms=<per pair, 1 core> opencv_only_ms=<...>

Usage: python benchmarks/chang2021_speed.py [--frames 20] [--pairs 200]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def last_line(cmd: list[str], env: dict[str, str] | None = None) -> str:
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
    lines = [ln for ln in out.splitlines() if ln.strip()]
    for ln in lines[:-1]:
        print("  " + ln)
    return lines[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="rendered pairs per range")
    ap.add_argument("--pairs", type=int, default=200, help="front-end pairs timed")
    args = ap.parse_args()
    py = sys.executable
    print("rendering, 2 threads, 1024 x 1024, target at 3 m (benchmarks/render_speed.py):")
    render = last_line(
        [py, str(HERE / "render_speed.py"), "--ranges", "3", "--frames", str(args.frames)]
    )
    rate = float(re.search(r"render_pairs_s=([\d.]+)", render).group(1))  # type: ignore[union-attr]
    print("image front end, one core, 120 features at 6 m (benchmarks/image_frontend.py):")
    one_core = {**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    fe = last_line(
        [
            py,
            str(HERE / "image_frontend.py"),
            "--timing-only",
            "--timing-pairs",
            str(args.pairs),
        ],
        env=one_core,
    )
    ms = re.search(r"frontend_ms=([\d.]+) opencv_only_ms=([\d.]+)", fe)
    assert ms is not None, fe
    print(
        f"render_pairs_s={rate:.2f} frontend_ms={float(ms[1]):.2f} opencv_only_ms={float(ms[2]):.2f}"
    )


if __name__ == "__main__":
    main()
