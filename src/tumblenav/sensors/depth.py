"""Flash-LIDAR / time-of-flight sensor (Yu 2019): ray-cast point clouds of the target mesh.

The sensor sits at the origin of its frame S with its boresight along +y (the same axis
convention as the stereo rig frame C: x right, y boresight, z = x cross y). It casts a square
grid of about ``points`` rays across its field of view, intersects them with the target mesh
at the true pose (Embree through trimesh), adds Gaussian range noise along each ray, replaces
a fraction of the returns by outliers (uniform in range along the ray) and drops returns beyond
the maximum range. Rays that miss return NaN: the cloud has a fixed size with an explicit mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tumblenav.target_model import TargetModel

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DepthSensor:
    fov_rad: float
    points: int  # number of rays (rounded to a square grid)
    range_noise_m: float = 0.0
    outlier_fraction: float = 0.0
    max_range_m: float = 100.0

    def directions(self) -> Array:
        """Unit ray directions in S, (n_rays, 3): a square grid over the field of view."""
        k = max(2, int(round(np.sqrt(self.points))))
        h = np.tan(self.fov_rad / 2)
        u = np.linspace(-h, h, k)
        X, Z = np.meshgrid(u, u)
        d = np.column_stack([X.ravel(), np.ones(k * k), Z.ravel()])
        return d / np.linalg.norm(d, axis=1, keepdims=True)


def _hit_fraction(model: TargetModel, R_SM: Array, p_MinS: Array, d_S: Array) -> float:
    R_MS = np.asarray(R_SM, dtype=float).T
    origin_M = -R_MS @ np.asarray(p_MinS, dtype=float)
    hits = model.mesh.ray.intersects_any(np.tile(origin_M, (len(d_S), 1)), d_S @ R_MS.T)
    return float(np.mean(hits))


def _window_directions(centre_S: Array, half_angle: float, n: int) -> Array:
    """A square grid of about ``n`` unit directions within ``half_angle`` of ``centre_S``."""
    c = centre_S / np.linalg.norm(centre_S)
    helper = np.array([0.0, 0.0, 1.0]) if abs(c[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(c, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e1, c)
    k = max(2, int(round(np.sqrt(n))))
    u = np.linspace(-np.tan(half_angle), np.tan(half_angle), k)
    X, Z = np.meshgrid(u, u)
    d = c + X.ravel()[:, None] * e1 + Z.ravel()[:, None] * e2
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def scan(
    sensor: DepthSensor,
    model: TargetModel,
    R_SM: Array,
    p_MinS: Array,
    rng: np.random.Generator,
    on_target: bool = False,
) -> tuple[Array, NDArray[np.bool_]]:
    """One point cloud in S: (n_rays, 3) with NaN where nothing is measured, and the mask.

    ``R_SM`` maps model-frame coordinates into S; ``p_MinS`` is the model origin in S (m).
    With ``on_target`` the rays are spread over the target's angular extent (its bounding
    sphere), with a density chosen so that about ``sensor.points`` of them hit it: Yu 2019
    Sec. 4 draws its 1800 points on the target surface. Rays outside the field of view are
    not measured either way.
    """
    d_S = sensor.directions()
    if on_target:
        centre_M, radius = (
            model.mesh.bounding_sphere.primitive.center,
            model.mesh.bounding_sphere.primitive.radius,
        )
        centre_S = np.asarray(R_SM) @ centre_M + np.asarray(p_MinS)
        dist = np.linalg.norm(centre_S)
        half = np.arcsin(min(radius / dist, 0.999)) if dist > 0 else np.pi / 2 - 1e-3
        frac = _hit_fraction(model, R_SM, p_MinS, _window_directions(centre_S, half, 400))
        n = int(min(sensor.points / max(frac, 0.02), 50 * sensor.points))
        d_S = _window_directions(centre_S, half, n)
        # inside the square field of view: both angles from the boresight below fov/2
        inside = (d_S[:, 1] > 0) & (np.abs(np.arctan2(d_S[:, 0], d_S[:, 1])) <= sensor.fov_rad / 2)
        inside &= np.abs(np.arctan2(d_S[:, 2], d_S[:, 1])) <= sensor.fov_rad / 2
        d_S = np.where(inside[:, None], d_S, np.nan)
    R_MS = np.asarray(R_SM, dtype=float).T
    origin_M = -R_MS @ np.asarray(p_MinS, dtype=float)  # the sensor in M
    valid = np.all(np.isfinite(d_S), axis=1)
    d_M = d_S[valid] @ R_MS.T
    locs, ray_idx, _ = model.mesh.ray.intersects_location(
        np.tile(origin_M, (len(d_M), 1)), d_M, multiple_hits=False
    )
    rng_m = np.full(len(d_S), np.nan)
    rng_m[np.flatnonzero(valid)[ray_idx]] = np.linalg.norm(locs - origin_M, axis=1)
    d_S = np.nan_to_num(d_S)
    hit = np.isfinite(rng_m)
    if sensor.range_noise_m > 0:
        rng_m[hit] += rng.normal(0.0, sensor.range_noise_m, hit.sum())
    if sensor.outlier_fraction > 0:
        out = hit & (rng.random(len(d_S)) < sensor.outlier_fraction)
        rng_m[out] = rng.uniform(0.0, sensor.max_range_m, out.sum())
    ok = hit & (rng_m > 0) & (rng_m <= sensor.max_range_m)
    pts = np.where(ok[:, None], d_S * rng_m[:, None], np.nan)
    return pts, ok
