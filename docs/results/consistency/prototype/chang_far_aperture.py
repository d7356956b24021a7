"""Do the image tracks at 59 m slide along their patch's edge? (twenty-first session, issue 18)

Re-runs the front end on run SEED (the same scenario and environment as chang_far_tracks.py,
whose CACHE must hold that run: the tracks are checked equal to the cache's), capturing each
feature's first-sighting template, and compares the template's gradient structure tensor with
the track's residuals about its best rigid point under the true poses: the angle between the
residuals' major direction and the template's weakest-gradient direction, and the residual
variance along / across that direction per tensor ratio. The weighting that follows from it
(each feature's pixel covariance the inverse structure tensor, 1 across, at most
``track_shape_max_ratio`` along) is the patch chang_aperture_shape.patch (against 1eb4141;
``git apply``), measured with chang_far_tracks.py on a fresh CACHE.

Usage::

    python chang_far_aperture.py CACHE SEED
"""

import pickle
import sys
from pathlib import Path

import cv2
import numpy as np

_proto = Path(__file__).with_name("chang_far_tracks.py").read_text()
_argv, sys.argv = sys.argv, [sys.argv[0], sys.argv[1], sys.argv[2], "none"]
exec(_proto.split("with threadpool_limits")[0])  # the shared helpers, without the main loop
sys.argv = _argv
from tumblenav.frontends.stereo_images import tracker as trk  # noqa: E402

k = int(sys.argv[2])
TPL: dict[int, np.ndarray] = {}
_orig = trk.ImageTracker._add


def _add(self, left, right, vacancy, st):
    n0 = len(self.ids)
    _orig(self, left, right, vacancy, st)
    for i, tpl in zip(self.ids[n0:], self.templates[n0:], strict=True):
        TPL[int(i)] = np.array(tpl, np.float64)


trk.ImageTracker._add = _add
_, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
new, _ = stages.prepare(meas, tuple(est.consumes), fe)
truth, tracks, P = pickle.load(open(cache / f"run{k}.pkl", "rb"))
same = new.uv.shape == tracks.uv.shape and np.allclose(np.nan_to_num(new.uv), np.nan_to_num(tracks.uv))
print(f"run {k}: tracks equal to the cache's: {same}; {len(TPL)} templates")


def tensor(t):
    gx = cv2.Sobel(t, cv2.CV_64F, 1, 0, ksize=3)[1:-1, 1:-1] / 8.0
    gy = cv2.Sobel(t, cv2.CV_64F, 0, 1, ksize=3)[1:-1, 1:-1] / 8.0
    n = t.shape[0]
    c = (n - 1) / 2
    yy, xx = np.mgrid[:n, :n]
    w = np.exp(-((xx - c) ** 2 + (yy - c) ** 2) / (2 * (n / 4) ** 2))[1:-1, 1:-1]
    return np.array(
        [[np.sum(w * gx * gx), np.sum(w * gx * gy)], [np.sum(w * gx * gy), np.sum(w * gy * gy)]]
    )


obs = tracks.observed
res = np.where(obs[..., None], tracks.uv - projections(truth, tracks, P), np.nan)
tracked = obs[:, 0] & (np.cumsum(obs[:, 0], 0) > 1)
cos, ratio, along, across = [], [], [], []
for i in np.flatnonzero(tracked.sum(0) >= 5):
    e = res[tracked[:, i], 0, i]
    e = e[np.all(np.isfinite(e), 1)]
    if len(e) < 5:
        continue
    C = np.cov((e - e.mean(0)).T)
    _, V = np.linalg.eigh(C)
    gw, gV = np.linalg.eigh(tensor(TPL[i]))
    cos.append(abs(V[:, 1] @ gV[:, 0]))  # residuals' major direction . template's weakest
    ratio.append(gw[1] / max(gw[0], 1e-12))
    along.append(gV[:, 0] @ C @ gV[:, 0])
    across.append(gV[:, 1] @ C @ gV[:, 1])
cos, ratio, along, across = map(np.array, (cos, ratio, along, across))
print(
    f"{len(cos)} tracks seen 5 times or more: |cos(residuals' major direction, template's "
    f"weakest gradient)| median {np.median(cos):.2f}, mean {cos.mean():.2f} (uniform angles: median 0.71, mean 0.64)"
)
for lo, hi in ((1, 2), (2, 4), (4, 10), (10, np.inf)):
    s = (ratio >= lo) & (ratio < hi)
    if s.sum():
        print(
            f"  tensor ratio [{lo}, {hi}): {s.sum()} tracks, |cos| median {np.median(cos[s]):.2f}, "
            f"residual variance along {np.median(along[s]):.4f} / across {np.median(across[s]):.4f} "
            f"px^2 (medians; ratio {np.median(along[s]) / np.median(across[s]):.2f})"
        )
