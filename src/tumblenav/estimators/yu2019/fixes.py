"""The pose fixes' error model from the rectangles' point statistics (first order, eq. 3-5),
split into a white part and the slowly varying ray-grid part (tumblenav), and the
model-symmetry test of a start."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot

Array = NDArray[np.float64]


def _fix_parts(fx, sigma: float, threshold_m: float) -> tuple[Array, float, float, float]:
    """``(cov_att, grid, normal, c)``: the first-order attitude covariance in P (contamination
    included), the ray grid's in-plane centre variance ``h^2 / 12`` (m^2), the normal centre
    variance ``sigma^2 / n`` (m^2) and the contamination angle ``c`` (rad); see
    :func:`fix_covariance`."""
    b, a = fx.sides_m
    n = max(fx.n_points, 3)
    lb, la, ls = b**2 / 12 + sigma**2, a**2 / 12 + sigma**2, sigma**2
    var_normal_tilt_long = la * ls / n / max(la - ls, 1e-12) ** 2  # about the short axis
    var_normal_tilt_short = lb * ls / n / max(lb - ls, 1e-12) ** 2  # about the long axis
    var_in_plane = la * lb / n / max(la - lb, 1e-3 * la) ** 2  # about the normal
    c = 0.5 * (threshold_m / max(b, 1e-12)) ** 2
    cov_att = np.diag([var_normal_tilt_long, var_normal_tilt_short, var_in_plane]) + c**2 * np.eye(
        3
    )
    return cov_att, a * b / n / 12, ls / n, c


def fix_covariance(fx, sigma: float, threshold_m: float = 0.0) -> tuple[Array, Array]:
    """Covariances (in the rectangle frame P: short, long, normal) of one fix's attitude and
    centre, white and slowly varying parts together (:func:`fix_noise` splits them).

    Attitude: first order for ``n`` points on an a x b rectangle with normal noise sigma,
    the eigenvector perturbation of the distribution matrix (eq. 4-5): ``Var J_ij =
    E[d_i^2 d_j^2] / n``; a rotation about axis k moves the eigenvectors i, j by
    ``J_ij / (lambda_i - lambda_j)``.

    Centre: along the normal, the noise's ``sigma^2 / n`` (eq. 3); in the plane, a sensor's
    regular ray grid (spacing ``h``, ``h^2 = a b / n``, the area per return) leaves the edges
    at a random phase, the centroid error of ``h^2 / 12`` (tumblenav default; measured on the
    five yu scenarios, issue 18: 0.07-0.96x of it across the face, 0.09-0.51x along it, the
    grid's alignment with the edges decides).

    Contamination (``threshold_m``, the plane's inlier distance): the slab of a plane also
    holds strips of the surfaces next to it, a fraction ``~ threshold / b`` of its points
    ``~ threshold`` off the plane at one edge, which tilts and shifts the fit by about
    ``c = (threshold / b)^2 / 2`` rad and ``c b / 2`` m: 0.03 deg on Yu's satellite at 1 cm,
    but 3 deg at its printed 0.1 m (tumblenav default; measured fix errors there 5-17 deg)."""
    cov_att, grid, normal, c = _fix_parts(fx, sigma, threshold_m)
    b = fx.sides_m[0]
    in_plane = grid + (c * b / 2) ** 2
    return cov_att, np.diag([in_plane, in_plane, normal])


# the six error components of a fix, in its rectangle frame P: the attitude about the short
# side, the long side and the normal, then the origin along them (FixNoise.cov's order)
COMPONENTS = ("att_short", "att_long", "att_normal", "pos_short", "pos_long", "pos_normal")


@dataclass(frozen=True)
class FixNoise:
    """One fix's error model in its rectangle frame P (short side, long side, normal):
    tumblenav's, beyond Yu 2019 (which gives a fix no covariance).

    ``base``: (6, 6) covariance of ``e = [eps, e_c]``, the attitude residual ``q_meas [-] q``
    (rad) and the rectangle centre's error (m), both in P, white and slow parts together
    (:data:`COMPONENTS`); ``slow_fraction``: (6,) the share of each component's variance
    that varies slowly, which the filter carries as a state per rectangle
    (:mod:`tumblenav.estimators.yu2019.filter`), the rest white; ``lever``: the rectangle's
    centre in P axes (m): the origin ``p_M = centre - R_SM centre_M`` takes the attitude
    error to it (an attitude residual ``eps`` is the turn ``R_SM = Exp(-eps) R_SM_true``,
    which moves the origin by ``-[lever x] eps``); ``decorrelation_rad``: the view turn over
    which the slow part decorrelates (e-fold); ``systematic``: (6, 6) a slow part of its own
    (the errors of an oblique view), not scaled with the learnt scales."""

    base: Array
    slow_fraction: Array
    lever: Array
    decorrelation_rad: float
    systematic: Array | None = None

    def _to_origin(self) -> Array:
        """(6, 6) ``[eps, e_c] -> [eps, origin error]``."""
        M = np.eye(6)
        M[3:, :3] = -rot.skew(self.lever)
        return M

    def _scaled(self, scales: Array | None) -> Array:
        d = np.sqrt(np.ones(6) if scales is None else np.asarray(scales, dtype=float))
        return d[:, None] * self.base * d[None, :]

    def cov(self, scales: Array | None = None) -> Array:
        """(6, 6) covariance of the white part of ``[attitude residual, origin error]`` in
        P, each component's variance multiplied by ``scales`` (None: 1)."""
        w = np.sqrt(1.0 - self.slow_fraction)
        M = self._to_origin()
        return M @ (w[:, None] * self._scaled(scales) * w[None, :]) @ M.T

    def slow_factor(self, scales: Array | None = None) -> Array:
        """(6, 6) ``F`` such that a unit-variance state ``s`` makes the slow part of
        ``[attitude residual, origin error]`` in P ``F s`` (scaled as :meth:`cov`)."""
        r = np.sqrt(self.slow_fraction)
        S = r[:, None] * self._scaled(scales) * r[None, :]
        if self.systematic is not None:
            S = S + self.systematic
        return self._to_origin() @ np.linalg.cholesky(S + 1e-30 * np.eye(6))


def fix_noise(
    fx,
    sigma: float,
    threshold_m: float = 0.0,
    slow_fraction=(0.0,) * 6,
    decorrelation_spacings: float = 7.0,
    centre_M: Array | None = None,
    view_S: Array | None = None,
    attitude_scale: float = 1.0,
    position_scale: float = 1.0,
    oblique_trace_spacings: float = 0.0,
    oblique_normal: float = 0.0,
    edge_turn_floor: float = 0.0,
) -> FixNoise:
    """The error model of one fix (:class:`FixNoise`), tumblenav's.

    Starts from :func:`fix_covariance` (first order, eq. 3-5). In the plane, a regular ray
    grid seen at an incidence ``cos i`` (``view_S``: the direction from the sensor to the
    rectangle, in S; None: face on) spaces its returns ``h / sqrt(cos i)`` along the view's
    trace on the face and ``h sqrt(cos i)`` across it (``h^2 = a b / n``, the area per
    return): the edge-phase variance ``h^2 / (12 cos i)`` along the trace, ``h^2 / 12``
    across it (measured on the five yu scenarios of issue 18: the error along the trace, in
    units of the foreshortened spacing, is flat in ``cos i``; across it, it does not shrink).

    The errors of a regular grid do not change much from one scan to the next: the edges'
    phase in the grid moves only as the view of the face turns. Measured (4 runs of each yu
    scenario, fixes against the truth, their autocorrelation over scans): a share of each
    component's variance (``slow_fraction``; in-plane centre 0.4-0.57, about the normal
    0.1-0.28, about the long side 0.04-0.18, the rest below 0.06) decorrelates over a view
    turn of about 7 ray spacings across the face (``decorrelation_spacings`` x ``h / a``,
    0.17-0.26 rad there, fitted 0.11-0.37), for steps of 0.009-0.035 rad per scan; the rest
    is white.

    A fix whose turn about the normal came from the face's edges (``fx.turn_var``,
    :func:`tumblenav.frontends.planes.edge_turn`) takes that variance instead of the edge
    phase's, at least ``edge_turn_floor`` of it."""
    b, a = fx.sides_m
    n = max(fx.n_points, 3)
    grid = a * b / n / 12  # h^2 / 12
    R_MP = fx.R_MP if fx.R_MP is not None else np.eye(3)
    ip = grid * np.eye(2)
    cos_i = 1.0
    u = np.zeros(2)
    if view_S is not None:
        v_P = (fx.R_SM @ R_MP).T @ (np.asarray(view_S, dtype=float) / np.linalg.norm(view_S))
        trace = np.linalg.norm(v_P[:2])
        cos_i = max(abs(float(v_P[2])), 0.05)  # a face seen within 3 deg of edge on: 20x
        if trace > 1e-9:
            u = v_P[:2] / trace
            ip = grid * (np.outer(u, u) / cos_i + np.eye(2) - np.outer(u, u))
    # along the normal: the range noise seen at incidence i, sigma^2 cos i per return
    # (measured: the normal centre error and both tilts, over sigma^2 / n and eq. 4-5's
    # first-order tilts, are flat in cos i with this, within 0.6-1.1x face on)
    ls = sigma**2 * cos_i
    c = 0.5 * (threshold_m / max(b, 1e-12)) ** 2  # contamination, as fix_covariance
    base = np.zeros((6, 6))
    base[0, 0] = 12.0 * ls / (n * a**2) + c**2  # tilt about the short side: long lever
    base[1, 1] = 12.0 * ls / (n * b**2) + c**2  # about the long side
    # about the normal: the edges' phase across the short side over half the long side
    base[2, 2] = 4.0 * ip[0, 0] / a**2 + c**2
    if getattr(fx, "turn_var", None) is not None:
        # the turn from the edges (planes.edge_turn), with its own sawtooth variance, at
        # least edge_turn_floor of the second moments' above
        base[2, 2] = max(fx.turn_var, edge_turn_floor * (base[2, 2] - c**2)) + c**2
    base[3:5, 3:5] = ip + (c * b / 2) ** 2 * np.eye(2)
    base[5, 5] = ls / n
    base[:3, :3] *= attitude_scale
    base[3:, 3:] *= position_scale
    c_P = R_MP.T @ np.asarray(centre_M if centre_M is not None else np.zeros(3), dtype=float)
    h = np.sqrt(grid * 12.0)
    # seen obliquely, the centre is off by a part of the ray spacing along the view's trace
    # (towards the sensor when grazing, away near face on: -0.3 to +0.15 h, the same in every
    # run) and the plane, with the strip of the face-on neighbour in its slab, sits
    # ~0.5 threshold^2 / (2 b) inside the face (measured on the yu scenarios of issue 18):
    # systematic errors of the view, slowly varying, their 1-sigma grows with sin i
    sin_i = np.sqrt(max(1.0 - cos_i**2, 0.0))
    systematic = np.zeros((6, 6))
    systematic[3:5, 3:5] = (oblique_trace_spacings * h * sin_i) ** 2 * np.outer(u, u)
    systematic[5, 5] = (oblique_normal * threshold_m**2 / (2 * b) * sin_i) ** 2
    systematic[:3, :3] *= attitude_scale
    systematic[3:, 3:] *= position_scale
    return FixNoise(
        base=base,
        slow_fraction=np.asarray(slow_fraction, dtype=float) * np.ones(6),
        lever=c_P,
        systematic=systematic,
        decorrelation_rad=float(decorrelation_spacings * h / max(a, 1e-12)),
    )


def _only_model_symmetric(fix, syms: list[Array]) -> bool:
    """True when all the candidate poses of one rectangle differ by symmetries of the model
    (then starting from any of them is as good as any other: the attitude is defined only up
    to those symmetries anyway)."""
    R0 = fix.candidates[0][0] if fix.candidates else fix.R_SM
    return all(any(np.allclose(R0.T @ R, G, atol=1e-6) for G in syms) for R, _ in fix.candidates)
