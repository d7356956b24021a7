"""The pose fixes' covariances from the rectangles' point statistics (first order, eq. 3-5)\nand the model-symmetry test of a start."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def fix_covariance(fx, sigma: float) -> tuple[Array, Array]:
    """First-order covariances (in the rectangle frame P: short, long, normal) of one fix from
    n points uniform on an a x b rectangle with normal noise sigma: eigenvector perturbation of
    the distribution matrix (eq. 4-5) and the sampling error of the centroid (eq. 3).
    ``Var J_ij = E[d_i^2 d_j^2] / n``; a rotation about axis k moves the eigenvectors i, j by
    ``J_ij / (lambda_i - lambda_j)``."""
    b, a = fx.sides_m
    n = max(fx.n_points, 3)
    lb, la, ls = b**2 / 12 + sigma**2, a**2 / 12 + sigma**2, sigma**2
    var_normal_tilt_long = la * ls / n / max(la - ls, 1e-12) ** 2  # about the short axis
    var_normal_tilt_short = lb * ls / n / max(lb - ls, 1e-12) ** 2  # about the long axis
    var_in_plane = la * lb / n / max(la - lb, 1e-3 * la) ** 2  # about the normal
    cov_att = np.diag([var_normal_tilt_long, var_normal_tilt_short, var_in_plane])
    cov_pos = np.diag([lb / n, la / n, ls / n])
    return cov_att, cov_pos


def _only_model_symmetric(fix, syms: list[Array]) -> bool:
    """True when all the candidate poses of one rectangle differ by symmetries of the model
    (then starting from any of them is as good as any other: the attitude is defined only up
    to those symmetries anyway)."""
    R0 = fix.candidates[0][0] if fix.candidates else fix.R_SM
    return all(any(np.allclose(R0.T @ R, G, atol=1e-6) for G in syms) for R, _ in fix.candidates)
