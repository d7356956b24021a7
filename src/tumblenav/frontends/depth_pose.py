"""Coarse pose of the target from one depth point cloud (Yu 2019 Sec. 2): extract planes,
recognise the model's rectangles by their sides, and turn each recognised rectangle into the
pose of the model frame M in the sensor frame S.

For a rectangle P of the model (``R_MP``, centre ``c_M``) seen as a plane with frame ``R_SP``
(:func:`tumblenav.frontends.planes.rectangle_frame`) and centroid ``r_m`` (eq. 3):
``R_SM = R_SP R_MP^T`` and ``p_MinS = r_m - R_SM c_M`` (the centroid of a fully seen
rectangle is its centre). The rectangle's four-fold symmetry (Fig. 2) is resolved against a
predicted attitude when one is given (eq. 21-25); without one the fix is flagged ambiguous.
A plane whose sides match no known rectangle (another surface, or a rectangle seen only in
part) gives no fix, and the reason is returned. With ``edge_turn`` the frame's turn about the
normal is refitted to the face's edges (:func:`tumblenav.frontends.planes.edge_turn`;
tumblenav, beyond Yu 2019), its variance kept in ``PoseFix.turn_var``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from tumblenav.frontends.planes import (
    RECTANGLE_SYMMETRIES,
    distribution_matrix,
    extract_planes,
    in_window,
    ray_footprint_weights,
    rectangle_frame,
    rectangle_sides,
    side_mismatch,
)
from tumblenav.frontends.planes import (
    edge_turn as edge_turn_fit,
)
from tumblenav.settings_rules import positive_or_rule
from tumblenav.target_model import TargetModel

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PoseFix:
    rectangle: str
    R_SM: Array  # model frame M into the sensor frame S
    p_MinS: Array  # model origin in S (m)
    n_points: int
    sides_m: tuple[float, float]
    ambiguous: bool  # True when no prediction resolved the four-fold symmetry
    candidates: tuple = ()  # every (R_SM, p_MinS) consistent with this rectangle
    R_MP: Array | None = None  # the recognised rectangle's frame in M
    turn_var: float | None = None  # variance (rad^2) of the turn from the edges, if used


def pose_fixes(
    points_S: Array,
    model: TargetModel,
    threshold_m: float,
    rng: np.random.Generator,
    sigma_m: float = 0.0,
    R_SM_predicted: Array | None = None,
    rel_tol: float = 0.08,
    min_points: int = 50,
    p_MinS_predicted: Array | None = None,
    edge_turn: bool = False,
) -> tuple[list[PoseFix], list[str]]:
    """All rectangle fixes in one cloud, and why the other planes were skipped. With a
    predicted origin ``p_MinS_predicted`` as well, candidates of equal attitude (faces of
    equal size and orientation, e.g. two solar panels) are told apart by their origin."""
    pts = np.asarray(points_S, dtype=float)
    pts = pts[np.all(np.isfinite(pts), axis=1)] if pts.size else pts.reshape(0, 3)
    if len(pts) < max(3, min_points):
        return [], [f"only {len(pts)} finite points"]
    fixes, skipped = [], []
    planes = extract_planes(pts, threshold_m, rng, min_points=min_points)
    for plane, members in zip(
        planes, _nearest_plane_members(pts, planes, threshold_m), strict=True
    ):
        if members.sum() < max(3, min_points):
            continue
        inl = pts[members]
        # the area centroid: each return weighted by its ray's footprint on the plane
        dist = distribution_matrix(inl, ray_footprint_weights(inl, plane.normal))
        b, a, spread = rectangle_sides(dist.eigenvalues, sigma_m)
        n_in = len(inl)
        if sigma_m > 0 and spread**2 > sigma_m**2 * (1.0 + 4.0 * np.sqrt(2.0 / n_in)):
            # the range noise alone spreads a face's points by at most sigma off its plane
            # (less where the rays are oblique): more says the plane's slab holds parts of
            # other surfaces, whose centre and axes would be wrong (tumblenav default)
            skipped.append(
                f"plane of {n_in} points spread {spread:.3f} m off its plane (noise "
                f"{sigma_m:.3f} m): more than one surface"
            )
            continue
        rects = _matches(model, b, a, rel_tol)
        if not rects:
            skipped.append(
                f"plane of {int(members.sum())} points, sides {b:.3f} x {a:.3f} m: "
                "no known rectangle (other surface, or seen in part)"
            )
            continue
        keep = _rectangle_points(inl, plane, rects[0].sides_m, threshold_m)
        if not np.all(keep) and keep.sum() >= 3:
            inl = inl[keep]
            dist = distribution_matrix(inl, ray_footprint_weights(inl, plane.normal))
        R_SP = rectangle_frame(dist)
        centre = dist.centroid
        turn_var = None
        if edge_turn:
            refined = edge_turn_fit(inl, R_SP, centre, rects[0].sides_m, sigma_m, pts, threshold_m)
            if refined is not None:
                c, s = np.cos(refined[0]), np.sin(refined[0])
                R_SP = R_SP @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
                turn_var = refined[1]
        # candidates: every rectangle with these sides x the four symmetric frames (Fig. 2);
        # the prediction picks the closest attitude (eq. 21-25), faces of equal size included
        cands = [(r, R_SP @ S @ r.R_MP.T) for r in rects for S in RECTANGLE_SYMMETRIES]
        # a face is seen only from outside: its outward normal points at the sensor
        cands = [(r, R) for r, R in cands if (R @ r.R_MP[:, 2]) @ dist.centroid < 0] or cands
        if R_SM_predicted is not None:
            score = np.array([np.sum(np.asarray(R_SM_predicted) * c) for _, c in cands])
            if p_MinS_predicted is not None:
                # among the attitudes as close as the best (within 1e-6), the nearest origin
                near = np.flatnonzero(score >= score.max() - 1e-6)
                miss = [
                    np.linalg.norm(centre - c @ r.centre_M - p_MinS_predicted)
                    for r, c in (cands[i] for i in near)
                ]
                k = int(near[int(np.argmin(miss))])
            else:
                k = int(np.argmax(score))
        else:
            k = 0
        rect, R_SM = cands[k]
        fixes.append(
            PoseFix(
                rect.name,
                R_SM,
                centre - R_SM @ rect.centre_M,
                len(inl),
                (b, a),
                R_SM_predicted is None,
                tuple((R, centre - R @ r.centre_M) for r, R in cands),
                rect.R_MP,
                turn_var,
            )
        )
    return fixes, skipped


def _nearest_plane_members(pts: Array, planes: list, threshold_m: float) -> list:
    """Each plane's points (tumblenav default): those within ``threshold_m`` of it, less the
    ones that lie nearer to another extracted plane *and* next to that plane's own points.

    RANSAC's consensus set of the first plane also holds the strip of every adjacent face
    within the threshold of their common edge (1-2% of its points, at one edge: several mm
    of centroid bias on Yu's satellite); on that face they lie on its own plane, within the
    noise, and continue its points, so they go back to it. A plane that merely crosses the
    first one (a panel's plane through the middle of a bus face) has no points there and
    takes none."""
    if not planes:
        return []
    from scipy.spatial import cKDTree

    D = np.abs(pts @ np.array([p.normal for p in planes]).T + np.array([p.d for p in planes]))
    slab = D < threshold_m
    nearest = np.argmin(D, axis=1)
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])) if len(pts) > 1 else 0.0
    reach = 2.0 * spacing + threshold_m
    members = [slab[:, j].copy() for j in range(len(planes))]
    for j in range(len(planes)):
        for k in range(len(planes)):
            if k == j:
                continue
            moved = slab[:, j] & (nearest == k)
            own_k = slab[:, k] & ~slab[:, j]
            if not moved.any() or not own_k.any():
                continue
            d, _ = cKDTree(pts[own_k]).query(pts[moved], distance_upper_bound=reach)
            idx = np.flatnonzero(moved)[np.isfinite(d)]
            members[j][idx] = False
    return members


def _rectangle_points(
    pts: Array, plane, sides_m: tuple[float, float], threshold_m: float
) -> NDArray[np.bool_]:
    """The plane's points that lie within one window of the known sides along each in-plane
    axis (:func:`tumblenav.frontends.planes.in_window`; tumblenav default)."""
    dist = distribution_matrix(pts, ray_footprint_weights(pts, plane.normal))
    R_SP = rectangle_frame(dist)
    keep = np.ones(len(pts), dtype=bool)
    for axis, side in zip((0, 1), sorted(sides_m), strict=True):
        keep &= in_window((pts - dist.centroid) @ R_SP[:, axis], side + 2.0 * threshold_m)
    return keep


def _matches(model: TargetModel, b: float, a: float, rel_tol: float) -> list:
    """The model's rectangles whose (short, long) sides match within ``rel_tol``."""
    return [r for r in model.rectangles if side_mismatch((b, a), r.sides_m) <= rel_tol]


def consistent_start(fixes: list[PoseFix]) -> tuple[Array, Array]:
    """Without a prediction: the candidate pose of the largest rectangle that agrees best with
    the candidates of every other rectangle seen in the same scan (Yu 2019 Sec. 2.3, two or
    more planes at once)."""
    fixes = sorted(fixes, key=lambda f: -f.n_points)
    best, score = fixes[0].candidates[0], np.inf
    for R, p in fixes[0].candidates:
        s = 0.0
        for other in fixes[1:]:
            s += float(
                min(np.linalg.norm(R - R2) + np.linalg.norm(p - p2) for R2, p2 in other.candidates)
            )
        if s < score:
            best, score = (R, p), s
    return best


def start_disagreement(fixes: list[PoseFix], R_SM: Array, p_MinS: Array) -> tuple[float, float]:
    """How far the other rectangles of a scan are from a start pose: the largest, over the
    fixes, of the smallest attitude angle (rad) and origin distance (m) to any of a fix's
    candidates (0, 0 for one fix). A plane taken for the wrong rectangle gives a pose the
    others do not share."""
    angle, dist = 0.0, 0.0
    for fx in fixes:
        a = min(
            float(np.arccos(np.clip((np.trace(R_SM.T @ R) - 1) / 2, -1.0, 1.0)))
            for R, _ in fx.candidates
        )
        d = min(float(np.linalg.norm(p - p_MinS)) for _, p in fx.candidates)
        angle, dist = max(angle, a), max(dist, d)
    return angle, dist


def model_symmetries(rectangles) -> list[Array]:
    """Proper rotations among the 24 signed axis permutations that map the model's set of
    rectangles onto itself: with rectangles alone the attitude is defined only up to these."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            G = np.zeros((3, 3))
            for i, j in enumerate(perm):
                G[i, j] = signs[i]
            if np.linalg.det(G) < 0:
                continue
            ok = all(
                any(
                    np.allclose(G @ r.centre_M, q.centre_M, atol=1e-9)
                    and np.allclose(G @ r.R_MP[:, 2], q.R_MP[:, 2], atol=1e-9)
                    and np.allclose(r.sides_m, q.sides_m)
                    for q in rectangles
                )
                for r in rectangles
            )
            if ok:
                out.append(G)
    return out


class PlanesTuning(BaseModel):
    """Settings of the planes front end (Yu 2019 Sec. 2-3: RANSAC planes, rectangles, pose
    fixes), under ``estimator.tuning.frontend`` of ekf-depth (the same keys at the top of
    ``estimator.tuning`` are still read, as before)."""

    model_config = ConfigDict(extra="forbid")
    plane_threshold_m: float | Literal["range_noise"] = Field(
        "range_noise",
        description="inlier distance of the RANSAC plane fits (m); 'range_noise': "
        "plane_threshold_sigmas x the sensor's range_noise_m, at least plane_threshold_min_m",
    )
    plane_threshold_sigmas: float = Field(
        3.0, gt=0, description="with plane_threshold_m 'range_noise': the threshold in sigmas"
    )
    edge_turn: bool = Field(
        True,
        description="refine each rectangle's turn about its normal from its edges, each "
        "bracketed between a grid line's last return and the next ray "
        "(planes.edge_turn; tumblenav, beyond Yu 2019's second moments, which turn with the "
        "ray grid's phase along the edges); false: the second moments' (eq. 5)",
    )
    plane_threshold_min_m: float = Field(
        1e-3, gt=0, description="with plane_threshold_m 'range_noise': its floor (m)"
    )

    @field_validator("plane_threshold_m", mode="before")
    @classmethod
    def _number_or_rule(cls, v: Any) -> Any:
        return positive_or_rule(v, "range_noise")

    def threshold(self, range_noise_m: float) -> float:
        """Inlier distance (m): as given, else ``plane_threshold_sigmas`` times the sensor's
        range noise, at least ``plane_threshold_min_m``."""
        if self.plane_threshold_m != "range_noise":
            return float(self.plane_threshold_m)
        return max(self.plane_threshold_sigmas * range_noise_m, self.plane_threshold_min_m)
