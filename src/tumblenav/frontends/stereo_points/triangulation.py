"""Triangulation of the stereo tracks of B runs with first-order covariances (Hu 2024 eq. 1,\nany rig)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends.triangulation import (
    triangulate_parallel,
    triangulate_two_ray,
    triangulation_jacobian,
)

Array = NDArray[np.float64]


def triangulate(meas_list) -> tuple[Array, Array, NDArray[np.bool_], dict[str, Array]]:
    """Points (B,n,N,3) in C, covariances, usable mask, skip counts, for B runs of one rig."""
    uv = np.stack([m.uv for m in meas_list])  # (B,n,2,N,2)
    obs = np.stack([m.observed for m in meas_list])  # (B,n,2,N)
    rig = meas_list[0].rig
    sigma = meas_list[0].noise_px

    def tri(uvl: Array, uvr: Array) -> Array:
        if rig.kind == "parallel":
            L = rig.left
            return triangulate_parallel(uvl, uvr, L.focal_px, rig.baseline_m, L.principal_point_px)
        L, R = rig.left, rig.right
        return triangulate_two_ray(
            uvl,
            uvr,
            (L.focal_px, R.focal_px),
            (L.principal_point_px, R.principal_point_px),
            L.R_CkC,
            L.p_CkinC,
            R.R_CkC,
            R.p_CkinC,
        )

    uvl, uvr = uv[:, :, 0], uv[:, :, 1]
    p = tri(uvl, uvr)
    # First-order covariance by central differences over the four pixel coordinates: works
    # for any rig (the closed form of triangulation_covariance covers the parallel one only).
    if rig.kind == "parallel":  # closed form (Hu 2024 eq. 1 differentiated)
        J = triangulation_jacobian(np.nan_to_num(p), rig.left.focal_px, rig.baseline_m)
        J = np.where(np.isfinite(p)[..., None], J, np.nan)
        cov = sigma**2 * (J @ np.swapaxes(J, -1, -2))
        return _finish_triangulation(p, cov, obs)
    h = 1e-3
    J = np.empty(p.shape + (4,))
    for k in range(4):
        d = np.zeros(4)
        d[k] = h
        dl, dr = d[:2], d[2:]
        J[..., k] = (tri(uvl + dl, uvr + dr) - tri(uvl - dl, uvr - dr)) / (2 * h)
    cov = sigma**2 * (J @ np.swapaxes(J, -1, -2))
    return _finish_triangulation(p, cov, obs)


def _finish_triangulation(p: Array, cov: Array, obs: NDArray[np.bool_]):
    both = obs[:, :, 0] & obs[:, :, 1]
    usable = both & np.all(np.isfinite(p), axis=-1) & np.all(np.isfinite(cov), axis=(-1, -2))
    p = np.where(usable[..., None], p, np.nan)
    skipped = {
        "one_camera_only": np.sum(obs[:, :, 0] ^ obs[:, :, 1], axis=(1, 2)),
        "bad_triangulation": np.sum(both & ~usable, axis=(1, 2)),
    }
    return p, cov, usable, skipped
