"""Epipolar geometry of a calibrated :class:`~tumblenav.sensors.StereoRig` in tumblenav pixels.

Pixel convention (tumblenav): ``u = cu + f x / y``, ``v = cv + f z / y`` in each camera frame
(``y`` the optical axis); the image spans ``[0, W] x [0, H]`` and pixel ``(i, j)`` has its centre
at ``(i + 0.5, j + 0.5)``.  OpenCV puts pixel centres at integers: ``u_opencv = u - 0.5``.
Everything here is in tumblenav pixels; only the callers of OpenCV convert.

The left ray of a left pixel is parametrised by its depth ``lam`` along the left optical axis:
``P(lam) = c_l + lam d`` with ``d = R_ClC^T [(u - cu)/f, 1, (v - cv)/f]``.  Its image in the
right camera is the epipolar line of the left pixel (Chang 2021 Sec. 2.3: the epipolar
constraint limits the stereo search; with the rig calibrated, ``F`` is known and no RANSAC is
needed).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends.triangulation import triangulate_two_ray
from tumblenav.sensors.stereo import StereoRig

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["EpipolarGeometry", "clip_segments"]

_FRONT_M = 1e-6  # a point must be this far in front of a camera (m) to be projected


def _skew(t: Array) -> Array:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def clip_segments(q0: Array, q1: Array, lo: Array, hi: Array) -> tuple[Array, Array, BoolArray]:
    """Clip segments ``q0 -> q1`` (m, 2) to the boxes ``[lo, hi]`` (2,) (Liang-Barsky).

    Returns the clipped end points (m, 2) each and whether anything is left (m,).
    """
    d = q1 - q0
    t0 = np.zeros(len(q0))
    t1 = np.ones(len(q0))
    ok = np.all(np.isfinite(q0) & np.isfinite(q1), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in range(2):
            for p, q in ((-d[:, ax], q0[:, ax] - lo[ax]), (d[:, ax], hi[ax] - q0[:, ax])):
                par = p == 0.0
                ok &= ~(par & (q < 0.0))
                r = np.where(par, 0.0, q / np.where(par, 1.0, p))
                enter = ~par & (p < 0.0)
                leave = ~par & (p > 0.0)
                t0 = np.where(enter, np.maximum(t0, r), t0)
                t1 = np.where(leave, np.minimum(t1, r), t1)
    ok &= t0 <= t1
    return q0 + t0[:, None] * d, q0 + t1[:, None] * d, ok


@dataclass(frozen=True, eq=False)
class EpipolarGeometry:
    """Projections, epipolar lines and triangulation of a calibrated rig (tumblenav pixels).

    ``F`` (3, 3) is the fundamental matrix with ``[u_r, v_r, 1] F [u_l, v_l, 1]^T = 0``
    (tumblenav pixels): ``F = A_r^-T [t]x R_rl A_l^-1`` with ``R_rl = R_CrC R_ClC^T``,
    ``t = R_CrC (c_l - c_r)`` and ``A`` mapping camera coordinates ``(x, y, z)`` to homogeneous
    pixels ``(f x + cu y, cv y + f z, y)``.
    """

    rig: StereoRig
    # set in __post_init__ from the rig
    f: Array = field(init=False, repr=False)  # focal lengths (2,) px
    pp: Array = field(init=False, repr=False)  # principal points (2, 2) px
    R: Array = field(init=False, repr=False)  # R_CkC (2, 3, 3)
    c: Array = field(init=False, repr=False)  # centres in C (2, 3) m
    F: Array = field(init=False, repr=False)  # fundamental matrix, tumblenav px
    b_hat: Array = field(init=False, repr=False)  # unit baseline, left -> right, in C
    a_right: Array = field(init=False, repr=False)  # left centre in right-camera coordinates

    def __post_init__(self) -> None:
        cams = self.rig.cameras
        f = np.array([c.focal_px for c in cams])
        pp = np.array([c.principal_point_px for c in cams], dtype=float)
        R = self.rig.R_CkC
        c = self.rig.centres_inC
        A = [
            np.array([[fk, p[0], 0.0], [0.0, p[1], fk], [0.0, 1.0, 0.0]])
            for fk, p in zip(f, pp, strict=True)
        ]
        R_rl = R[1] @ R[0].T
        t = R[1] @ (c[0] - c[1])
        F = np.linalg.inv(A[1]).T @ _skew(t) @ R_rl @ np.linalg.inv(A[0])
        F /= np.linalg.norm(F)
        b_hat = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
        for name, value in (
            ("f", f),
            ("pp", pp),
            ("R", R),
            ("c", c),
            ("F", F),
            ("b_hat", b_hat),
            ("a_right", t),
        ):
            object.__setattr__(self, name, value)

    def size(self, k: int) -> tuple[int, int]:
        """``(W, H)`` of camera ``k`` (px)."""
        return self.rig.cameras[k].resolution_px

    def left_rays(self, uv_l: Array) -> Array:
        """Directions (m, 3) in C of the left rays, scaled to unit depth along the left axis."""
        d_cam = np.stack(
            [
                (uv_l[:, 0] - self.pp[0, 0]) / self.f[0],
                np.ones(len(uv_l)),
                (uv_l[:, 1] - self.pp[0, 1]) / self.f[0],
            ],
            axis=1,
        )
        return d_cam @ self.R[0]  # R_ClC^T d_cam, row-wise

    def project(self, k: int, p_inC: Array) -> tuple[Array, Array]:
        """Pixels (m, 2) of points ``p_inC`` (m, 3) in camera ``k`` and their depths (m,)."""
        p = (p_inC - self.c[k]) @ self.R[k].T
        y = p[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack(
                [self.pp[k, 0] + self.f[k] * p[:, 0] / y, self.pp[k, 1] + self.f[k] * p[:, 2] / y],
                axis=1,
            )
        uv[~(y > _FRONT_M)] = np.nan
        return uv, y

    def right_lines(self, uv_l: Array) -> Array:
        """Epipolar lines (m, 3) in the right image, scaled so that ``a^2 + b^2 = 1``."""
        x = np.column_stack([uv_l, np.ones(len(uv_l))])
        lines = x @ self.F.T
        return lines / np.hypot(lines[:, 0], lines[:, 1])[:, None]

    def epipolar_distance(self, uv_l: Array, uv_r: Array) -> Array:
        """Distance (px) of the right pixels from the epipolar lines of the left ones."""
        lines = self.right_lines(uv_l)
        return np.abs(lines[:, 0] * uv_r[:, 0] + lines[:, 1] * uv_r[:, 1] + lines[:, 2])

    def directions(self, uv_l: Array, lam: Array) -> tuple[Array, Array]:
        """Unit directions (m, 2) of the left and right epipolar lines, consistently oriented.

        Both are the image motion of the point at depth ``lam`` on the left ray when it moves
        along the baseline (towards the right camera): corresponding patches sampled along
        ``(d, rot90(d))`` in each image are then a locally rectified pair (for a parallel rig
        ``d = (1, 0)`` in both).
        """
        rays = self.left_rays(uv_l)
        P = self.c[0] + lam[:, None] * rays
        eps = 1e-3 * lam[:, None] * np.linalg.norm(rays, axis=1)[:, None]
        out = []
        for k in (0, 1):
            a, _ = self.project(k, P)
            b, _ = self.project(k, P + eps * self.b_hat)
            d = b - a
            out.append(d / np.hypot(d[:, 0], d[:, 1])[:, None])
        return out[0], out[1]

    def right_of_depth(self, uv_l: Array, lam: Array) -> Array:
        """Right pixels (m, 2) of the points at depth ``lam`` on the left rays (NaN if behind)."""
        P = self.c[0] + lam[:, None] * self.left_rays(uv_l)
        return self.project(1, P)[0]

    def right_segments(
        self, uv_l: Array, min_depth_m: float, max_depth_m: float | None
    ) -> tuple[Array, Array]:
        """End points (m, 2) each of the right images of the left rays over a depth range.

        With ``max_depth_m`` None the far end is the vanishing point of the ray (or, for a ray
        that leaves the right camera's front half-space, a point just before it does).  The
        nearer end is NaN where no depth in the range is in front of the right camera.
        """
        g = self.left_rays(uv_l) @ self.R[1].T  # right-camera coordinates of the rays
        a = self.a_right  # right-camera coordinates of the left centre
        lo = np.full(len(uv_l), float(min_depth_m))
        hi = np.full(len(uv_l), np.inf if max_depth_m is None else float(max_depth_m))
        gy = g[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam_edge = (_FRONT_M - a[1]) / gy  # depth at which the ray crosses y_r = 0+
        lo = np.where(gy > 0.0, np.maximum(lo, lam_edge * (1.0 + 1e-9)), lo)
        hi = np.where(gy < 0.0, np.minimum(hi, lam_edge * (1.0 - 1e-6)), hi)
        near = self.right_of_depth(uv_l, lo)
        far = np.empty_like(near)
        fin = np.isfinite(hi)
        far[fin] = self.right_of_depth(uv_l[fin], hi[fin])
        with np.errstate(divide="ignore", invalid="ignore"):
            vp = self.pp[1] + self.f[1] * g[:, [0, 2]] / gy[:, None]
        far[~fin] = vp[~fin]
        bad = ~(lo < hi)
        near[bad] = np.nan
        return near, far

    def triangulate(self, uv_l: Array, uv_r: Array) -> Array:
        """Points (m, 3) in C from matched pixels, by the general two-ray (midpoint) method."""
        return triangulate_two_ray(
            uv_l,
            uv_r,
            self.f,
            self.pp,
            self.R[0],
            self.c[0],
            self.R[1],
            self.c[1],
        )

    def left_depth(self, p_inC: Array) -> Array:
        """Depth (m) of points along the left optical axis (the ``lam`` of :meth:`left_rays`)."""
        return (p_inC - self.c[0]) @ self.R[0][1]
