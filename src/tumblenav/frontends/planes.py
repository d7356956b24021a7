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


KAPPA_SPREAD = 0.2  # the relative uncertainty of the grid's phase drift along a side


def ray_lattice(uv: Array) -> Array | None:
    """The two step vectors (2, 2) of a ray grid seen in the sensor's image-plane coordinates
    ``uv`` (N, 2) (``x / y, z / y`` for a boresight along +y), from the points' nearest
    neighbours (tumblenav): the most common nearest-neighbour direction and the shortest
    common one across it. None when fewer than 8 points or no second direction."""
    from scipy.spatial import cKDTree

    if len(uv) < 8:
        return None
    d, j = cKDTree(uv).query(uv, k=5)
    vec = (uv[j[:, 1:]] - uv[:, None, :]).reshape(-1, 2)
    dist = d[:, 1:].ravel()
    ok = np.isfinite(dist) & (dist > 0)
    vec, dist = vec[ok], dist[ok]
    if len(vec) < 8:
        return None
    vec = np.where((vec[:, 1] < 0) | ((vec[:, 1] == 0) & (vec[:, 0] < 0)), -1, 1)[:, None] * vec
    ang = np.arctan2(vec[:, 1], vec[:, 0]) % np.pi
    short = dist < 1.3 * np.quantile(dist, 0.1)

    def peak(mask: NDArray[np.bool_]) -> Array | None:
        if mask.sum() < 4:
            return None
        a = ang[mask]
        hist, edges = np.histogram(a, bins=36, range=(0.0, np.pi))
        i = int(np.argmax(hist))
        c = 0.5 * (edges[i] + edges[i + 1])
        near = mask & (np.abs((ang - c + np.pi / 2) % np.pi - np.pi / 2) < np.pi / 36)
        v = vec[near]
        v = np.where((v @ np.array([np.cos(c), np.sin(c)]) < 0)[:, None], -v, v)
        return np.median(v, axis=0)

    g1 = peak(short)
    if g1 is None:
        return None
    across = np.abs(np.sin(ang - np.arctan2(g1[1], g1[0]))) > np.sin(np.radians(20.0))
    if across.sum() < 4:
        return None
    g2 = peak(across & (dist < 1.3 * np.quantile(dist[across], 0.1)))
    if g2 is None:
        return None
    return np.array([g1, g2])


def edge_turn(
    points_S: Array,
    R_SP: Array,
    centre_S: Array,
    sides_m: tuple[float, float],
    sigma: float = 0.0,
    cloud_S: Array | None = None,
    threshold_m: float = 0.0,
) -> tuple[float, float, int] | None:
    """The turn ``delta`` (rad) about the normal that aligns the rectangle frame ``R_SP`` (X
    short side, Y long side) with the face's edges, its variance (rad^2), and the number of
    edge points used (tumblenav, beyond Yu 2019's second moments; None when the edges do not
    determine it).

    Why: the second moments of a face sampled by a regular ray grid turn with the grid's
    phase along the edges (docs/results/consistency.md, Yu section: a per-face bias of up to
    8 mrad and heavy tails). Here each line of the grid that ends on the face brackets the
    edge between its last return and the next ray: that ray (one grid step on in the
    sensor's image plane, :func:`ray_lattice`) is intersected with the face's plane and the
    edge point taken midway. The bracket holds only if the next ray returned nothing or a
    point behind the plane (a point in front may hide the face, one on it is the face's), and
    none of the four rays after it is on the face (a return lost to an outlier). The edge
    points are assigned to the nearest side (those within a step of a corner left out), one
    turn and four side offsets are fitted by weighted least squares (linear in the small
    turn; weights ``1 / (bracket^2 / 12 + sigma^2)``), and points more than 1.2 half-brackets
    off are dropped (a ray lost to an outlier at the edge) before fitting again.

    The variance: the edge's place in each bracket is not independent from one grid line to
    the next but drifts with the grid's phase along the side (a sawtooth, constant when the
    grid is aligned with the side). Per side and grid direction, the phase drift per metre
    along the side follows from the two grid steps on the plane; the turn's variance is the
    fitted slope's mean square over a uniform starting phase, combined over the sides with
    the least squares' weights, plus the range noise's part."""
    from scipy.spatial import cKDTree

    p = np.asarray(points_S, dtype=float)
    if len(p) < 8 or np.any(p[:, 1] <= 0):
        return None
    n = R_SP[:, 2]
    uv = p[:, [0, 2]] / p[:, 1:2]
    G = ray_lattice(uv)
    if G is None:
        return None
    tree = cKDTree(uv)
    # a ray grid: most returns have a neighbour one step on along each grid direction (a
    # scanner's irregular pattern has not, and its "edges" would be noise)
    for g in G:
        d, _ = tree.query(uv + g, distance_upper_bound=0.35 * float(np.linalg.norm(g)))
        if np.mean(np.isfinite(d)) < 0.5:
            return None
    if cloud_S is None:
        cloud = p
    else:
        cloud = np.asarray(cloud_S, dtype=float)
        cloud = cloud[np.all(np.isfinite(cloud), axis=1) & (cloud[:, 1] > 0)]
    cloud_tree = cKDTree(cloud[:, [0, 2]] / cloud[:, 1:2])
    margin = max(threshold_m, 3.0 * sigma)
    b, a = sides_m
    Pxy = R_SP[:, :2]

    def on_plane(uvs: Array) -> tuple[Array, NDArray[np.bool_], Array]:
        """In-plane coordinates of the rays ``uvs`` where they meet the plane, whether they
        do (in front of the sensor), and the meeting point's y (the rays' y is 1)."""
        ray = np.column_stack([uvs[:, 0], np.ones(len(uvs)), uvs[:, 1]])
        denom = ray @ n
        ok = np.abs(denom) > 1e-9
        t = (centre_S @ n) / np.where(ok, denom, 1.0)
        return (ray * t[:, None] - centre_S) @ Pxy, ok & (t > 0), t

    rows: list[tuple] = []  # (mid (2,), step (2,), other step (2,), side, family)
    for family, (g, g_other) in enumerate(
        ((G[0], G[1]), (-G[0], G[1]), (G[1], G[0]), (-G[1], G[0]))
    ):
        gl = float(np.linalg.norm(g))
        dist, _ = tree.query(uv + g, distance_upper_bound=0.35 * gl)
        last = ~np.isfinite(dist)
        # rays lost to outliers inside the face: one of the next few is on the face again
        for j in range(2, 6):
            if not last.any():
                break
            dist2, _ = tree.query(uv[last] + j * g, distance_upper_bound=0.35 * gl)
            last[np.flatnonzero(last)[np.isfinite(dist2)]] = False
        if not last.any():
            continue
        uvn = uv[last] + g
        q_next, ok, t_next = on_plane(uvn)
        q_other, ok_other, _ = on_plane(uv[last] + g_other)
        ok &= ok_other
        # the next ray's own return: in front of the plane (another part may hide the face)
        # or on it (a point of the face the plane left out): not bracketed
        dn, jn = cloud_tree.query(uvn, distance_upper_bound=0.35 * gl)
        has = np.isfinite(dn)
        behind = np.ones(len(uvn), dtype=bool)
        if has.any():
            # farther along the ray than the plane (the rays' y is 1: ranges scale with y)
            ray_len = np.sqrt(1.0 + np.sum(uvn[has] ** 2, axis=1))
            behind[has] = (cloud[jn[has], 1] - t_next[has]) * ray_len > margin
        ok &= behind
        q_last = (p[last] - centre_S) @ Pxy
        # the range noise moves a return along its ray: sigma sin(i) in the plane, half of
        # it at the midpoint
        r_last = p[last] / np.linalg.norm(p[last], axis=1, keepdims=True)
        noise_mid = 0.5 * sigma * np.sqrt(np.clip(1.0 - (r_last @ n) ** 2, 0.0, 1.0))
        # the grid's steps on the plane from the rays alone (the returns' range noise, sigma
        # sin(i) in the plane, would swamp the small drift across a side that the variance
        # needs); the midpoint from the return itself, with its noise
        q_ray = on_plane(uv[last])[0]
        for i in np.flatnonzero(ok):
            step = q_next[i] - q_ray[i]
            mid = q_last[i] + 0.5 * (q_next[i] - q_last[i])
            x, y = mid
            side = (
                (0 if x > 0 else 1) if abs(x) / (b / 2) >= abs(y) / (a / 2) else (2 if y > 0 else 3)
            )
            across = abs(step[0]) if side < 2 else abs(step[1])
            h = float(np.linalg.norm(step))
            if (abs(abs(x) - b / 2) < h and abs(abs(y) - a / 2) < h) or across < 0.3 * h:
                continue
            rows.append((mid, step, q_other[i] - q_ray[i], side, family, noise_mid[i]))
    if len(rows) < 6:
        return None
    E = np.array([r[0] for r in rows])
    step = np.array([r[1] for r in rows])
    other = np.array([r[2] for r in rows])
    S = np.array([r[3] for r in rows])
    fam = np.array([r[4] for r in rows])
    sn = np.array([r[5] for r in rows])
    long_side = S < 2
    obs = np.where(long_side, E[:, 0], E[:, 1])  # across the side
    along = np.where(long_side, E[:, 1], E[:, 0])
    L = np.abs(np.where(long_side, step[:, 0], step[:, 1]))  # the bracket across the side
    w = 1.0 / (L**2 / 12.0 + sn**2)
    # long sides: x_i = d_s - delta y_i; short sides: y_i = d_s + delta x_i
    A = np.zeros((len(E), 5))
    A[:, 0] = np.where(long_side, -E[:, 1], E[:, 0])
    A[np.arange(len(E)), 1 + S] = 1.0
    use = np.ones(len(E), dtype=bool)
    x = np.zeros(5)
    for _ in range(4):
        if use.sum() < 6:
            return None
        Aw = A[use] * w[use, None]
        x = np.linalg.lstsq(A[use].T @ Aw, Aw.T @ obs[use], rcond=None)[0]
        keep = np.abs(obs - A @ x) <= 0.6 * L + 3.0 * sn
        if np.array_equal(keep, use):
            break
        use = keep
    if use.sum() < 6:
        return None
    if abs(x[0]) > 0.1:  # the moments are never this far off: the edges are not the face's
        return None
    var = _sawtooth_turn_variance(
        along[use], L[use], w[use], S[use], fam[use], step[use], other[use], long_side[use], sn[use]
    )
    if not np.isfinite(var):
        return None
    return float(x[0]), var, int(use.sum())


def _sawtooth_turn_variance(along, L, w, side, fam, step, other, long_side, sn) -> float:
    """The variance of :func:`edge_turn`'s turn (see there): per (side, grid direction)
    group, the phase of the edge in its brackets drifts by ``-(n . g') / (n . g)`` per grid
    line, which advances ``t . g' - (n . g' / n . g) t . g`` along the side (``g`` the
    bracket's step, ``g'`` the other grid step, ``n``, ``t`` the side's normal and
    direction); the group's slope error is averaged over 32 starting phases."""
    Wsum, num = 0.0, 0.0
    phases = (np.arange(32) + 0.5) / 32
    for s in range(4):
        for f in range(4):
            m = (side == s) & (fam == f)
            if m.sum() < 2:
                continue
            y, Lm, wm = along[m], L[m], w[m]
            yc = y - np.sum(wm * y) / np.sum(wm)
            W = float(np.sum(wm * yc**2))
            if W <= 0:
                continue
            nrm = np.array([1.0, 0.0]) if long_side[m][0] else np.array([0.0, 1.0])
            tng = np.array([-nrm[1], nrm[0]])
            g, go = np.median(step[m], axis=0), np.median(other[m], axis=0)
            ng, ngo = nrm @ g, nrm @ go
            if abs(ng) < 1e-12:
                continue
            drift = -ngo / ng  # phase per grid line
            advance = tng @ go + drift * (tng @ g)  # metres along the side per grid line
            kappa = drift / advance if abs(advance) > 1e-12 else 0.0
            # the drift varies over the face (perspective) and its estimate with it: averaged
            # over +-KAPPA_SPREAD of it, so that a drift of whole periods (whose slope errors
            # cancel) is not taken at its word
            kap = kappa * (1.0 + KAPPA_SPREAD * np.linspace(-1.0, 1.0, 5))
            phi = (phases[None, :, None] + kap[:, None, None] * y[None, None, :]) % 1.0
            e = (Lm[None, :] * (phi - 0.5)).reshape(-1, len(y))  # the edge points' errors
            slope = _gated_slopes(e, y, wm, Lm, sn[m])
            Wsum += W
            num += W**2 * float(np.mean(slope**2))
            num += float(np.sum((wm * yc) ** 2 * sn[m] ** 2))
    if Wsum <= 0:
        return float("nan")
    return num / Wsum**2


def _gated_slopes(e: Array, y: Array, w: Array, L: Array, sn: Array) -> Array:
    """Per row of ``e`` (errors across a side at positions ``y``), the slope that
    :func:`edge_turn`'s fit takes from them: weighted least squares of an offset and a slope,
    points more than ``0.6 L + 3 sn`` off (``sn`` each point's noise) dropped and fitted again (a wrap of the phase
    inside the side is a step of one bracket, which the gate cuts off)."""
    use = np.ones(e.shape, dtype=bool)
    slope = np.zeros(len(e))
    for _ in range(4):
        ww = np.where(use, w[None, :], 0.0)
        sw = ww.sum(axis=1)
        ok = sw > 0
        sw = np.where(ok, sw, 1.0)
        ym = (ww * y).sum(axis=1) / sw
        em = (ww * e).sum(axis=1) / sw
        yc = y[None, :] - ym[:, None]
        syy = (ww * yc**2).sum(axis=1)
        slope = np.where(
            syy > 0, (ww * yc * (e - em[:, None])).sum(axis=1) / np.where(syy > 0, syy, 1.0), 0.0
        )
        res = e - em[:, None] - slope[:, None] * yc
        keep = np.abs(res) <= 0.6 * L[None, :] + 3.0 * sn[None, :]
        if np.array_equal(keep, use):
            break
        use = keep
    return slope
