"""Plane extraction speed (Yu 2019 Table 1's hardest case): 2500-point cloud with 1250 outliers.

Times tumblenav's RANSAC (``tumblenav.frontends.planes.ransac_plane``, distance threshold 0.005,
at most 300 iterations, adaptive stop of Yu 2019 eq. 2) and, when it is installed, Open3D's
``segment_plane`` on the same cloud with the same threshold and iteration limit.
Open3D is a benchmark-only reference: ``pip install 'tumblenav[bench]'`` (about 600 MB).

Usage: python benchmarks/plane_extraction.py [--repeats 101]
Last line: ``ms=<ours, median> open3d_ms=<Open3D, median or nan> extracted=<points>``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tumblenav.frontends.planes import ransac_plane
from tumblenav.papers.yu2019 import ITERATIONS, THRESHOLD_CM, with_outliers


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=101)
    args = ap.parse_args()
    cloud = with_outliers(2500, 1250, np.random.default_rng([2019, 1250]))
    ours, counts = [], []
    for r in range(args.repeats):
        t0 = time.perf_counter()
        fit = ransac_plane(cloud, THRESHOLD_CM, np.random.default_rng(r), max_iterations=ITERATIONS)
        ours.append((time.perf_counter() - t0) * 1e3)
        counts.append(fit.n_inliers)
    o3d_ms = float("nan")
    try:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
        times, o3d_counts = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            _, idx = pcd.segment_plane(THRESHOLD_CM, 3, ITERATIONS)
            times.append((time.perf_counter() - t0) * 1e3)
            o3d_counts.append(len(idx))
        o3d_ms = float(np.median(times))
        print(
            f"open3d {o3d.__version__}: median {o3d_ms:.3f} ms, extracted "
            f"{int(np.median(o3d_counts))} points"
        )
    except ImportError:
        print("open3d not installed: pip install 'tumblenav[bench]' for the reference timing")
    print(
        f"tumblenav: median {np.median(ours):.3f} ms, extracted {int(np.median(counts))} points "
        f"(Yu 2019 Table 1: 1252 points in 70 ms)"
    )
    print(f"ms={np.median(ours):.3f} open3d_ms={o3d_ms:.3f} extracted={int(np.median(counts))}")


if __name__ == "__main__":
    main()
