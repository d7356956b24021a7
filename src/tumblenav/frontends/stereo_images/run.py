"""Track a whole sequence of stereo pairs into :class:`~tumblenav.measurements.StereoMeasurements`."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

from tumblenav.errors import InputError
from tumblenav.frontends.stereo_images.tracker import FrameStats, ImageTracker
from tumblenav.frontends.stereo_images.tuning import DEFAULT_TUNING, ImageFrontEndTuning
from tumblenav.measurements.stereo import StereoMeasurements
from tumblenav.sensors.stereo import StereoRig

Array = NDArray[np.float64]

__all__ = ["FrontEndStats", "track_images"]


@dataclass(frozen=True)
class FrontEndStats:
    """Per-epoch counts of the image front end: one (n,) int64 array per :class:`FrameStats`
    field (``detected``, ``tracked``, ``lost``, ``fb_rejected``, ``template_rejected``, ``matched``,
    ``epipolar_rejected``, ``new``, ``aged``, ``removed``, ``features``), plus ``track_length``
    (the number of epochs each feature ID was observed, (N,))."""

    counts: dict[str, NDArray[np.int64]]
    track_length: NDArray[np.int64]

    @classmethod
    def from_frames(
        cls, frames: list[FrameStats], track_length: NDArray[np.int64]
    ) -> FrontEndStats:
        names = [f.name for f in fields(FrameStats)]
        counts = {n: np.array([getattr(s, n) for s in frames], dtype=np.int64) for n in names}
        return cls(counts=counts, track_length=track_length)

    @property
    def totals(self) -> dict[str, int]:
        """Sums over the epochs (``features``: the sum of per-epoch feature counts)."""
        return {k: int(v.sum()) for k, v in self.counts.items()}

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary: totals, features held (mean / min after the first epoch), track
        lengths (IDs, mean, median, max in epochs)."""
        feats = self.counts["features"]
        tl = self.track_length
        return {
            "epochs": int(len(feats)),
            "totals": self.totals,
            "features_mean": float(feats.mean()) if len(feats) else 0.0,
            "features_min": int(feats.min()) if len(feats) else 0,
            "feature_ids": int(len(tl)),
            "track_length_mean": float(tl.mean()) if len(tl) else 0.0,
            "track_length_median": float(np.median(tl)) if len(tl) else 0.0,
            "track_length_max": int(tl.max()) if len(tl) else 0,
        }


def track_images(
    frames: Iterable[tuple[NDArray[np.uint8], NDArray[np.uint8]]],
    t: Array,
    rig: StereoRig,
    q_CL: Array,
    q_LI: Array,
    noise_px: float,
    tuning: ImageFrontEndTuning = DEFAULT_TUNING,
    progress: Callable[[int], None] | None = None,
) -> tuple[StereoMeasurements, FrontEndStats]:
    """Run :class:`ImageTracker` over a sequence of (left, right) grey images.

    Parameters
    ----------
    frames : iterable of (left, right) uint8 (H, W) arrays
        Consumed lazily, one pair at a time; exactly ``len(t)`` pairs.
    t : (n,) array
        Epoch of each pair (s).
    rig : StereoRig
        The calibrated rig that took the images.
    q_CL, q_LI : (n, 4) arrays
        Rig and LVLH attitudes (known to the chaser), passed through.
    noise_px : float
        Pixel noise (px) the estimators should assume for the tracked features.
    tuning : ImageFrontEndTuning
    progress : callable, optional
        Called with the epoch index after each pair.

    Returns
    -------
    StereoMeasurements
        ``uv`` (n, 2, N, 2) with the feature axis the feature ID (N = IDs created), NaN where
        unobserved; ``observed`` (n, 2, N) True in both cameras where the feature was tracked
        in the left image and matched in the right one.
    FrontEndStats
    """
    t = np.asarray(t, dtype=float)
    n = len(t)
    q_CL = np.asarray(q_CL, dtype=float)
    q_LI = np.asarray(q_LI, dtype=float)
    if q_CL.shape != (n, 4) or q_LI.shape != (n, 4):
        raise InputError(f"q_CL and q_LI must have shape ({n}, 4), got {q_CL.shape}, {q_LI.shape}")
    if not noise_px >= 0.0:
        raise InputError(f"noise_px must be >= 0, got {noise_px}")
    tracker = ImageTracker(rig, tuning)
    ids: list[NDArray[np.int64]] = []
    uvs: list[Array] = []
    stats: list[FrameStats] = []
    k = -1
    for k, (left, right) in enumerate(frames):
        if k >= n:
            raise InputError(f"more image pairs than epochs ({n})")
        fr = tracker.step(left, right)
        ids.append(fr.ids)
        uvs.append(fr.uv)
        stats.append(fr.stats)
        if progress is not None:
            progress(k)
    if k + 1 != n:
        raise InputError(f"{k + 1} image pairs for {n} epochs")
    N = tracker.next_id
    uv = np.full((n, 2, N, 2), np.nan)
    observed = np.zeros((n, 2, N), dtype=bool)
    for e, (i, u) in enumerate(zip(ids, uvs, strict=True)):
        uv[e][:, i] = u
        observed[e][:, i] = True
    track_length = observed[:, 0].sum(axis=0).astype(np.int64)
    meas = StereoMeasurements(
        t=t,
        uv=uv,
        observed=observed,
        q_CL=q_CL,
        q_LI=q_LI,
        rig=rig,
        noise_px=float(noise_px),
        slide_px2_per_frame=tuning.slide_px2(),
        track_noise_px=tuning.tracked_noise_px(float(noise_px)),
    )
    return meas, FrontEndStats.from_frames(stats, track_length)
