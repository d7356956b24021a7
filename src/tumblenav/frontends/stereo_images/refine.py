"""Affine template refinement of tracked and matched features (tumblenav's, beyond Chang 2021).

Chang 2021 tracks the left image frame to frame with pyramidal LK and matches the right image by
a similarity along the epipolar line (Sec. 2.3-2.4). Both assume that a small patch only
translates. On a tumbling target a patch also turns and foreshortens, so

* a left track follows the patch's texture rather than the surface point it started on and
  slides, roughly linearly with its age (``lk_window_px``'s description: 0.5 px at 60 frames
  on chang2021_close's renders, ``benchmarks/image_frontend.py``), and
* the right match of a slanted patch is biased along the epipolar line by the left-right
  difference of view, the same way at every frame of the track: a depth error that persists
  over the track's life (1.5 px-equivalent robust sigma per track against the renderer's
  surface point on chang2021_close, run 0).

Here each LK result is refined by maximising the enhanced correlation coefficient (ECC,
Evangelidis & Psarakis 2008, ``cv2.findTransformECC``) of an affine warp of a template:

* left: the ``template_px`` patch at the feature's first sighting, warped by the affine map
  carried from frame to frame (the template update problem, Matthews, Ishikawa & Baker 2004:
  drift-free because the template is never replaced), and
* right: the left patch of the same frame, warped from the epipolar match.

The correlation coefficient is invariant to a gain and an offset of the grey levels (the sun
angle changes the shading as the target turns).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from cv2.typing import MatLike
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["AffineRefinement", "refine_affine", "template_at"]


def template_at(image: NDArray[np.uint8], uv: Array, side: int) -> NDArray[np.float32]:
    """The ``side`` x ``side`` patches (m, side, side) centred on the tumblenav pixels ``uv``
    (m, 2), bilinear."""
    out = np.empty((len(uv), side, side), np.float32)
    for i, (u, v) in enumerate(np.asarray(uv, float)):
        # float output: a uint8 patch would round the bilinear grey levels to integers
        out[i] = cv2.getRectSubPix(image, (side, side), (u - 0.5, v - 0.5), patchType=cv2.CV_32F)
    return out


@dataclass(frozen=True)
class AffineRefinement:
    """Refined pixels ``uv`` (m, 2, tumblenav), the warps' linear parts ``lin`` (m, 2, 2),
    their ECC scores ``cc`` (m,) and whether each was accepted ``ok`` (m,)."""

    uv: Array
    lin: Array
    cc: Array
    ok: NDArray[np.bool_]


# ECC's termination: 20 iterations or a change of the correlation below 1e-3. As accurate as
# 50 and 1e-4 (benchmarks/image_frontend.py --ranges-m 9: median match error 0.055 against
# 0.056 px, drift at 60 frames 0.05 px both) in half the time.
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-3)


def refine_affine(
    templates: NDArray[np.float32],
    image: NDArray[np.uint8],
    uv_pred: Array,
    lin: Array,
    min_cc: float,
    max_shift_px: float,
) -> AffineRefinement:
    """Warp each template into ``image`` by the affine map of linear part ``lin`` (m, 2, 2)
    that takes the template's centre to ``uv_pred`` (m, 2, tumblenav), refine the warp by ECC
    (``cv2.findTransformECC``, MOTION_AFFINE, on a crop around the prediction), and accept the
    result when ECC succeeds, scores (the correlation coefficient) at least ``min_cc`` and
    moves the centre by at most ``max_shift_px`` from ``uv_pred`` (else ``uv_pred`` and
    ``lin`` are returned).

    OpenCV's ECC takes one template per call, hence the loop (~0.17 ms a feature on one core).
    A batched inverse-compositional and a batched forward-additive Gauss-Newton over all the
    features (one ``cv2.remap`` per iteration) were tried: as accurate only with ECC's own
    gradient and stopping rule, and then slower in numpy (66 against 50 ms per pair at 120
    features, benchmarks/image_frontend.py)."""
    m = len(uv_pred)
    side = templates.shape[-1]
    c = (side - 1) / 2.0
    # the crop holds any accepted warp: the template's corners turned and scaled by the warp
    # (its rows' absolute sums) plus the shift allowed, and a margin for ECC's gradients
    reach = c * np.abs(np.asarray(lin, float)).sum(axis=-1).max(axis=-1) if m else np.zeros(0)
    h, w = image.shape
    uv = np.array(uv_pred, float, copy=True)
    lin_out = np.array(lin, float, copy=True)
    cc = np.full(m, np.nan)
    ok = np.zeros(m, bool)
    cen = np.array([c, c])
    for i in range(m):
        p = uv_pred[i] - 0.5  # OpenCV pixel
        if not (np.all(np.isfinite(p)) and np.isfinite(reach[i])):
            continue
        half = int(np.ceil(reach[i] + max_shift_px)) + 4
        # the crop, clipped to the image (ECC masks what a warp takes outside it)
        x0, y0 = max(int(round(p[0])) - half, 0), max(int(round(p[1])) - half, 0)
        x1, y1 = min(int(round(p[0])) + half + 1, w), min(int(round(p[1])) + half + 1, h)
        if x1 - x0 < side or y1 - y0 < side:
            continue
        crop = image[y0:y1, x0:x1].astype(np.float32)  # the crop alone: the matcher calls
        # this several times a frame on the same image (tracked features, each batch of new ones)
        L = lin[i]
        warp = np.empty((2, 3), np.float32)
        warp[:, :2] = L
        warp[:, 2] = p - L @ cen - (x0, y0)
        try:
            score, found = cv2.findTransformECC(
                templates[i], crop, warp, cv2.MOTION_AFFINE, _CRITERIA, cast(MatLike, None), 1
            )
        except cv2.error:  # ECC failed (a flat or vanished patch)
            continue
        warp = np.asarray(found, np.float32)
        q = warp[:, :2].astype(float) @ cen + warp[:, 2] + (x0, y0)
        cc[i] = score
        if score < min_cc or np.hypot(*(q - p)) > max_shift_px:
            continue
        uv[i] = q + 0.5
        lin_out[i] = warp[:, :2]
        ok[i] = True
    return AffineRefinement(uv, lin_out, cc, ok)
