"""FAST corners in the left image, masked around existing features and ranked by response
(Chang 2021 Sec. 2.3-2.4)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends.stereo_images.tuning import ImageFrontEndTuning

Array = NDArray[np.float64]

__all__ = ["FAST_CIRCLE", "CornerDetector", "feature_mask", "sad_response", "take_spaced"]

# The 16-pixel Bresenham circle of radius 3 of the FAST segment test, as (dx, dy).
FAST_CIRCLE = np.array(
    [
        (0, -3),
        (1, -3),
        (2, -2),
        (3, -1),
        (3, 0),
        (3, 1),
        (2, 2),
        (1, 3),
        (0, 3),
        (-1, 3),
        (-2, 2),
        (-3, 1),
        (-3, 0),
        (-3, -1),
        (-2, -2),
        (-1, -3),
    ],
    dtype=np.intp,
)


def sad_response(image: NDArray[np.uint8], cols: NDArray[np.intp], rows: NDArray[np.intp]) -> Array:
    """Chang 2021 Sec. 2.3 corner response: ``sum_k |I(p) - I(p + c_k)|`` over the 16 pixels
    ``c_k`` of the FAST circle, for pixels ``(cols, rows)`` at least 3 px inside the image."""
    centre = image[rows, cols].astype(np.int32)
    ring = image[rows[:, None] + FAST_CIRCLE[:, 1], cols[:, None] + FAST_CIRCLE[:, 0]]
    return np.abs(ring.astype(np.int32) - centre[:, None]).sum(axis=1).astype(float)


def feature_mask(
    shape: tuple[int, int], uv: Array, side_px: int, border_px: int
) -> NDArray[np.uint8]:
    """Detection mask (H, W) uint8: 0 within ``border_px`` of the image edge and in the
    ``side_px`` square around the pixel of each feature ``uv`` (m, 2) (tumblenav pixels, so the
    pixel is ``floor(uv)``), 255 elsewhere (Chang 2021 Sec. 2.4: a 5 x 5 mask)."""
    h, w = shape
    mask = np.zeros((h, w), np.uint8)
    if border_px * 2 < min(h, w):
        mask[border_px : h - border_px, border_px : w - border_px] = 255
    _block(mask, uv, side_px)
    return mask


def _block(mask: NDArray[np.uint8], uv: Array, side_px: int) -> None:
    """Zero the ``side_px`` square around each pixel ``floor(uv)`` of ``mask`` (in place)."""
    if len(uv) == 0:
        return
    h, w = mask.shape
    lo = side_px // 2
    hi = side_px - lo  # e.g. side 5: from -2 to +2
    ij = np.floor(uv).astype(np.intp)
    for i, j in ij:
        mask[max(j - lo, 0) : max(min(j + hi, h), 0), max(i - lo, 0) : max(min(i + hi, w), 0)] = 0


def take_spaced(
    uv: Array, mask: NDArray[np.uint8], side_px: int, limit: int, start: int = 0
) -> tuple[NDArray[np.intp], int]:
    """Up to ``limit`` corners of ``uv`` (sorted best first), from index ``start`` on, whose
    pixel is still free in ``mask``; each one taken blocks its ``side_px`` square, so new
    corners are spaced like existing features.  ``mask`` is modified.

    Returns the indices taken and the index to resume from.
    """
    taken: list[int] = []
    lo = side_px // 2
    hi = side_px - lo
    h, w = mask.shape
    cols = np.floor(uv[:, 0]).astype(np.intp).tolist()
    rows = np.floor(uv[:, 1]).astype(np.intp).tolist()
    k = start
    n = len(cols)
    while k < n and len(taken) < limit:
        i, j = cols[k], rows[k]
        if mask[j, i]:
            taken.append(k)
            mask[max(j - lo, 0) : min(j + hi, h), max(i - lo, 0) : min(i + hi, w)] = 0
        k += 1
    return np.array(taken, dtype=np.intp), k


class CornerDetector:
    """FAST (OpenCV TYPE_9_16, non-maximum suppression) with Chang's or OpenCV's response."""

    def __init__(self, tuning: ImageFrontEndTuning) -> None:
        self.tuning = tuning
        self._fast = cv2.FastFeatureDetector.create(
            threshold=tuning.fast_threshold,  # tumblenav default (Chang 2021 silent)
            nonmaxSuppression=True,
            type=cv2.FastFeatureDetector_TYPE_9_16,
        )

    def detect(self, image: NDArray[np.uint8], mask: NDArray[np.uint8]) -> tuple[Array, Array]:
        """Corners (n, 2) in tumblenav pixels (pixel centres ``i + 0.5``) and their responses
        (n,), sorted by decreasing response (Chang 2021 Sec. 2.4: sort by response)."""
        kps = self._fast.detect(image, mask)
        if not kps:
            return np.zeros((0, 2)), np.zeros(0)
        pts = np.asarray(
            cv2.KeyPoint.convert(kps), dtype=float
        )  # OpenCV pixels: centres at integers
        cols = np.rint(pts[:, 0]).astype(np.intp)
        rows = np.rint(pts[:, 1]).astype(np.intp)
        if self.tuning.response == "sad":
            resp = sad_response(image, cols, rows)
        else:
            resp = np.array([k.response for k in kps], dtype=float)
        order = np.argsort(-resp, kind="stable")
        uv = np.column_stack([cols, rows]).astype(float)[order] + 0.5  # tumblenav pixels
        return uv, resp[order]
