"""The stereo-image tracker: one step per stereo pair (Chang 2021 Sec. 2.3-2.4, Figs. 5-7).

Per frame, in Chang 2021 Sec. 2.4's order:

1. drop the features whose survival time (frames tracked, counting the first) would exceed
   ``max_age_frames``; track the others in the left image, frame k-1 -> k, with pyramidal LK;
   drop the lost ones and those failing the forward-backward check (tumblenav: Chang 2021
   gives no gating); refine each tracked pixel by an affine warp of the feature's
   first-sighting patch and end the tracks whose refinement fails (``template_refine``,
   tumblenav's: :mod:`~tumblenav.frontends.stereo_images.refine`);
2. match the tracked features in the right image along the epipolar line; drop the failures (a
   feature is observed only when tracked in the left image AND matched in the right one);
3. if fewer than ``n_min`` remain, detect FAST corners in the left image, masked in a 5 x 5
   square around each feature, sort them by response, stereo-match the best ones and add the
   vacancy ``n_min - m`` of them with new IDs (never reused);
4. if more than ``n_max`` remain, remove the ``m - n_max`` most-tracked ones.

A frame with nothing to see (black, target out of view) ends with zero features; the next one
starts detection again.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, cast

import cv2
import numpy as np
from cv2.typing import MatLike
from numpy.typing import NDArray

from tumblenav.errors import InputError
from tumblenav.frontends.stereo_images.detection import CornerDetector, feature_mask, take_spaced
from tumblenav.frontends.stereo_images.geometry import EpipolarGeometry
from tumblenav.frontends.stereo_images.matching import MatchStatus, StereoMatcher
from tumblenav.frontends.stereo_images.refine import refine_affine, template_at
from tumblenav.frontends.stereo_images.tuning import DEFAULT_TUNING, ImageFrontEndTuning
from tumblenav.sensors.stereo import StereoRig

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["FrameStats", "ImageTracker", "TrackedFrame", "most_tracked_to_remove"]


@dataclass(frozen=True)
class FrameStats:
    """Counts of one frame (numbers of features or corners)."""

    detected: int = 0  # FAST corners found outside the mask (0 when no vacancy: no detection)
    tracked: int = 0  # features LK tracked k-1 -> k (status ok, inside the image)
    lost: int = 0  # features LK lost (status 0 or left the image)
    fb_rejected: int = 0  # tracked but failing the forward-backward check
    template_rejected: int = 0  # tracked, but the affine refinement against the first patch failed
    matched: int = 0  # tracked features matched in the right image (kept)
    epipolar_rejected: int = 0  # tracked features or new corners failing the right match
    new: int = 0  # features created (new IDs)
    aged: int = 0  # features dropped for exceeding max_age_frames
    removed: int = 0  # features removed above n_max (Chang's most-tracked rule)
    features: int = 0  # features observed (left and right) after the frame

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass(frozen=True)
class TrackedFrame:
    """Features observed in one stereo pair.

    ids : (m,) int64 -- feature IDs (0, 1, ... in order of creation; never reused).
    uv : (2, m, 2) -- pixels (u, v) in the left (0) and right (1) image, tumblenav convention
        (pixel centres at i + 0.5).
    age : (m,) int64 -- survival time: frames in which the feature has been observed so far.
    p_inC : (m, 3) -- the triangulated points in the rig frame C (m).
    ncc : (m,) -- the NCC score of the left -> right match.
    stats : FrameStats
    """

    ids: IntArray
    uv: Array
    age: IntArray
    p_inC: Array
    ncc: Array
    stats: FrameStats


def most_tracked_to_remove(ids: IntArray, age: IntArray, n_max: int) -> NDArray[np.intp]:
    """Indices of the ``m - n_max`` features to remove when ``m > n_max`` (empty otherwise).

    Chang 2021 Sec. 2.4: sort by consecutive-tracking count and remove the features with the
    MOST tracking.  The paper prints the count as ``(n_max - m)``, which is negative whenever
    removal applies: a sign error, corrected here to ``m - n_max``.  Ties: the older ID first.
    """
    excess = len(ids) - n_max
    if excess <= 0:
        return np.zeros(0, dtype=np.intp)
    order = np.lexsort((ids, -age))  # by age descending, then ID ascending
    return np.sort(order[:excess])


class ImageTracker:
    """Stateful FAST + LK + epipolar-NCC stereo tracker of a calibrated rig."""

    def __init__(self, rig: StereoRig, tuning: ImageFrontEndTuning = DEFAULT_TUNING) -> None:
        self.rig = rig
        self.tuning = tuning
        self.geometry = EpipolarGeometry(rig)
        self.detector = CornerDetector(tuning)
        self.matcher = StereoMatcher(self.geometry, tuning)
        w, h = rig.left.resolution_px
        if rig.right.resolution_px != (w, h):
            raise InputError("the image front end needs both cameras of the same resolution")
        self.shape = (h, w)
        win = tuning.lk_window_px
        self._win = (win, win)
        self._criteria = (
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
            tuning.lk_max_iterations,
            tuning.lk_epsilon_px,
        )
        self._margin = tuning.patch_px // 2 + 2  # tracked features must keep a patch inside
        self.next_id = 0
        self.reset()

    def reset(self) -> None:
        """Forget all features (IDs keep counting up)."""
        self._prev: NDArray[np.uint8] | None = None
        self.ids = np.zeros(0, dtype=np.int64)
        self.uv_l = np.zeros((0, 2))
        self.uv_r = np.zeros((0, 2))
        self.age = np.zeros(0, dtype=np.int64)
        self.depth = np.zeros(0)
        self.p_inC = np.zeros((0, 3))
        self.ncc = np.zeros(0)
        # template_refine: each feature's first-sighting patch and its affine warp's linear part
        side = self.tuning.template_px
        self.templates = np.zeros((0, side, side), np.float32)
        self.lin = np.zeros((0, 2, 2))

    def _check(self, image: NDArray[np.uint8], name: str) -> NDArray[np.uint8]:
        a = np.asarray(image)
        if a.dtype != np.uint8 or a.ndim != 2:
            raise InputError(
                f"{name} image must be a 2-D uint8 grey image, got {a.dtype} {a.shape}"
            )
        if a.shape != self.shape:
            raise InputError(f"{name} image is {a.shape[::-1]} px, the rig's is {self.shape[::-1]}")
        return np.ascontiguousarray(a)

    def _keep(self, idx: NDArray[np.intp]) -> None:
        for name in ("ids", "uv_l", "uv_r", "age", "depth", "p_inC", "ncc", "templates", "lin"):
            setattr(self, name, getattr(self, name)[idx])

    def step(self, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> TrackedFrame:
        """Process the next stereo pair; returns the features observed in it."""
        tu = self.tuning
        left = self._check(left, "left")
        right = self._check(right, "right")
        st: dict[str, int] = {}

        # 1. age cap, then LK k-1 -> k with the forward-backward check
        keep = np.flatnonzero(self.age < tu.max_age_frames)
        st["aged"] = len(self.ids) - keep.size
        self._keep(keep)
        if self._prev is not None and len(self.ids):
            self._track(self._prev, left, st)
        else:
            self._keep(np.zeros(0, dtype=np.intp))
        self._prev = left

        # 2. right matches of the tracked features
        m = len(self.ids)
        if m:
            res = self.matcher.match(left, right, self.uv_l, self.depth)
            edge = np.flatnonzero(res.status == MatchStatus.EDGE)
            uv_r, score, status = res.uv_r.copy(), res.score.copy(), res.status.copy()
            if edge.size:  # the depth moved beyond the window: search the whole segment
                again = self.matcher.match(left, right, self.uv_l[edge])
                uv_r[edge], score[edge], status[edge] = again.uv_r, again.score, again.status
            ok = status == MatchStatus.OK
            st["epipolar_rejected"] = int((~ok).sum())
            self.uv_r, self.ncc = uv_r, score
            self._keep(np.flatnonzero(ok))
            self.age = self.age + 1
            self._triangulate()
            ahead = np.flatnonzero(np.all(np.isfinite(self.p_inC), axis=1))
            st["epipolar_rejected"] += len(self.ids) - ahead.size
            self._keep(ahead)
        st["matched"] = len(self.ids)

        # 3. fill the vacancy n_min - m with new corners
        vacancy = tu.n_min - len(self.ids)
        if vacancy > 0:
            self._add(left, right, vacancy, st)

        # 4. Chang's cap: remove the (m - n_max) most-tracked features
        drop = most_tracked_to_remove(self.ids, self.age, tu.n_max)
        st["removed"] = drop.size
        if drop.size:
            self._keep(np.setdiff1d(np.arange(len(self.ids)), drop))
        st["features"] = len(self.ids)
        return TrackedFrame(
            ids=self.ids.copy(),
            uv=np.stack([self.uv_l, self.uv_r]),
            age=self.age.copy(),
            p_inC=self.p_inC.copy(),
            ncc=self.ncc.copy(),
            stats=FrameStats(**st),
        )

    def _track(self, prev: NDArray[np.uint8], cur: NDArray[np.uint8], st: dict[str, int]) -> None:
        tu = self.tuning
        p0 = (self.uv_l - 0.5).astype(np.float32).reshape(-1, 1, 2)  # OpenCV pixels
        kw: dict[str, Any] = dict(
            winSize=self._win,
            maxLevel=tu.lk_levels,
            criteria=self._criteria,
            minEigThreshold=tu.lk_min_eigen,
        )
        p1, s1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, cast(MatLike, None), **kw)
        uv = p1.reshape(-1, 2).astype(float) + 0.5
        ok = (s1.ravel() == 1) & np.all(np.isfinite(uv), axis=1) & self._inside(uv)
        st["lost"] = int((~ok).sum())
        idx = np.flatnonzero(ok)
        fb_ok = np.zeros(0, dtype=bool)
        if idx.size:
            # Forward-backward check (tumblenav default, Chang 2021 silent)
            back, s2, _ = cv2.calcOpticalFlowPyrLK(
                cur,
                prev,
                p1[idx].copy(),
                p0[idx].copy(),
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                **kw,
            )
            err = np.hypot(*(back.reshape(-1, 2) - p0[idx].reshape(-1, 2)).T.astype(float))
            fb_ok = (s2.ravel() == 1) & (err <= tu.fb_max_px)
        st["fb_rejected"] = int((~fb_ok).sum())
        st["tracked"] = int(idx.size)
        keep = idx[fb_ok]
        self._keep(keep)
        self.uv_l = uv[keep]
        if tu.template_refine and len(keep):
            res = refine_affine(
                self.templates, cur, self.uv_l, self.lin, tu.template_min_cc,
                tu.template_max_shift_px,
            )  # fmt: skip
            ok = res.ok & self._inside(res.uv)  # a refined pixel must keep the patch inside too
            st["template_rejected"] = int((~ok).sum())
            self.uv_l, self.lin = res.uv, res.lin
            self._keep(np.flatnonzero(ok))

    def _inside(self, uv: Array) -> NDArray[np.bool_]:
        """Whether each pixel keeps a patch inside the image (``_margin`` from every edge)."""
        h, w = self.shape
        mg = self._margin
        return (uv[:, 0] >= mg) & (uv[:, 0] <= w - mg) & (uv[:, 1] >= mg) & (uv[:, 1] <= h - mg)

    def _triangulate(self) -> None:
        p = self.geometry.triangulate(self.uv_l, self.uv_r)
        self.p_inC = p
        self.depth = self.geometry.left_depth(p)

    def _add(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8], vacancy: int, st: dict[str, int]
    ) -> None:
        tu = self.tuning
        mask = feature_mask(self.shape, self.uv_l, tu.mask_px, max(tu.border_px, self._margin))
        cand, _ = self.detector.detect(left, mask)
        st["detected"] = len(cand)
        if not len(cand):
            return
        # the best corners, spaced by the same mask among themselves, matched in batches
        # until the vacancy is filled (Chang 2021 Sec. 2.4: sort by response, drop the weak)
        got_l: list[Array] = []
        got_r: list[Array] = []
        got_s: list[Array] = []
        rejected = 0
        start = 0
        while vacancy > 0 and start < len(cand):
            idx, start = take_spaced(cand, mask, tu.mask_px, max(2 * vacancy, 16), start)
            if not idx.size:
                break
            batch = cand[idx]
            res = self.matcher.match(left, right, batch)
            ok = np.flatnonzero(res.ok)[:vacancy]
            rejected += int((~res.ok).sum())
            got_l.append(batch[ok])
            got_r.append(res.uv_r[ok])
            got_s.append(res.score[ok])
            vacancy -= ok.size
        st["epipolar_rejected"] = st.get("epipolar_rejected", 0) + rejected
        if not got_l:
            return
        uv_l = np.concatenate(got_l)
        uv_r = np.concatenate(got_r)
        p = self.geometry.triangulate(uv_l, uv_r)
        ahead = np.all(np.isfinite(p), axis=1)
        st["epipolar_rejected"] += int((~ahead).sum())
        uv_l, uv_r, p, score = uv_l[ahead], uv_r[ahead], p[ahead], np.concatenate(got_s)[ahead]
        n = len(uv_l)
        st["new"] = n
        if not n:
            return
        self.ids = np.concatenate([self.ids, self.next_id + np.arange(n, dtype=np.int64)])
        self.next_id += n
        self.uv_l = np.concatenate([self.uv_l, uv_l])
        self.uv_r = np.concatenate([self.uv_r, uv_r])
        self.age = np.concatenate([self.age, np.ones(n, dtype=np.int64)])
        self.p_inC = np.concatenate([self.p_inC, p])
        self.depth = np.concatenate([self.depth, self.geometry.left_depth(p)])
        self.ncc = np.concatenate([self.ncc, score])
        self.templates = np.concatenate([self.templates, template_at(left, uv_l, tu.template_px)])
        self.lin = np.concatenate([self.lin, np.broadcast_to(np.eye(2), (n, 2, 2))])
