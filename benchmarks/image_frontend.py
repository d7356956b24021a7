"""Image front end (frontends/stereo_images): accuracy against the renderer's truth, and speed.

Scene: the procedural satellite (sensors.render.StereoRenderer, procedural texture, sun, shot
noise) seen by Chang 2021's convergent rig (0.92 m baseline, 10 deg toe-in per camera), preset
"text" (1024 x 1024, f = 1623.86 px, c = 512 px: 35 deg) or "table1" (1280 x 1280,
f = 2029.8 px, sensors.chang2021_rig()), at a fixed range on the rig's bisector, tumbling at
Chang 2021's rate (-0.04, -0.06, -0.05) rad/s (Sec. 3.1), 10 Hz.

Accuracy per range (truth from the renderer's left depth map, bilinear at the feature's left
pixel, where the four neighbours agree to 1 %):
  outlier rate  -- right pixel more than 2 px from the true correspondence (points the right
                   camera sees: the right depth map agrees with the point);
  match error   -- median / p95 of that distance over the inliers (px);
  depth error   -- triangulated depth along the left axis minus the truth (m), median |.| and
                   p95 |.|, against sigma_z = z^2 / (f b) per px of disparity;
  drift         -- left pixel of a track minus the projection of the surface point it started
                   on (px), at track ages 10, 30, 60, 100 (LK drift: what limits the age cap);
  track length, features held per frame.
Speed (one core: cv2.setNumThreads(1)): wall time of ImageTracker.step per pair over >= 100
pairs of the range given by --timing-range-m, and, in a second pass, the time spent inside the
compiled calls the front end makes, each wrapped by a timer:
  OpenCV calls   -- FAST detect, calcOpticalFlowPyrLK, remap, matchTemplate, getRectSubPix
                    (and findTransformECC, which the front end no longer calls: the affine
                    refinement's ECC was OpenCV's until it moved to the compiled kernel below);
  ECC kernel     -- stereo_images.ecc_kernel.ecc_affine (numba), the affine refinements' ECC
                    for all the features of one refine_affine call.
What lies outside both is Python (numpy glue, the per-feature loops that remain).

Run:  .venv/bin/python benchmarks/image_frontend.py [--pairs 120] [--ranges-m 3 6 10]
      [--tuning '{"template_refine": false}']
The last line reads ``frontend_ms=<per pair, 1 core> opencv_only_ms=<OpenCV calls alone>
ecc_kernel_ms=<the compiled ECC alone>``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "2")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from tumblenav.frontends.stereo_images import (  # noqa: E402
    EpipolarGeometry,
    ImageFrontEndTuning,
    ImageTracker,
)
from tumblenav.frontends.stereo_images import refine as refine_module  # noqa: E402
from tumblenav.sensors.render import RenderSettings, StereoRenderer  # noqa: E402
from tumblenav.sensors.stereo import StereoRig, chang2021_rig, convergent_rig  # noqa: E402
from tumblenav.target_model import procedural_satellite  # noqa: E402

OMEGA_M = np.array([-0.04, -0.06, -0.05])  # Chang 2021 Sec. 3.1, rad/s (body rates)
DT_S = 0.1  # 10 Hz: tumblenav default (Chang 2021 silent)
SUN_C = np.array([0.4, -1.0, -0.5])  # towards the sun, behind the chaser, up and left


def make_rig(preset: str) -> StereoRig:
    if preset == "table1":
        return chang2021_rig()
    return convergent_rig(1623.86, 0.92, np.radians(10.0), (1024, 1024), (512.0, 512.0))


def render_sequence(rig: StereoRig, range_m: float, n: int, seed: int) -> list[dict[str, Any]]:
    renderer = StereoRenderer(procedural_satellite(), rig, RenderSettings())
    rng = np.random.default_rng(seed)
    R0 = Rotation.from_euler("xyz", [25.0, -35.0, 15.0], degrees=True).as_matrix()
    p = np.array([rig.baseline_m / 2, range_m, 0.0])
    out = []
    for k in range(n):
        R_CM = R0 @ Rotation.from_rotvec(OMEGA_M * DT_S * k).as_matrix()
        pair = renderer.render(R_CM, p, SUN_C, rng, truth=True)
        out.append(
            {
                "images": pair.images,
                "depth": pair.depth_m,
                "R_CM": R_CM,
                "p_MinC": p,
            }
        )
    return out


def _bilinear_depth(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth at tumblenav pixels (centres at i + 0.5); NaN where the 4 neighbours disagree."""
    h, w = depth.shape
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    i0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    j0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = x - i0, y - j0
    q = np.stack(
        [depth[j0, i0], depth[j0, i0 + 1], depth[j0 + 1, i0], depth[j0 + 1, i0 + 1]], axis=1
    ).astype(float)
    val = (
        q[:, 0] * (1 - fx) * (1 - fy)
        + q[:, 1] * fx * (1 - fy)
        + q[:, 2] * (1 - fx) * fy
        + q[:, 3] * fx * fy
    )
    smooth = np.all(np.isfinite(q), axis=1) & (np.ptp(q, axis=1) < 0.01 * np.nanmin(q, axis=1))
    return np.where(smooth, val, np.nan)


def accuracy(rig: StereoRig, seq: list[dict[str, Any]], tuning: ImageFrontEndTuning) -> dict:
    geo = EpipolarGeometry(rig)
    tracker = ImageTracker(rig, tuning)
    f, b = rig.left.focal_px, rig.baseline_m
    match_err, depth_err, sig_z, held = [], [], [], []
    first_M: dict[int, np.ndarray] = {}
    drift: dict[int, list[float]] = {2: [], 5: [], 10: [], 30: [], 60: [], 100: []}
    length: dict[int, int] = {}
    n_valid = n_out = 0
    for fr_truth in seq:
        fr = tracker.step(fr_truth["images"][0], fr_truth["images"][1])
        held.append(len(fr.ids))
        if not len(fr.ids):
            continue
        for i in fr.ids.tolist():
            length[i] = length.get(i, 0) + 1
        R_CM, p = fr_truth["R_CM"], fr_truth["p_MinC"]
        lam = _bilinear_depth(fr_truth["depth"][0], fr.uv[0])
        P = geo.c[0] + lam[:, None] * geo.left_rays(fr.uv[0])
        uv_r, y_r = geo.project(1, P)
        d_r = _bilinear_depth(fr_truth["depth"][1], np.nan_to_num(uv_r, nan=1.0))
        seen_r = np.isfinite(lam) & (np.abs(d_r - y_r) < 0.02 + 0.01 * y_r)
        e = np.hypot(*(fr.uv[1] - uv_r).T)[seen_r]
        n_valid += e.size
        n_out += int((e > 2.0).sum())
        match_err.append(e[e <= 2.0])
        dz = geo.left_depth(fr.p_inC) - lam
        depth_err.append(dz[seen_r & (np.hypot(*(fr.uv[1] - uv_r).T) <= 2.0)])
        sig_z.append(lam[seen_r] ** 2 / (f * b))
        # LK drift: the surface point a track started on, carried with the target
        P_M = (P - p) @ R_CM  # R_CM^T (P - p), row-wise
        for r, (i, a) in enumerate(zip(fr.ids.tolist(), fr.age.tolist(), strict=True)):
            if a == 1 and np.isfinite(P_M[r]).all():
                first_M[i] = P_M[r]
            elif a in drift and i in first_M:
                uv0, _ = geo.project(0, (R_CM @ first_M[i] + p)[None])
                drift[a].append(float(np.hypot(*(fr.uv[0, r] - uv0[0]))))
    me = np.concatenate(match_err) if match_err else np.zeros(0)
    de = np.abs(np.concatenate(depth_err)) if depth_err else np.zeros(0)
    tl = np.array(list(length.values()))
    return {
        "matches_checked": n_valid,
        "outlier_rate": n_out / max(n_valid, 1),
        "match_err_med_px": float(np.median(me)) if me.size else np.nan,
        "match_err_p95_px": float(np.percentile(me, 95)) if me.size else np.nan,
        "depth_err_med_m": float(np.median(de)) if de.size else np.nan,
        "depth_err_p95_m": float(np.percentile(de, 95)) if de.size else np.nan,
        "sigma_z_per_px_m": float(np.median(np.concatenate(sig_z))) if sig_z else np.nan,
        "drift_px": {a: (float(np.median(v)) if v else np.nan, len(v)) for a, v in drift.items()},
        "track_len_mean": float(tl.mean()) if tl.size else 0.0,
        "track_len_median": float(np.median(tl)) if tl.size else 0.0,
        "ids": int(tl.size),
        "held_mean": float(np.mean(held[1:])) if len(held) > 1 else 0.0,
        "held_min": int(np.min(held[1:])) if len(held) > 1 else 0,
    }


class _OpenCVTimer:
    """Accumulates the wall time of the OpenCV calls the front end makes (``total``) and of the
    compiled ECC kernel (``kernel``), each by name in ``by_name`` (monkeypatched)."""

    NAMES = ("calcOpticalFlowPyrLK", "remap", "matchTemplate", "findTransformECC", "getRectSubPix")
    KERNEL = "ecc_affine"  # refine_affine's compiled ECC (stereo_images.ecc_kernel)

    def __init__(self, tracker: ImageTracker) -> None:
        self.total = 0.0
        self.kernel = 0.0
        self.by_name: dict[str, float] = {}
        self._orig: dict[str, Callable[..., Any]] = {}
        self._tracker = tracker

    def _wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                if name == self.KERNEL:
                    self.kernel += dt
                else:
                    self.total += dt
                self.by_name[name] = self.by_name.get(name, 0.0) + dt

        return timed

    def __enter__(self) -> _OpenCVTimer:
        for n in self.NAMES:
            self._orig[n] = getattr(cv2, n)
            setattr(cv2, n, self._wrap(n, self._orig[n]))
        self._kernel = refine_module.ecc_affine
        refine_module.ecc_affine = self._wrap(self.KERNEL, self._kernel)
        fast = self._tracker.detector._fast
        self._detector = self._tracker.detector
        self._tracker.detector._fast = _Fast(fast, self._wrap("FAST.detect", fast.detect))  # type: ignore[assignment]
        return self

    def __exit__(self, *exc: object) -> None:
        for n, fn in self._orig.items():
            setattr(cv2, n, fn)
        refine_module.ecc_affine = self._kernel
        self._detector._fast = self._detector._fast._inner  # type: ignore[attr-defined]


class _Fast:
    def __init__(self, inner: Any, detect: Callable[..., Any]) -> None:
        self._inner = inner
        self.detect = detect


def timing(rig: StereoRig, seq: list[dict[str, Any]], tuning: ImageFrontEndTuning, pairs: int):
    cv2.setNumThreads(1)
    frames = [s["images"] for s in seq]
    # warm-up (first calls, allocations)
    warm = ImageTracker(rig, tuning)
    for im in frames[:5]:
        warm.step(im[0], im[1])
    # the sequence forwards then backwards, repeated: the tumble continues smoothly
    order = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
    idx = [order[k % len(order)] for k in range(pairs)]
    tracker = ImageTracker(rig, tuning)
    per = np.zeros(pairs)
    feats = np.zeros(pairs)
    c0 = time.process_time()
    for n, k in enumerate(idx):
        t0 = time.perf_counter()
        fr = tracker.step(frames[k][0], frames[k][1])
        per[n] = time.perf_counter() - t0
        feats[n] = len(fr.ids)
    cpu_ms = 1e3 * (time.process_time() - c0) / pairs  # less sensitive to other processes
    tracker = ImageTracker(rig, tuning)
    with _OpenCVTimer(tracker) as cvt:
        for k in idx:
            tracker.step(frames[k][0], frames[k][1])
    return per, feats, cvt, cpu_ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", choices=["text", "table1"], default="text")
    ap.add_argument("--pairs", type=int, default=120, help="rendered pairs per range")
    ap.add_argument("--ranges-m", type=float, nargs="+", default=[3.0, 6.0, 10.0])
    ap.add_argument("--timing-range-m", type=float, default=6.0)
    ap.add_argument("--timing-pairs", type=int, default=200)
    ap.add_argument("--max-age", type=int, nargs="*", default=[], help="also run these caps")
    ap.add_argument("--response", choices=["sad", "opencv"], default=None)
    ap.add_argument("--lk-refine", action="store_true")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--timing-only", action="store_true", help="skip the accuracy runs")
    ap.add_argument("--tuning", default="{}", help="JSON of ImageFrontEndTuning fields")
    args = ap.parse_args()
    rig = make_rig(args.preset)
    kw: dict[str, Any] = {}
    if args.response:
        kw["response"] = args.response
    if args.lk_refine:
        kw["lk_refine"] = True
    tuning = ImageFrontEndTuning(**{**kw, **json.loads(args.tuning)})
    w, h = rig.left.resolution_px
    print(f"rig preset {args.preset}: {w}x{h} f={rig.left.focal_px} px, b={rig.baseline_m} m")
    print(f"tuning: {tuning.model_dump()}")
    seqs = {}
    if args.timing_only:
        args.ranges_m = []
    for r in sorted(set(args.ranges_m) | {args.timing_range_m}):
        t0 = time.perf_counter()
        seqs[r] = render_sequence(rig, r, args.pairs, args.seed)
        print(f"rendered {args.pairs} pairs at {r:g} m in {time.perf_counter() - t0:.1f} s")
    for r in args.ranges_m:
        for age in [tuning.max_age_frames, *args.max_age]:
            tu = tuning.model_copy(update={"max_age_frames": age})
            a = accuracy(rig, seqs[r], tu)
            drift = " ".join(f"@{k}:{v[0]:.2f}({v[1]})" for k, v in a["drift_px"].items())
            print(
                f"range {r:g} m max_age {age}: outliers(>2px) {a['outlier_rate']:.2%} of "
                f"{a['matches_checked']}; match err med {a['match_err_med_px']:.3f} "
                f"p95 {a['match_err_p95_px']:.3f} px; depth err med {a['depth_err_med_m']:.4f} "
                f"p95 {a['depth_err_p95_m']:.4f} m (sigma_z/px {a['sigma_z_per_px_m']:.4f} m); "
                f"drift med px {drift}; track len mean {a['track_len_mean']:.1f} median "
                f"{a['track_len_median']:.0f}; IDs {a['ids']}; held mean {a['held_mean']:.1f} "
                f"min {a['held_min']}"
            )
    per, feats, cvt, cpu_ms = timing(rig, seqs[args.timing_range_m], tuning, args.timing_pairs)
    n = len(per)
    cv_ms = 1e3 * cvt.total / n
    kernel_ms = 1e3 * cvt.kernel / n
    parts = " ".join(f"{k}={1e3 * v / n:.2f}" for k, v in sorted(cvt.by_name.items()))
    print(
        f"timing at {args.timing_range_m:g} m, {n} pairs, 1 OpenCV thread: mean "
        f"{1e3 * per.mean():.2f} ms, median {1e3 * np.median(per):.2f}, p95 "
        f"{1e3 * np.percentile(per, 95):.2f}, max {1e3 * per.max():.2f}; features mean "
        f"{feats.mean():.1f}; process CPU {cpu_ms:.2f} ms/pair; compiled calls (ms/pair): "
        f"{parts}"
    )
    print(
        f"frontend_ms={1e3 * per.mean():.2f} opencv_only_ms={cv_ms:.2f} "
        f"ecc_kernel_ms={kernel_ms:.2f}"
    )


if __name__ == "__main__":
    main()
