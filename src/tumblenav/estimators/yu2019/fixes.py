"""The pose fixes' covariances from the rectangles' point statistics (first order, eq. 3-5)\nand the model-symmetry test of a start."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def fix_covariance(
    fx, sigma: float, view_step_rad: float | None = None, threshold_m: float = 0.0
) -> tuple[Array, Array]:
    """Covariances (in the rectangle frame P: short, long, normal) of one fix.

    Attitude: first order for ``n`` points on an a x b rectangle with normal noise sigma,
    the eigenvector perturbation of the distribution matrix (eq. 4-5): ``Var J_ij =
    E[d_i^2 d_j^2] / n``; a rotation about axis k moves the eigenvectors i, j by
    ``J_ij / (lambda_i - lambda_j)``.

    Centre: along the normal, the noise's ``sigma^2 / n`` (eq. 3); in the plane, a sensor's
    regular ray grid (spacing ``h``, ``h^2 = a b / n``, the area per return) leaves the edges
    at a random phase, the centroid error of ``h^2 / 12`` (tumblenav default; measured on the
    yu2019 scans: 0.8x across the spin, 0.05x along it, docs/results/yu2019.md). That phase
    changes only as the view turns by about ``psi_c = h / a``: with ``view_step_rad``, the
    turn between two scans, consecutive errors correlate as ``r = exp(-step / psi_c)`` and the
    in-plane variance is inflated by ``(1 + r) / (1 - r)`` (an AR(1) error counted as white),
    at most 50x. All of it scales with the model's sizes, the sensor's resolution on the
    target and the tumble (None: no inflation).

    Contamination (``threshold_m``, the plane's inlier distance): the slab of a plane also
    holds strips of the surfaces next to it, a fraction ``~ threshold / b`` of its points
    ``~ threshold`` off the plane at one edge, which tilts and shifts the fit by about
    ``c = (threshold / b)^2 / 2`` rad and ``c b / 2`` m: 0.03 deg on Yu's satellite at 1 cm,
    but 3 deg at its printed 0.1 m (tumblenav default; measured fix errors there 5-17 deg)."""
    b, a = fx.sides_m
    n = max(fx.n_points, 3)
    lb, la, ls = b**2 / 12 + sigma**2, a**2 / 12 + sigma**2, sigma**2
    var_normal_tilt_long = la * ls / n / max(la - ls, 1e-12) ** 2  # about the short axis
    var_normal_tilt_short = lb * ls / n / max(lb - ls, 1e-12) ** 2  # about the long axis
    var_in_plane = la * lb / n / max(la - lb, 1e-3 * la) ** 2  # about the normal
    cov_att = np.diag([var_normal_tilt_long, var_normal_tilt_short, var_in_plane])
    h2 = a * b / n
    inflate = 1.0
    if view_step_rad is not None:
        r = float(np.exp(-abs(view_step_rad) / max(np.sqrt(h2) / max(a, 1e-12), 1e-12)))
        inflate = min((1 + r) / max(1 - r, 1e-12), 50.0)
    c = 0.5 * (threshold_m / max(b, 1e-12)) ** 2
    cov_att = cov_att + c**2 * np.eye(3)
    in_plane = inflate * h2 / 12 + (c * b / 2) ** 2
    cov_pos = np.diag([in_plane, in_plane, ls / n])
    return cov_att, cov_pos


def _only_model_symmetric(fix, syms: list[Array]) -> bool:
    """True when all the candidate poses of one rectangle differ by symmetries of the model
    (then starting from any of them is as good as any other: the attitude is defined only up
    to those symmetries anyway)."""
    R0 = fix.candidates[0][0] if fix.candidates else fix.R_SM
    return all(any(np.allclose(R0.T @ R, G, atol=1e-6) for G in syms) for R, _ in fix.candidates)
