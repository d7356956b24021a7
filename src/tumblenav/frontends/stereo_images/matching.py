"""Left -> right matching along the epipolar line of the calibrated rig (Chang 2021 Sec. 2.3).

Chang 2021 constrains the stereo search to the epipolar line (against repetitive texture) but
gives neither the similarity measure nor the tolerance.  Ours (tumblenav default, Chang 2021
silent): a ``patch_px`` square around the left pixel, sampled along the left epipolar direction,
is compared by normalised cross-correlation (``cv2.matchTemplate``, TM_CCOEFF_NORMED) with a
strip sampled along the right epipolar line, so that the pair is locally rectified whatever the
rig (a toed-in rig tilts the epipolar lines).  The score peak is refined by a parabola, then by
an affine ECC warp of the left patch (``affine_match_refine``, tumblenav's,
:mod:`~tumblenav.frontends.stereo_images.refine`), optionally by one full-resolution LK step
from the left image to the right one before that (``lk_refine``).

A feature with a known depth (a tracked one) is searched ``track_search_px`` either side of the
point its previous depth gives on the new epipolar line; a new one over the right image of its
ray between ``min_depth_m`` and ``max_depth_m``, and must then be unique.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import cv2
import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends.stereo_images.geometry import EpipolarGeometry, clip_segments
from tumblenav.frontends.stereo_images.refine import refine_affine, template_at
from tumblenav.frontends.stereo_images.tuning import ImageFrontEndTuning

Array = NDArray[np.float64]

__all__ = ["MatchStatus", "Matches", "StereoMatcher", "parabola_peak", "sample_patches"]


class MatchStatus(IntEnum):
    """Why a left pixel has (or has no) right match."""

    OK = 0
    NO_TEXTURE = 1  # left patch below min_patch_std
    NO_SEGMENT = 2  # the epipolar search segment misses the image (or the geometry fails)
    EDGE = 3  # best score at an end of the searched segment
    LOW_SCORE = 4  # best NCC below ncc_min
    NOT_UNIQUE = 5  # a second peak within ncc_unique_margin (full searches only)


@dataclass(frozen=True)
class Matches:
    """Right pixels (m, 2) (tumblenav, NaN where unmatched), NCC scores (m,), statuses (m,)."""

    uv_r: Array
    score: Array
    status: NDArray[np.int8]

    @property
    def ok(self) -> NDArray[np.bool_]:
        return self.status == MatchStatus.OK


def parabola_peak(s_m: Array, s_0: Array, s_p: Array) -> Array:
    """Offset in ``[-0.5, 0.5]`` of the vertex of the parabola through ``(-1, s_m), (0, s_0),
    (1, s_p)`` (sub-pixel peak of a sampled score; 0 where the samples are not concave)."""
    den = s_m - 2.0 * s_0 + s_p
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0.0, 0.5 * (s_m - s_p) / den, 0.0)
    return np.clip(off, -0.5, 0.5)


def _sample(image: NDArray[np.uint8], xs: Array, ys: Array) -> NDArray[np.float32]:
    """Bilinear samples of ``image`` at tumblenav pixel coordinates (arrays of equal shape, 2-D
    after the first axis is merged with the second); 0 outside the image."""
    shape = xs.shape
    mx = (xs - 0.5).reshape(shape[0] * shape[1], -1).astype(np.float32)  # OpenCV: centres at ints
    my = (ys - 0.5).reshape(shape[0] * shape[1], -1).astype(np.float32)
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(shape).astype(np.float32)


def sample_patches(
    image: NDArray[np.uint8], centres: Array, d: Array, half: int
) -> NDArray[np.float32]:
    """Patches (m, 2h+1, 2h+1) around ``centres`` (m, 2) with columns along ``d`` (m, 2, unit)
    and rows along ``rot90(d) = (-d_v, d_u)`` (so ``d = (1, 0)`` gives the upright patch)."""
    k = np.arange(-half, half + 1, dtype=float)
    n = np.column_stack([-d[:, 1], d[:, 0]])
    # point (row j, column i) = c + i d + j n
    xs = centres[:, 0, None, None] + k[None, None, :] * d[:, 0, None, None]
    xs = xs + k[None, :, None] * n[:, 0, None, None]
    ys = centres[:, 1, None, None] + k[None, None, :] * d[:, 1, None, None]
    ys = ys + k[None, :, None] * n[:, 1, None, None]
    return _sample(image, xs, ys)


class StereoMatcher:
    """Epipolar NCC matcher of a calibrated rig (tumblenav pixels in and out)."""

    def __init__(self, geometry: EpipolarGeometry, tuning: ImageFrontEndTuning) -> None:
        self.geometry = geometry
        self.tuning = tuning
        self.half = tuning.patch_px // 2
        w, h = geometry.size(1)
        margin = self.half * np.sqrt(2.0) + 1.0  # a rotated patch stays inside the image
        self._lo = np.array([margin, margin])
        self._hi = np.array([w - margin, h - margin])
        self._criteria = (
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
            tuning.lk_max_iterations,
            tuning.lk_epsilon_px,
        )

    def match(
        self,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        uv_l: Array,
        depth_prior_m: Array | None = None,
    ) -> Matches:
        """Right matches of the left pixels ``uv_l`` (m, 2).

        ``depth_prior_m`` (m,): previous depth along the left optical axis of tracked features
        (NaN: none); with a prior the search covers ``track_search_px`` either side of its point
        on the epipolar line, without one the whole segment of the depth range.
        """
        tu = self.tuning
        geo = self.geometry
        m = len(uv_l)
        status = np.full(m, MatchStatus.OK, dtype=np.int8)
        uv_r = np.full((m, 2), np.nan)
        score = np.full(m, np.nan)
        if m == 0:
            return Matches(uv_r, score, status)
        prior = np.full(m, np.nan) if depth_prior_m is None else np.asarray(depth_prior_m, float)
        windowed = np.isfinite(prior) & (prior > 0.0)
        lam_nom = np.where(windowed, prior, 4.0 * tu.min_depth_m)
        d_l, d_r = geo.directions(uv_l, lam_nom)

        # the search segment on the right epipolar line, oriented along d_r
        near, far = geo.right_segments(uv_l, tu.min_depth_m, tu.max_depth_m)
        flip = np.sum((far - near) * d_r, axis=1) < 0.0
        q0 = np.where(flip[:, None], far, near)
        q1 = np.where(flip[:, None], near, far)
        if windowed.any():
            q = geo.right_of_depth(uv_l[windowed], prior[windowed])
            s = tu.track_search_px
            q0[windowed] = q - s * d_r[windowed]
            q1[windowed] = q + s * d_r[windowed]
        p0, p1, inside = clip_segments(q0, q1, self._lo, self._hi)
        inside &= np.all(np.isfinite(d_r), axis=1) & np.all(np.isfinite(d_l), axis=1)
        n_pos = np.where(inside, np.floor(np.hypot(*(p1 - p0).T) + 1e-9).astype(np.intp) + 1, 0)
        status[n_pos < 3] = MatchStatus.NO_SEGMENT

        h = self.half
        todo = np.flatnonzero(status == MatchStatus.OK)
        if todo.size == 0:
            return Matches(uv_r, score, status)
        patches = sample_patches(left, uv_l[todo], d_l[todo], h)
        flat = patches.std(axis=(1, 2)) < tu.min_patch_std
        status[todo[flat]] = MatchStatus.NO_TEXTURE
        patches = patches[~flat]
        todo = todo[~flat]
        if todo.size == 0:
            return Matches(uv_r, score, status)

        # strips: rows j along n_r, columns s = -h .. n_pos - 1 + h along d_r from p0
        L = int(n_pos[todo].max()) + 2 * h
        cols = np.arange(L, dtype=float) - h
        rows = np.arange(-h, h + 1, dtype=float)
        dr = d_r[todo]
        nr = np.column_stack([-dr[:, 1], dr[:, 0]])
        xs = p0[todo, 0, None, None] + cols[None, None, :] * dr[:, 0, None, None]
        xs = xs + rows[None, :, None] * nr[:, 0, None, None]
        ys = p0[todo, 1, None, None] + cols[None, None, :] * dr[:, 1, None, None]
        ys = ys + rows[None, :, None] * nr[:, 1, None, None]
        strips = _sample(right, xs, ys)

        for r, k in enumerate(todo):
            n = int(n_pos[k])
            sc = cv2.matchTemplate(strips[r, :, : n + 2 * h], patches[r], cv2.TM_CCOEFF_NORMED)[0]
            i = int(np.argmax(sc))
            best = float(sc[i])
            score[k] = best
            if best < tu.ncc_min:
                status[k] = MatchStatus.LOW_SCORE
                continue
            if i == 0 or i == n - 1:
                status[k] = MatchStatus.EDGE
                continue
            if not windowed[k]:
                far_away = np.abs(np.arange(n) - i) > tu.patch_px
                if far_away.any() and sc[far_away].max() > best - tu.ncc_unique_margin:
                    status[k] = MatchStatus.NOT_UNIQUE
                    continue
            sm, s0, sp = float(sc[i - 1]), best, float(sc[i + 1])
            den = sm - 2.0 * s0 + sp  # parabola through the peak and its neighbours
            off = min(max(0.5 * (sm - sp) / den, -0.5), 0.5) if den < 0.0 else 0.0
            uv_r[k] = p0[k] + (i + off) * d_r[k]

        ok = np.flatnonzero(status == MatchStatus.OK)
        if tu.lk_refine and ok.size:
            uv_r[ok] = self._refine(left, right, uv_l[ok], uv_r[ok])
        if tu.affine_match_refine and ok.size:
            uv_r[ok] = self._refine_affine(left, right, uv_l[ok], uv_r[ok])
        return Matches(uv_r, score, status)

    def _refine_affine(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv_l: Array, uv_r: Array
    ) -> Array:
        """The affine ECC refinement of the matches (``affine_match_refine``,
        :mod:`~tumblenav.frontends.stereo_images.refine`): the left patch warped into the right
        image from the match; refused (the match kept) when it fails, scores below
        template_min_cc, moves more than epipolar_tol_px or leaves the epipolar band."""
        tu = self.tuning
        res = refine_affine(
            template_at(left, uv_l, tu.template_px),
            right,
            uv_r,
            np.broadcast_to(np.eye(2), (len(uv_l), 2, 2)),
            tu.template_min_cc,
            tu.epipolar_tol_px,
        )
        good = res.ok & (self.geometry.epipolar_distance(uv_l, res.uv) <= tu.epipolar_tol_px)
        return np.where(good[:, None], res.uv, uv_r)

    def _refine(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8], uv_l: Array, uv_r: Array
    ) -> Array:
        """One full-resolution LK step left -> right from the NCC match; refused (NCC kept) when
        it fails, moves more than epipolar_tol_px, or leaves the epipolar band."""
        tu = self.tuning
        p_l = (uv_l - 0.5).astype(np.float32).reshape(-1, 1, 2)
        p_r = (uv_r - 0.5).astype(np.float32).reshape(-1, 1, 2)
        out, st, _ = cv2.calcOpticalFlowPyrLK(
            left,
            right,
            p_l,
            p_r.copy(),
            winSize=(tu.patch_px, tu.patch_px),
            maxLevel=0,
            criteria=self._criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            minEigThreshold=tu.lk_min_eigen,
        )
        ref = out.reshape(-1, 2).astype(float) + 0.5
        good = (st.ravel() == 1) & np.all(np.isfinite(ref), axis=1)
        good &= np.hypot(*(ref - uv_r).T) <= tu.epipolar_tol_px
        good &= self.geometry.epipolar_distance(uv_l, ref) <= tu.epipolar_tol_px
        return np.where(good[:, None], ref, uv_r)
