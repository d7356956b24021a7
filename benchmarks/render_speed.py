"""Stereo renderer speed (tumblenav.sensors.render): stereo pairs per second at 1024 x 1024.

The issue's target: >= 5 stereo pairs/s on 2 cores with the target filling most of the view
(fx = 1623.86 px, 35 deg FOV, convergent rig b = 0.92 m, 10 deg toe-in, target at ~3 m).
A tumbling procedural satellite (1 deg of rotation a frame) is rendered with the default
settings (noise on, truth maps on) at each range; the rate is one over the median time a pair
(robust to other processes on a shared machine); the last line is
``render_pairs_s=<pairs/s at the first range>``.

    .venv/bin/python benchmarks/render_speed.py [--ranges 3 8] [--frames 20] [--threads 2]
        [--supersample 1] [--no-truth] [--no-noise] [--save-png docs/results/chang2021]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from tumblenav.sensors.image_noise import ImageNoise
from tumblenav.sensors.render import RenderSettings, StereoRenderer
from tumblenav.sensors.stereo import convergent_rig
from tumblenav.target_model import procedural_satellite


def bench_rig(size: int = 1024):
    """Chang 2021 text rig: 1024 px, 35 deg FOV (f = 512 / tan 17.5 deg = 1623.86 px)."""
    return convergent_rig(1623.86 * size / 1024, 0.92, np.deg2rad(10.0), (size, size))


def poses(range_m: float, frames: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A tumbling target between the two boresights at ``range_m`` (M origin in C)."""
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    start = Rotation.from_euler("xyz", [-60, 10, 25], degrees=True)
    p = np.array([0.46, range_m, 0.0])
    return [
        ((Rotation.from_rotvec(np.radians(1.0 * k) * axis) * start).as_matrix(), p)
        for k in range(frames)
    ]


def save_pair(out, range_m: float, folder: str) -> None:
    """Left | right side by side (a 4-px grey bar between), and FAST corners (threshold 20)."""
    import cv2

    left, right = out.images
    bar = np.full((left.shape[0], 4), 128, np.uint8)
    path = Path(folder) / f"render_{range_m:g}m.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.hstack([left, bar, right]))
    fast = cv2.FastFeatureDetector_create(20, True, cv2.FastFeatureDetector_TYPE_9_16)
    n = [len(fast.detect(im)) for im in (left, right)]
    print(f"saved {path}: FAST (threshold 20) corners left {n[0]}, right {n[1]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ranges", type=float, nargs="+", default=[3.0, 8.0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--supersample", type=int, default=1)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--no-truth", action="store_true")
    ap.add_argument("--no-noise", action="store_true")
    ap.add_argument("--save-png", metavar="DIR", help="save each range's first pair as a PNG")
    args = ap.parse_args()

    settings = RenderSettings(
        supersample=args.supersample,
        threads=args.threads,
        noise=None if args.no_noise else ImageNoise(read_noise_e=20.0),
    )
    model = procedural_satellite()
    rig = bench_rig(args.size)
    t0 = time.perf_counter()
    renderer = StereoRenderer(model, rig, settings)
    print(f"scene build {1e3 * (time.perf_counter() - t0):.0f} ms (cached per model)")
    sun_C = np.array([0.5, -0.6, -0.6])
    print(
        f"cores={os.cpu_count()} size={args.size} threads={args.threads} "
        f"supersample={args.supersample} truth={not args.no_truth} noise={not args.no_noise}"
    )
    rates = []
    for range_m in args.ranges:
        rng = np.random.default_rng(0)
        seq = poses(range_m, args.frames + 2)
        for R_CM, p in seq[:2]:  # warm-up: compiled kernels, allocations
            renderer.render(R_CM, p, sun_C, rng, truth=not args.no_truth)
        cover, times = [], []
        for R_CM, p in seq[2:]:
            t0 = time.perf_counter()
            out = renderer.render(R_CM, p, sun_C, rng, truth=not args.no_truth)
            times.append(time.perf_counter() - t0)
            if out.mask is not None:
                cover.append(float(np.mean(out.mask)))
            if args.save_png and len(times) == 1:
                save_pair(out, range_m, args.save_png)
        # the median pair: robust to other processes on a shared machine
        med, mean = float(np.median(times)), float(np.mean(times))
        rate = 1.0 / med
        rates.append(rate)
        cov = f", target pixels {100 * np.mean(cover):.0f}%" if cover else ""
        print(
            f"range {range_m:g} m: median {1e3 * med:.1f} ms/pair ({rate:.2f} pairs/s), "
            f"mean {1e3 * mean:.1f} ms, min {1e3 * min(times):.1f} ms{cov}"
        )
    print(f"render_pairs_s={rates[0]:.2f}")


if __name__ == "__main__":
    main()
