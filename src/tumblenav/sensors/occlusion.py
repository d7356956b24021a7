"""Visibility masks: scheduled measurement loss, long-term occlusion and self-occlusion.

All masks are boolean and True where the feature / epoch is **visible**.  Epoch masks have
shape ``(n,)``; pass them to :func:`tumblenav.sensors.stereo.measure` as ``m[:, None, None]``.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

BoolArray = NDArray[np.bool_]

__all__ = ["loss_from_mask", "scheduled_mask", "self_occlusion_mask"]


def scheduled_mask(t: ArrayLike, windows: Iterable[tuple[float, float]]) -> BoolArray:
    """Visibility over time with complete measurement loss inside given windows.

    Hu 2024 Sec. 5 (Fig. 3) removes every measurement for 20 s, about half a rotation period
    of the target (``|w0| ~ 10 deg/s``).

    Parameters
    ----------
    t : (n,) array
        Epochs (s).
    windows : iterable of (start_s, end_s)
        Loss windows (s); each is half-open, ``start_s <= t < end_s``.

    Returns
    -------
    (n,) bool array
        True where the epoch is outside every window (measurements available).
    """
    t = np.asarray(t, dtype=float)
    visible = np.ones(t.shape, dtype=bool)
    for start, end in windows:
        if end < start:
            raise ValueError(f"loss window ends before it starts: ({start}, {end})")
        visible &= ~((t >= start) & (t < end))
    return visible


def loss_from_mask(t: ArrayLike, t_loss_s: float | None) -> BoolArray:
    """Visibility over time with all measurements lost from ``t_loss_s`` on.

    Kabir 2025 Sec. 2.5 and 3.2: stereo data for ``T_train = 1500 s``, then long-term
    occlusion until the end of the run.

    Parameters
    ----------
    t : (n,) array
        Epochs (s).
    t_loss_s : float or None
        Start of the permanent loss (s); ``None`` keeps every epoch visible.

    Returns
    -------
    (n,) bool array
        True for ``t < t_loss_s``.
    """
    t = np.asarray(t, dtype=float)
    if t_loss_s is None:
        return np.ones(t.shape, dtype=bool)
    return t < float(t_loss_s)


def self_occlusion_mask(
    p_FinC: ArrayLike, n_FinC: ArrayLike, cam_centres_inC: ArrayLike
) -> BoolArray:
    """Self-occlusion by surface orientation: a feature faces a camera or is hidden.

    A feature at ``p`` with outward surface normal ``n`` is seen by a camera at ``c`` only
    while ``dot(n, c - p) > 0`` (the angle between the normal and the direction to the camera
    is acute; Hu 2024 Sec. 5, their ref. [29]).  Exact for convex bodies only; it ignores
    occlusion by other parts of a concave target.

    Parameters
    ----------
    p_FinC : (..., N, 3) array
        Feature positions in the rig frame ``C`` (m).
    n_FinC : (..., N, 3) array
        Outward surface normals at the features, in ``C`` (any length > 0).
    cam_centres_inC : (2, 3) array
        Centres of projection (left, right) in ``C`` (m), e.g. ``StereoRig.centres_inC``.

    Returns
    -------
    (..., 2, N) bool array
        True where the feature faces that camera.
    """
    p = np.asarray(p_FinC, dtype=float)
    n = np.asarray(n_FinC, dtype=float)
    c = np.asarray(cam_centres_inC, dtype=float)
    if c.ndim != 2 or c.shape[-1] != 3:
        raise ValueError(f"cam_centres_inC must have shape (K, 3), got {c.shape}")
    to_cam = c[:, None, :] - p[..., None, :, :]  # (..., K, N, 3)
    return np.sum(n[..., None, :, :] * to_cam, axis=-1) > 0.0
