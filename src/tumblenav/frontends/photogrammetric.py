"""Photogrammetric target frame G and its angular rate (Hu 2024 Sec. 3, eq. 6-7 and 15-16).

G is a target-fixed frame built from three triangulated features ``m1, m2, m3`` (rig frame C):
origin at ``m1``, ``x_G`` along ``m2 - m1``, ``z_G`` normal to the features' plane.  Because
the features are arbitrary, G is *not* a principal frame; :mod:`tumblenav.frontends.inertia`
identifies the inertia in G and rotates G into the principal frame T.

Keeping G through occlusion
---------------------------
Once G is defined, every tracked feature gets constant G coordinates
(:func:`features_in_G`).  When one of the three defining features is occluded, G is recovered
from *any* three or more visible features with known G coordinates by a least-squares rigid
alignment (:func:`recover_G`, Kabsch/Horn).  These helpers hold no state: the caller keeps
the feature catalogue ``p_inG_known``.

Rate of G (Hu 2024 eq. 15-16 in tumblenav's convention)
-------------------------------------------------------
Hu 2024 writes (JPL quaternions) ``omega = 2 Xi(q)^T q_dot`` with
``Xi(q) = [q4 I3 + [q_{1:3} x]; -q_{1:3}^T]``.  With tumblenav's Hamilton quaternions and
``dq_GI/dt = -1/2 [omega; 0] (x) q_GI`` (:mod:`tumblenav.rotations`) the same relation is::

    [omega; 0] = -2 q_dot (x) conj(q)
    omega      = 2 Xi_H(q)^T q_dot,   Xi_H(q) = [[q_v x] - q_w I3 ; q_v^T]      (4 x 3)

(the scalar part of ``q_dot (x) conj(q)`` vanishes because ``q . q_dot = 0``).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from itertools import combinations
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tumblenav.rotations import log_quat, matrix_to_quat, quat_conjugate, quat_multiply, skew

Array = NDArray[np.float64]

__all__ = [
    "GAlignment",
    "best_triplet",
    "features_in_G",
    "g_frame_from_points",
    "rate_from_attitudes",
    "recover_G",
    "triplet_score",
]


def g_frame_from_points(m1: ArrayLike, m2: ArrayLike, m3: ArrayLike) -> Array:
    """Attitude ``R_GC`` of the photogrammetric frame G from three features (Hu 2024 eq. 6-7).

    ::

        c1 = (m2 - m1) / |m2 - m1|
        c3 = (m2 - m1) x (m3 - m1) / |(m2 - m1) x (m3 - m1)|
        c2 = c3 x c1
        R_GC = [c1 c2 c3]^T          (rows are G's axes expressed in C)

    The origin of G is ``m1``.  ``p_inG = R_GC (p_inC - m1)``.

    Parameters
    ----------
    m1, m2, m3 : array_like, shape (..., 3)
        The three features in the rig frame C (m); any leading (e.g. time) axes broadcast.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        ``R_GC``, a proper rotation.  All-NaN where the features coincide or are collinear
        (or contain NaN).
    """
    m1 = np.asarray(m1, dtype=float)
    e12 = np.asarray(m2, dtype=float) - m1
    e13 = np.asarray(m3, dtype=float) - m1
    e12, e13 = np.broadcast_arrays(e12, e13)
    n = np.cross(e12, e13)
    l12 = np.linalg.norm(e12, axis=-1, keepdims=True)
    ln = np.linalg.norm(n, axis=-1, keepdims=True)
    # Collinear (|n| tiny relative to the sides) or coincident features define no frame.
    ok = (ln > 1e-12 * l12 * np.linalg.norm(e13, axis=-1, keepdims=True)) & (l12 > 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        c1 = e12 / np.where(ok, l12, 1.0)
        c3 = n / np.where(ok, ln, 1.0)
    c2 = np.cross(c3, c1)
    R = np.stack([c1, c2, c3], axis=-2)  # Hu 2024 eq. 7: rows c1, c2, c3
    return np.where(ok[..., None], R, np.nan)


def triplet_score(m1: ArrayLike, m2: ArrayLike, m3: ArrayLike) -> Array:
    """Conditioning score of a feature triplet: the triangle's smallest altitude (m).

    ``score = 2 area / longest side``.  With ``m1 m2`` the longest side, the attitude error of
    G is about ``sigma / |m2 - m1|`` for ``x_G`` and ``sigma / h3`` for the tilt of ``z_G``
    about ``x_G`` (``h3`` = altitude of ``m3``), and ``h3 = score <= |m2 - m1|``; so the score
    bounds the worst of the two lever arms.  It is zero for collinear features and small for
    both small and slender triangles.  Shapes broadcast; NaN input gives a NaN score.
    """
    a = np.asarray(m1, dtype=float)
    b = np.asarray(m2, dtype=float)
    c = np.asarray(m3, dtype=float)
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    sides = np.stack(
        [
            np.linalg.norm(b - a, axis=-1),
            np.linalg.norm(c - b, axis=-1),
            np.linalg.norm(a - c, axis=-1),
        ],
        axis=-1,
    )
    longest = np.max(sides, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(longest > 0.0, area2 / np.where(longest > 0.0, longest, 1.0), 0.0)


def best_triplet(
    points: ArrayLike, visible: ArrayLike | None = None, *, max_candidates: int = 40
) -> tuple[int, int, int]:
    """Best-conditioned triplet of visible features to define G (Hu 2024 eq. 6 needs three).

    Maximises :func:`triplet_score` (smallest triangle altitude, m) over all triplets of
    visible features with finite coordinates, then orders the winner so that ``m1 m2`` is its
    longest side (``x_G`` along the longest lever arm) and ``m1`` has the lower index of the
    two.  Ties keep the lexicographically first triplet, so the result is deterministic.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Feature positions at the current epoch, rig frame C (m).  NaN rows count as invisible.
    visible : array_like of bool, shape (N,), optional
        Visibility mask (default: all features with finite coordinates).
    max_candidates : int
        The search is O(M^3) in the number M of visible features; above ``max_candidates`` only
        the ``max_candidates`` features farthest from the visible centroid are searched (a
        well-conditioned triangle uses the periphery of the point cloud).

    Returns
    -------
    (i, j, k) : tuple of int
        Indices into ``points`` of ``m1, m2, m3``.

    Raises
    ------
    ValueError
        Fewer than three usable features, or all usable features collinear.
    """
    p = np.asarray(points, dtype=float)
    usable = np.all(np.isfinite(p), axis=-1)
    if visible is not None:
        usable &= np.asarray(visible, dtype=bool)
    idx = np.flatnonzero(usable)
    if idx.size < 3:
        raise ValueError(f"need at least 3 visible features to define G, got {idx.size}")
    if idx.size > max_candidates:
        dist = np.linalg.norm(p[idx] - p[idx].mean(axis=0), axis=-1)
        idx = np.sort(idx[np.argsort(-dist, kind="stable")[:max_candidates]])
    tri = np.array(list(combinations(range(idx.size), 3)))
    q = p[idx]
    a, b, c = q[tri[:, 0]], q[tri[:, 1]], q[tri[:, 2]]
    score = triplet_score(a, b, c)
    best = int(np.argmax(score))
    scale = np.max(np.linalg.norm(q - q.mean(axis=0), axis=-1))
    if not score[best] > 1e-9 * scale:
        raise ValueError("all visible features are (nearly) collinear: G is undefined")
    i, j, k = (int(v) for v in idx[tri[best]])
    pairs = [((i, j), k), ((j, k), i), ((i, k), j)]
    lengths = [np.linalg.norm(p[s] - p[r]) for (s, r), _ in pairs]
    (s, r), o = pairs[int(np.argmax(lengths))]
    return (min(s, r), max(s, r), o)


def features_in_G(p_inC: ArrayLike, R_GC: ArrayLike, origin_inC: ArrayLike) -> Array:
    """Feature coordinates in G: ``p_inG = R_GC (p_inC - origin_inC)``.

    Parameters
    ----------
    p_inC : array_like, shape (..., N, 3) or (..., 3)
        Features in the rig frame C (m).
    R_GC : array_like, shape (..., 3, 3)
        Attitude of G (from :func:`g_frame_from_points` or :func:`recover_G`).
    origin_inC : array_like, shape (..., 3)
        Origin of G in C (``m1``), m.

    Returns
    -------
    numpy.ndarray
        ``p_inG`` (m), same shape as ``p_inC``; constant in time for a rigid target.
    """
    p = np.asarray(p_inC, dtype=float)
    R = np.asarray(R_GC, dtype=float)
    o = np.asarray(origin_inC, dtype=float)
    if p.ndim >= 2 and p.ndim == R.ndim:  # (..., N, 3) features with (..., 3, 3) frames
        return np.einsum("...ij,...nj->...ni", R, p - o[..., None, :])
    return np.einsum("...ij,...j->...i", R, p - o)


@dataclass(frozen=True)
class GAlignment:
    """Result of :func:`recover_G`; unpacks as ``R_GC, origin_inC = recover_G(...)``.

    Attributes
    ----------
    R_GC : numpy.ndarray, shape (3, 3)
        Attitude of G (maps C into G), a proper rotation.
    origin_inC : numpy.ndarray, shape (3,)
        Origin of G expressed in C (m).
    residual_rms_m : float
        RMS distance between the measured features and the aligned catalogue (m); a large
        value flags a mismatched feature or a non-rigid target.
    n_features : int
        Number of features used.
    """

    R_GC: Array
    origin_inC: Array
    residual_rms_m: float
    n_features: int

    def __iter__(self) -> Iterator[Array]:
        yield self.R_GC
        yield self.origin_inC


def recover_G(
    p_inC_visible: ArrayLike,
    p_inG_known: ArrayLike,
    idx: ArrayLike | None = None,
    weights: ArrayLike | None = None,
) -> GAlignment:
    """Recover G from any >= 3 non-collinear visible features with known G coordinates.

    Solves the weighted least-squares rigid alignment (Kabsch / Horn, SVD)::

        min_{R_CG, o} sum_i w_i | p_inC_i - (R_CG p_inG_i + o) |^2

    with ``H = sum w_i (p_inG_i - a_bar)(p_inC_i - b_bar)^T = U S V^T``,
    ``R_CG = V diag(1, 1, det(V U^T)) U^T`` (a proper rotation, det = +1) and
    ``o = b_bar - R_CG a_bar``; returns ``R_GC = R_CG^T`` and ``origin_inC = o``.  With noise-free
    features the original G is recovered exactly, whichever triplet defined it.

    Parameters
    ----------
    p_inC_visible : array_like, shape (M, 3)
        Visible features in the rig frame C at the current epoch (m).
    p_inG_known : array_like, shape (N, 3) or (M, 3)
        Catalogue of G coordinates (m); rows with NaN are "unknown" and ignored.
    idx : array_like of int, shape (M,), optional
        Catalogue row of each visible feature; if omitted, ``p_inG_known`` must have M rows
        in the same order as ``p_inC_visible``.
    weights : array_like, shape (M,), optional
        Non-negative weights (e.g. inverse depth variance).  Default: equal.

    Returns
    -------
    GAlignment

    Raises
    ------
    ValueError
        Fewer than three usable pairs, or the usable features are collinear.
    """
    b = np.asarray(p_inC_visible, dtype=float).reshape(-1, 3)
    a = np.asarray(p_inG_known, dtype=float).reshape(-1, 3)
    if idx is not None:
        a = a[np.asarray(idx, dtype=int)]
    if a.shape != b.shape:
        raise ValueError(f"p_inG rows {a.shape} do not match p_inC_visible rows {b.shape}")
    w = np.ones(len(b)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    use = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1) & (w > 0.0)
    a, b, w = a[use], b[use], w[use]
    if len(a) < 3:
        raise ValueError(f"need at least 3 features with known G coordinates, got {len(a)}")
    w = w / w.sum()
    a_bar = w @ a
    b_bar = w @ b
    A = a - a_bar
    B = b - b_bar
    sv = np.linalg.svd(A * np.sqrt(w)[:, None], compute_uv=False)
    if not sv[1] > 1e-9 * max(sv[0], 1e-300):
        raise ValueError("features used to recover G are collinear")
    H = (A * w[:, None]).T @ B
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(V @ U.T)) or 1.0])
    R_CG = V @ D @ U.T
    origin = b_bar - R_CG @ a_bar
    resid = b - (a @ R_CG.T + origin)
    rms = float(np.sqrt(np.sum(w * np.sum(resid**2, axis=1))))
    return GAlignment(R_GC=R_CG.T, origin_inC=origin, residual_rms_m=rms, n_features=len(a))


def _align_signs(q: Array) -> Array:
    """Flip quaternion signs along axis 0 so consecutive samples lie on the same hemisphere."""
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    flips = np.concatenate([[1.0], np.cumprod(np.where(dots < 0.0, -1.0, 1.0))])
    return q * flips[:, None]


def rate_from_attitudes(
    R_GC_seq: ArrayLike,
    t: ArrayLike,
    R_CI_seq: ArrayLike | None = None,
    *,
    method: Literal["geodesic", "quaternion"] = "geodesic",
) -> Array:
    """Angular rate of G relative to the inertial frame, in G, from sampled attitudes.

    The chaser's own rotation is removed first: ``R_GI = R_GC R_CI`` (``R_CI`` from the chaser's
    attitude determination and the rig mounting, ``R_CI = R_CB R_BI``).  Then, with
    ``dR_GI/dt = -[omega x] R_GI`` (``omega = omega_GI_G``):

    ``method="geodesic"`` (default)
        Midpoint rates ``omega_{k+1/2} = -Log(q_{k+1} (x) conj(q_k)) / (t_{k+1} - t_k)``
        (exact for a constant rate over the step, double cover handled by the log), linearly
        interpolated to the samples (second order, also for uneven steps) and linearly
        extrapolated at the two ends.  Exact for any rotation at a constant rate in G.
    ``method="quaternion"``
        Hu 2024 eq. 15-16 literally, in the Hamilton form ``omega = 2 Xi_H(q)^T q_dot`` with
        ``Xi_H(q) = [[q_v x] - q_w I3; q_v^T]``; ``q_dot`` is the second-order central
        difference of the sign-aligned quaternion sequence (``numpy.gradient``, second-order
        one-sided at the ends).  For a constant rate its relative error is about
        ``(|omega| dt)^2 / 24`` inside and ``(|omega| dt)^2 / 12`` at the two ends.

    Parameters
    ----------
    R_GC_seq : array_like, shape (n, 3, 3)
        Attitude of G relative to the rig, e.g. from :func:`g_frame_from_points` (n >= 2;
        n >= 3 for ``"quaternion"``).
    t : array_like, shape (n,)
        Strictly increasing sample times (s).  The rotation between two samples must stay
        below pi rad (sampling faster than twice the tumbling frequency).
    R_CI_seq : array_like, shape (n, 3, 3) or (3, 3), optional
        Attitude of the rig relative to inertial.  ``None`` means a non-rotating rig.

    Returns
    -------
    numpy.ndarray, shape (n, 3)
        ``omega_GI_G`` (rad/s).
    """
    R_GC = np.asarray(R_GC_seq, dtype=float)
    t = np.asarray(t, dtype=float)
    n = R_GC.shape[0]
    if t.shape != (n,):
        raise ValueError(f"t has shape {t.shape}, expected ({n},)")
    if n < 2 or not np.all(np.diff(t) > 0.0):
        raise ValueError("need at least 2 samples with strictly increasing times")
    R_GI = R_GC if R_CI_seq is None else R_GC @ np.asarray(R_CI_seq, dtype=float)
    q = matrix_to_quat(R_GI)  # q_GI
    if method == "quaternion":
        if n < 3:
            raise ValueError("method='quaternion' needs at least 3 samples")
        q = _align_signs(q)
        q_dot = np.gradient(q, t, axis=0, edge_order=2)
        qv, qw = q[:, :3], q[:, 3]
        # Xi_H(q) = [[q_v x] - q_w I3 ; q_v^T]   (Hamilton form of Hu 2024 eq. 16)
        xi = np.concatenate([skew(qv) - qw[:, None, None] * np.eye(3), qv[:, None, :]], axis=1)
        return 2.0 * np.einsum("nji,nj->ni", xi, q_dot)  # Hu 2024 eq. 15
    if method != "geodesic":
        raise ValueError(f"unknown method {method!r}")
    h = np.diff(t)
    w_mid = -log_quat(quat_multiply(q[1:], quat_conjugate(q[:-1]))) / h[:, None]
    if n == 2:
        return np.repeat(w_mid, 2, axis=0)
    out = np.empty((n, 3))
    h0, h1 = h[:-1, None], h[1:, None]
    out[1:-1] = (h1 * w_mid[:-1] + h0 * w_mid[1:]) / (h0 + h1)
    out[0] = w_mid[0] + (w_mid[0] - w_mid[1]) * h[0] / (h[0] + h[1])
    out[-1] = w_mid[-1] + (w_mid[-1] - w_mid[-2]) * h[-1] / (h[-1] + h[-2])
    return out
