"""Chang 2021 speed targets in one line: rendering (stereo pairs/s on both cores, 1024 x 1024,
the target filling most of the view at 3 m) and the image front end (ms per pair on one core,
120 features; the OpenCV calls alone and the compiled ECC kernel alone).

Runs the two benchmarks that measure each part (benchmarks/render_speed.py and
benchmarks/image_frontend.py, see them for the details and options), then times the renderer
as a campaign worker uses it: one thread (``TUMBLENAV_RENDER_THREADS=1``), the frames of a
``chang2021_close`` run (``--close-pairs`` pairs spread over the run, its noise chain, no truth
maps), the minimum over ``--repeats`` passes of the wall and CPU time per pair (the machine may
be shared: the minimum is the least disturbed pass).  It ends with

    render_pairs_s=<pairs per s, 2 cores> frontend_ms=<per pair, 1 core> opencv_only_ms=<...>
    ecc_kernel_ms=<...>

(``opencv_only_ms``: the OpenCV calls of the front end; ``ecc_kernel_ms``: the affine
refinements' compiled ECC, stereo_images.ecc_kernel, which replaced OpenCV's findTransformECC:
see benchmarks/image_frontend.py.)

Usage: python benchmarks/chang2021_speed.py [--frames 20] [--pairs 200] [--close-pairs 20]
    [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def last_line(cmd: list[str], env: dict[str, str] | None = None) -> str:
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
    lines = [ln for ln in out.splitlines() if ln.strip()]
    for ln in lines[:-1]:
        print("  " + ln)
    return lines[-1]


def close_range_pairs(pairs: int, repeats: int) -> None:
    """One-thread render time per pair of chang2021_close's frames (run in a subprocess whose
    environment pins one thread); prints ``close_render_ms=<wall> cpu_ms=<cpu> ...``."""
    import time

    from tumblenav import simulation
    from tumblenav.scenario import load_scenario

    scenario = load_scenario("chang2021_close")
    _, meas = simulation.simulate(scenario, 0)
    frames = meas.source
    assert isinstance(frames, simulation.RenderedFrames)
    epochs = np.linspace(0, len(frames) - 1, pairs).round().astype(int)
    frames.pair(int(epochs[0]))  # compiled shader and scene loaded
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for k in epochs:
            frames.pair(int(k))
        wall.append((time.perf_counter() - t0) / pairs * 1e3)
        cpu.append((time.process_time() - c0) / pairs * 1e3)
    print(
        f"close_render_ms={min(wall):.1f} cpu_ms={min(cpu):.1f} (min of {repeats}; "
        f"wall {' '.join(f'{w:.1f}' for w in wall)}; {pairs} pairs, 1024 x 1024, one thread)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="rendered pairs per range")
    ap.add_argument("--pairs", type=int, default=200, help="front-end pairs timed")
    ap.add_argument("--close-pairs", type=int, default=20, help="chang2021_close pairs timed")
    ap.add_argument("--repeats", type=int, default=3, help="passes over the close-range pairs")
    ap.add_argument("--close-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.close_only:
        close_range_pairs(args.close_pairs, args.repeats)
        return
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
    ms = re.search(r"frontend_ms=([\d.]+) opencv_only_ms=([\d.]+) ecc_kernel_ms=([\d.]+)", fe)
    assert ms is not None, fe
    print("rendering chang2021_close frames as a campaign worker does (one thread, no truth maps):")
    single = {**one_core, "TUMBLENAV_RENDER_THREADS": "1"}
    close = last_line(
        [
            py,
            str(Path(__file__).resolve()),
            "--close-only",
            "--close-pairs",
            str(args.close_pairs),
            "--repeats",
            str(args.repeats),
        ],
        env=single,
    )
    print("  " + close)
    print(
        f"render_pairs_s={rate:.2f} frontend_ms={float(ms[1]):.2f} "
        f"opencv_only_ms={float(ms[2]):.2f} ecc_kernel_ms={float(ms[3]):.2f}"
    )


if __name__ == "__main__":
    main()
