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
Evangelidis & Psarakis 2008) of an affine warp of a template, by OpenCV's algorithm
(``cv2.findTransformECC``, modules/video/src/ecc.cpp) compiled for all the features of a call
at once (:mod:`~tumblenav.frontends.stereo_images.ecc_kernel`: OpenCV's ECC takes one template
per call, and its per-call overhead, not the arithmetic, had made three quarters of the front
end's time):

* left: the ``template_px`` patch at the feature's first sighting, warped by the affine map
  carried from frame to frame (the template update problem, Matthews, Ishikawa & Baker 2004:
  drift-free because the template is never replaced), and
* right: the left patch of the same frame, warped from the epipolar match.

The correlation coefficient is invariant to a gain and an offset of the grey levels (the sun
angle changes the shading as the target turns).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends.stereo_images.ecc_kernel import ECC_OK, ecc_affine

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
_MAX_ITER = 20
_EPS = 1e-3


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
    (OpenCV's ``findTransformECC``, MOTION_AFFINE, on a crop around the prediction, here
    :func:`~tumblenav.frontends.stereo_images.ecc_kernel.ecc_affine`), and accept the result
    when ECC succeeds, scores (the correlation coefficient) at least ``min_cc`` and moves the
    centre by at most ``max_shift_px`` from ``uv_pred`` (else ``uv_pred`` and ``lin`` are
    returned).

    The crop holds any accepted warp (the template's corners turned and scaled by the warp,
    the shift allowed and 4 px for the gradients), clipped to the image; a warp that reaches
    past it finds 0 there and the pixels it takes outside are masked, as in OpenCV.

    Why a hand-written kernel: OpenCV's ECC takes one template per call, and its per-call
    overhead with the Python loop around it (~0.13 ms a feature on one core, mostly fixed costs
    around 225 pixels of arithmetic) made three quarters of the front end's time (33 of 44 ms
    a pair, benchmarks/image_frontend.py; 3.2 ms with the kernel). ``ecc_affine`` runs OpenCV's
    algorithm step by step (``gaussFiltSize`` 1, no mask) for all the features in one
    compiled loop; it agrees with ``cv2.findTransformECC`` to rounding (float64 here, float32
    there; ``tests/test_image_frontend.py``). A batched inverse-compositional and a batched
    forward-additive Gauss-Newton in numpy were tried before: as accurate only with ECC's own
    gradient and stopping rule, and then slower."""
    m = len(uv_pred)
    side = templates.shape[-1]
    c = (side - 1) / 2.0
    cen = np.array([c, c])
    lin_in = np.asarray(lin, float).reshape(m, 2, 2)
    uv = np.array(uv_pred, float, copy=True).reshape(m, 2)
    p = uv - 0.5  # OpenCV pixels
    lin_out = lin_in.copy()
    cc = np.full(m, np.nan)
    ok = np.zeros(m, bool)
    # the crop: the template's corners turned and scaled by the warp (its rows' absolute sums)
    # plus the shift allowed, and a margin for ECC's gradients; clipped to the image
    reach = c * np.abs(lin_in).sum(axis=-1).max(axis=-1)
    run = np.isfinite(p).all(axis=1) & np.isfinite(reach)
    half = np.ceil(np.where(run, reach, 0.0) + max_shift_px).astype(np.int64) + 4
    p_int = np.rint(np.where(run[:, None], p, 0.0)).astype(np.int64)  # round() ties to even
    h, w = image.shape
    boxes = np.stack(
        [
            np.maximum(p_int[:, 0] - half, 0),
            np.maximum(p_int[:, 1] - half, 0),
            np.minimum(p_int[:, 0] + half + 1, w),
            np.minimum(p_int[:, 1] + half + 1, h),
        ],
        axis=1,
    )
    run &= (boxes[:, 2] - boxes[:, 0] >= side) & (boxes[:, 3] - boxes[:, 1] >= side)
    idx = np.flatnonzero(run)
    if not idx.size:
        return AffineRefinement(uv, lin_out, cc, ok)
    # the initial warps, template pixels -> crop pixels (float32, as OpenCV's warpMatrix)
    warps = np.empty((idx.size, 2, 3), np.float32)
    warps[:, :, :2] = lin_in[idx]
    warps[:, :, 2] = p[idx] - lin_in[idx] @ cen - boxes[idx, :2]
    found, score, status = ecc_affine(
        np.ascontiguousarray(templates[idx], dtype=np.float32),
        np.ascontiguousarray(image),
        boxes[idx],
        warps,
        _MAX_ITER,
        _EPS,
    )
    done = status == ECC_OK
    q = found[:, :, :2].astype(float) @ cen + found[:, :, 2] + boxes[idx, :2]
    cc[idx[done]] = score[done]
    good = done & (score >= min_cc) & (np.hypot(*(q - p[idx]).T) <= max_shift_px)
    uv[idx[good]] = q[good] + 0.5
    lin_out[idx[good]] = found[good, :, :2]
    ok[idx[good]] = True
    return AffineRefinement(uv, lin_out, cc, ok)
