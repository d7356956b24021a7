"""Planes in depth point clouds (Yu 2019 Sec. 2.1-2.2): RANSAC extraction, the point-cloud
distribution matrix and rectangle recognition.

- :func:`ransac_iterations` is Yu 2019 eq. 2; :func:`ransac_plane` the RANSAC of Sec. 2.1 with
  the point-to-plane distance of eq. 1, vectorised over hypotheses (all hypotheses of a round
  are scored in one matrix product), with an adaptive stop when eq. 2 is met for the inlier
  ratio found so far, and a least-squares refit on the consensus set.
- :func:`distribution_matrix` is eq. 3-5 (centroid, matrix J, eigen-decomposition).
- :func:`rectangle_sides` inverts eq. 17: ``E(I) = side^2 / 12 + sigma^2``.

Written with numpy rather than taken from Open3D (``segment_plane``), which is a 600 MB
dependency; Open3D is the reference in ``benchmarks/plane_extraction.py`` when installed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def ransac_iterations(outlier_fraction: float, probability: float = 0.99, sample: int = 3) -> int:
    """Yu 2019 eq. 2: ``K = log(1 - Phi) / log(1 - (1 - tau)^3)`` (rounded up).

    ``tau`` is the proportion of outliers, ``Phi`` the probability that at least one sample of
    three points is outlier-free.
    """
    if not 0.0 <= outlier_fraction < 1.0:
        raise ValueError(f"outlier_fraction must be in [0, 1), got {outlier_fraction}")
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability}")
    good = (1.0 - outlier_fraction) ** sample
    if good >= 1.0:
        return 1
    return max(1, math.ceil(math.log(1.0 - probability) / math.log(1.0 - good)))


@dataclass(frozen=True)
class PlaneFit:
    """A plane ``n . x + d = 0`` (unit normal) and its consensus set."""

    normal: Array  # (3,)
    d: float
    inliers: NDArray[np.bool_]  # (N,)
    iterations: int

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def _clean(points: Array) -> Array:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    return p


def ransac_plane(
    points: Array,
    threshold: float,
    rng: np.random.Generator,
    max_iterations: int = 300,
    probability: float = 0.99,
    adaptive: bool = True,
    batch: int = 16,
) -> PlaneFit | None:
    """The plane with the largest consensus (Yu 2019 Sec. 2.1, steps 1-5), or None.

    Non-finite points never vote and are never inliers. With ``adaptive`` the search stops as
    soon as the number of hypotheses drawn reaches eq. 2's ``K`` for the best inlier ratio found
    so far (never more than ``max_iterations``); hypotheses are drawn and scored ``batch`` at a
    time. The returned plane is the least-squares plane of the consensus set, whose inliers are
    then recounted.
    """
    p = _clean(points)
    finite = np.all(np.isfinite(p), axis=1)
    idx = np.flatnonzero(finite)
    if len(idx) < 3:
        return None
    q = p[idx]
    n = len(q)
    best_count, best = -1, None
    drawn = 0
    need = max_iterations
    while drawn < min(need, max_iterations):
        m = min(batch, min(need, max_iterations) - drawn)
        tri = rng.integers(0, n, size=(m, 3))  # repeated indices give a zero normal: dropped
        a, b, c = q[tri[:, 0]], q[tri[:, 1]], q[tri[:, 2]]
        nrm = np.cross(b - a, c - a)
        ln = np.linalg.norm(nrm, axis=1)
        ok = ln > 1e-12 * np.maximum(1.0, np.abs(q).max()) ** 2
        nrm = nrm[ok] / ln[ok, None]
        dd = -np.sum(nrm * a[ok], axis=1)
        drawn += m
        if len(nrm) == 0:
            continue
        # Yu 2019 eq. 1 for every point and hypothesis at once
        counts = np.sum(np.abs(q @ nrm.T + dd) < threshold, axis=0)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best = int(counts[k]), (nrm[k], dd[k])
            if adaptive:
                need = ransac_iterations(1.0 - best_count / n, probability)
    if best is None or best_count < 3:
        return None
    normal, d = best
    inl = np.abs(q @ normal + d) < threshold
    # refit on the consensus set (least squares: normal = smallest principal direction)
    c0 = q[inl].mean(axis=0)
    _, _, vt = np.linalg.svd(q[inl] - c0, full_matrices=False)
    normal = vt[-1]
    d = -float(normal @ c0)
    inl = np.abs(q @ normal + d) < threshold
    full = np.zeros(len(p), dtype=bool)
    full[idx[inl]] = True
    return PlaneFit(normal=normal, d=d, inliers=full, iterations=drawn)


def extract_planes(
    points: Array,
    threshold: float,
    rng: np.random.Generator,
    min_points: int = 50,
    max_planes: int = 5,
    **kwargs,
) -> list[PlaneFit]:
    """Several planes: RANSAC, remove the consensus set, repeat while a plane keeps at least
    ``min_points`` points. Inlier masks refer to the input points."""
    p = _clean(points)
    remaining = np.all(np.isfinite(p), axis=1)
    planes: list[PlaneFit] = []
    while len(planes) < max_planes and remaining.sum() >= max(3, min_points):
        sub = np.where(remaining[:, None], p, np.nan)
        fit = ransac_plane(sub, threshold, rng, **kwargs)
        if fit is None or fit.n_inliers < min_points:
            break
        planes.append(fit)
        remaining &= ~fit.inliers
    return planes


@dataclass(frozen=True)
class Distribution:
    """Yu 2019 eq. 3-5: centroid ``r_m``, distribution matrix ``J``, eigenvalues (ascending)
    and eigenvectors (columns), with ``J = R diag(lam) R^T``."""

    centroid: Array
    J: Array
    eigenvalues: Array
    R: Array


def distribution_matrix(points: Array, weights: Array | None = None) -> Distribution:
    """Centroid (eq. 3), distribution matrix (eq. 4) and its eigen-decomposition (eq. 5).

    ``weights`` (tumblenav default, beyond Yu 2019): per-point weights for a weighted mean and
    matrix, e.g. the surface area each ray of a scanning sensor stands for
    (:func:`ray_footprint_weights`); None is Yu's plain mean."""
    p = _clean(points)
    finite = np.all(np.isfinite(p), axis=1)
    if weights is not None and np.shape(weights) != (len(p),):
        raise ValueError(f"weights must have shape ({len(p)},), got {np.shape(weights)}")
    p = p[finite]
    if len(p) < 3:
        raise ValueError("a distribution matrix needs at least 3 finite points")
    if weights is None:
        w = np.full(len(p), 1.0 / len(p))
    else:
        w = np.asarray(weights, dtype=float)[finite]
        if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError("weights must be finite and non-negative, not all 0")
        w = w / w.sum()
    rm = w @ p  # eq. 3
    d = p - rm
    J = (d * w[:, None]).T @ d  # eq. 4
    lam, R = np.linalg.eigh(J)  # eq. 5 (ascending eigenvalues)
    return Distribution(centroid=rm, J=J, eigenvalues=lam, R=R)


def ray_footprint_weights(points_S: Array, normal_S: Array) -> Array:
    """The surface area each return of a ray-grid sensor (origin at the sensor) stands for on
    a plane with unit normal ``normal_S`` (tumblenav default): a ray of fixed solid angle
    covers ``rho^2 / cos(i)`` of the plane, ``cos(i) = |n . p| / rho``, so ``rho^3 / |n . p|``.

    Equal-angle rays sample a tilted plane more densely on its near side; Yu's plain centroid
    (eq. 3) then lies ``side^2 sin(tilt) / (6 rho)`` towards the sensor (8 mm for Yu's 1.5 m
    face at 25 m, 45 deg), a bias that does not average out over scans. Weighting each point
    by its footprint restores the area centroid and the area moments of eq. 17."""
    p = np.asarray(points_S, dtype=float)
    rho = np.linalg.norm(p, axis=1)
    along = np.abs(p @ np.asarray(normal_S, dtype=float))
    return rho**3 / np.maximum(along, 1e-6 * np.maximum(rho, 1e-12))


def rectangle_sides(eigenvalues: Array, sigma: float = 0.0) -> tuple[float, float, float]:
    """Side lengths (short, long) and the out-of-plane noise estimate from the eigenvalues of a
    rectangular point cloud, inverting Yu 2019 eq. 17: ``E(I) = side^2/12 + sigma^2``
    (``E(I_z) = sigma^2``). ``sigma`` is the known per-axis noise; the smallest eigenvalue
    gives an estimate of it, returned as the third value."""
    lam = np.sort(np.asarray(eigenvalues, dtype=float))
    s2 = sigma**2
    b = math.sqrt(max(12.0 * (lam[1] - s2), 0.0))
    a = math.sqrt(max(12.0 * (lam[2] - s2), 0.0))
    return b, a, math.sqrt(max(lam[0], 0.0))


def side_mismatch(sides: tuple[float, float], known: tuple[float, float]) -> float:
    """Largest relative difference between two rectangles' (short, long) sides."""
    b, a = sorted(sides)
    kb, ka = sorted(known)
    return max(abs(b - kb) / kb, abs(a - ka) / ka)


def match_rectangle(
    sides: tuple[float, float], known: dict[str, tuple[float, float]], rel_tol: float = 0.05
) -> str | None:
    """Name of the known rectangle whose (short, long) sides match within ``rel_tol``."""
    best, err = None, rel_tol
    for name, k in known.items():
        e = side_mismatch(sides, k)
        if e <= err:
            best, err = name, e
    return best


def in_window(s: Array, length: float) -> NDArray[np.bool_]:
    """The points of the largest set of 1-D positions ``s`` that fits in one window of the
    given ``length`` (ties: the first), tumblenav default: on a rectangle of known side the
    points beyond it (an outlier that fell into the plane's slab, a stray surface) are left
    out of its centroid."""
    x = np.asarray(s, dtype=float)
    if len(x) == 0:
        return np.zeros(0, dtype=bool)
    xs = np.sort(x)
    end = np.searchsorted(xs, xs + length, side="right")  # window [xs_i, xs_i + length]
    i = int(np.argmax(end - np.arange(len(xs))))
    return (x >= xs[i]) & (x <= xs[end[i] - 1])


# --- coarse pose and the four-fold symmetry of a rectangle (Yu 2019 Sec. 2.3) --------------

# The four frames a rectangle's eigenvectors can give (Yu 2019 Fig. 2): identity and the
# half turns about the frame's X, Y and Z axes (eq. 25 with theta = 180 deg).
RECTANGLE_SYMMETRIES = np.array(
    [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
)


def rectangle_frame(dist: Distribution) -> Array:
    """``R_CP``: the rectangle's body frame P in the sensor frame C (Yu 2019 Sec. 2.2-2.3).

    Columns: X along the short side (middle eigenvalue), Y along the long side (largest),
    Z = X x Y along the normal (smallest); a proper rotation. The eigenvectors' signs are
    arbitrary: the result is one of the four cases of Fig. 2, see :func:`resolve_symmetry`.
    Yu 2019 eq. 20 turns this matrix into a (scalar-first) quaternion; tumblenav keeps the
    matrix and converts with :func:`tumblenav.rotations.matrix_to_quat` where needed.
    """
    R = dist.R  # ascending eigenvalues: (normal, short, long)
    x, y = R[:, 1], R[:, 2]
    return np.column_stack([x, y, np.cross(x, y)])


def resolve_symmetry(R_CP: Array, R_CP_predicted: Array) -> tuple[Array, int]:
    """Yu 2019 eq. 21-25: among the four symmetric frames of a rectangle, the one closest to
    the prediction (the case whose difference rotation has a scalar part near 1, eq. 23).

    Returns the corrected ``R_CP`` and the index of the half turn applied (0 = none, 1-3 =
    about X, Y, Z, Yu's cases 2-4).
    """
    cands = R_CP @ RECTANGLE_SYMMETRIES  # R_CP q' (eq. 24) for every case
    # trace(R_pred^T R) = 1 + 2 cos(angle): the largest is the smallest rotation (eq. 23)
    score = np.einsum("ij,kij->k", R_CP_predicted, cands)
    k = int(np.argmax(score))
    return cands[k], k
