"""Compiled (numba) sigma-point loops of Kabir 2025's UKF: the torque-free propagation
(:func:`~.model.propagate_rotation`, eq. 8-10 and 13) and the stencil measurement model
(:func:`~.observations.stencil_measurement_model`, eq. 22-23 and 27), one sigma point at a
time.

Why by hand: the stencil model propagates every sigma point to ``t +- dt``, ``t +- 2 dt`` and
projects it five times per update; as numpy stacks that is some 300 small-array operations per
epoch, which profiling showed to be 84 % of a ukf-gp filter pass. The numpy functions stay the
reference (any stack shape); ``tests/test_ukf.py`` checks these against them (the same
arithmetic in another order: equal to rounding).  Exact IEEE arithmetic (no ``fastmath``).
The RK4 is written in scalars (:func:`tumblenav.dynamics.compiled.rk4_attitude`'s equations
without its temporary arrays), the rotation matrix is
:func:`tumblenav.rotations_compiled.quat_to_matrix`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tumblenav.rotations_compiled import quat_to_matrix


@njit(cache=True, error_model="numpy")
def _substeps(W, dt, max_turn, max_n):  # pragma: no cover - compiled
    """:func:`~.model.rk4_substeps` for the fastest rate of the stack ``W`` (S, 3) (NaN rates
    ignored; an infinite or no rate: one step), at most ``max_n``."""
    wmax = -1.0
    for s in range(W.shape[0]):
        nrm = math.sqrt(W[s, 0] * W[s, 0] + W[s, 1] * W[s, 1] + W[s, 2] * W[s, 2])
        if nrm > wmax or math.isinf(nrm):
            wmax = nrm
    if not (wmax >= 0.0 and math.isfinite(wmax)):
        wmax = 0.0
    n = max(1, int(math.ceil(abs(wmax * dt) / max_turn - 1e-12)))
    return min(n, max_n)


@njit(cache=True, error_model="numpy")
def _coefficients(k, c):  # pragma: no cover - compiled
    """Kabir 2025 eq. 8's Euler coefficients for ``I / I2 = diag(e^k1, 1, e^k2)`` into ``c``
    (:func:`~.model._euler_coefficients`)."""
    e1 = math.exp(k[0])
    e2 = math.exp(k[1])
    c[0] = (1.0 - e2) / e1
    c[1] = e2 - e1
    c[2] = (e1 - 1.0) / e2


@njit(cache=True, error_model="numpy")
def _derivative(w0, w1, w2, q0, q1, q2, q3, c0, c1, c2):  # pragma: no cover - compiled
    """Kabir 2025 eq. 8-10: ``dq_TI/dt = -1/2 [omega; 0] (x) q_TI`` and the Euler equations
    ``dw/dt = c * [wy wz, wx wz, wx wy]``, as :func:`tumblenav.dynamics.compiled.rk4_attitude`
    writes them (``[omega; 0] (x) q`` by :func:`tumblenav.rotations_compiled.quat_multiply`)."""
    d0 = q3 * w0 + (w1 * q2 - w2 * q1)
    d1 = q3 * w1 + (w2 * q0 - w0 * q2)
    d2 = q3 * w2 + (w0 * q1 - w1 * q0)
    d3 = -(w0 * q0 + w1 * q1 + w2 * q2)
    return (
        c0 * w1 * w2,
        c1 * w0 * w2,
        c2 * w0 * w1,
        -0.5 * d0,
        -0.5 * d1,
        -0.5 * d2,
        -0.5 * d3,
    )


@njit(cache=True, error_model="numpy")
def _propagate(W, Q, K, dt, n):  # pragma: no cover - compiled
    """``n`` RK4 steps of ``dt / n`` of every (omega, q, k) of the stacks, in place
    (:func:`tumblenav.dynamics.integrators.rk4_step`'s stages, in scalars)."""
    c = np.empty(3)
    h = dt / n
    for s in range(W.shape[0]):
        _coefficients(K[s], c)
        c0, c1, c2 = c[0], c[1], c[2]
        y = (W[s, 0], W[s, 1], W[s, 2], Q[s, 0], Q[s, 1], Q[s, 2], Q[s, 3])
        for _ in range(n):
            k1 = _derivative(*y, c0, c1, c2)
            y2 = (
                y[0] + 0.5 * h * k1[0],
                y[1] + 0.5 * h * k1[1],
                y[2] + 0.5 * h * k1[2],
                y[3] + 0.5 * h * k1[3],
                y[4] + 0.5 * h * k1[4],
                y[5] + 0.5 * h * k1[5],
                y[6] + 0.5 * h * k1[6],
            )
            k2 = _derivative(*y2, c0, c1, c2)
            y3 = (
                y[0] + 0.5 * h * k2[0],
                y[1] + 0.5 * h * k2[1],
                y[2] + 0.5 * h * k2[2],
                y[3] + 0.5 * h * k2[3],
                y[4] + 0.5 * h * k2[4],
                y[5] + 0.5 * h * k2[5],
                y[6] + 0.5 * h * k2[6],
            )
            k3 = _derivative(*y3, c0, c1, c2)
            y4 = (
                y[0] + h * k3[0],
                y[1] + h * k3[1],
                y[2] + h * k3[2],
                y[3] + h * k3[3],
                y[4] + h * k3[4],
                y[5] + h * k3[5],
                y[6] + h * k3[6],
            )
            k4 = _derivative(*y4, c0, c1, c2)
            s6 = h / 6
            y = (
                y[0] + s6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
                y[1] + s6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]),
                y[2] + s6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2]),
                y[3] + s6 * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3]),
                y[4] + s6 * (k1[4] + 2 * k2[4] + 2 * k3[4] + k4[4]),
                y[5] + s6 * (k1[5] + 2 * k2[5] + 2 * k3[5] + k4[5]),
                y[6] + s6 * (k1[6] + 2 * k2[6] + 2 * k3[6] + k4[6]),
            )
        W[s, 0], W[s, 1], W[s, 2] = y[0], y[1], y[2]
        Q[s, 0], Q[s, 1], Q[s, 2], Q[s, 3] = y[3], y[4], y[5], y[6]


@njit(cache=True, error_model="numpy")
def propagate_stack(W, Q, K, dt, max_turn, max_n):  # pragma: no cover - compiled
    """:func:`~.model.propagate_rotation` of the stacks ``W`` (S, 3), ``Q`` (S, 4), ``K``
    (S, 2) over ``dt``: new arrays (the quaternions not normalised)."""
    W1 = W.copy()
    Q1 = Q.copy()
    _propagate(W1, Q1, K, dt, _substeps(W, dt, max_turn, max_n))
    return W1, Q1


@njit(cache=True, error_model="numpy")
def _project(x, R_CI, r0, v0, cl, cr, R, Rq, out, flow_only, weight):  # pragma: no cover
    """Kabir 2025 eq. 22-23 (:func:`~.observations.measurement_model`) of one state ``x``
    (nominal) with the mass centre at ``r0`` moving at ``v0``: ``out`` (N, 9) gets the
    projections and flows, or with ``flow_only`` ``weight`` times the four projections added
    to its flow columns (eq. 27's stencil)."""
    quat_to_matrix(x[3:7], Rq)
    # R_CT = R_CI R_TI^T
    for i in range(3):
        for j in range(3):
            R[i, j] = R_CI[i, 0] * Rq[j, 0] + R_CI[i, 1] * Rq[j, 1] + R_CI[i, 2] * Rq[j, 2]
    ox = R[0, 0] * x[0] + R[0, 1] * x[1] + R[0, 2] * x[2]  # omega_C = R_CT omega_TI_T
    oy = R[1, 0] * x[0] + R[1, 1] * x[1] + R[1, 2] * x[2]
    oz = R[2, 0] * x[0] + R[2, 1] * x[1] + R[2, 2] * x[2]
    N = out.shape[0]
    for f in range(N):
        p0, p1, p2 = x[9 + 3 * f], x[10 + 3 * f], x[11 + 3 * f]
        # rho_i = rho0_C + R_CT p_i (eq. 4 in C); r = rho_i - rho0_C
        rx = R[0, 0] * p0 + R[0, 1] * p1 + R[0, 2] * p2
        ry = R[1, 0] * p0 + R[1, 1] * p1 + R[1, 2] * p2
        rz = R[2, 0] * p0 + R[2, 1] * p1 + R[2, 2] * p2
        px, py, pz = r0[0] + rx, r0[1] + ry, r0[2] + rz
        iy = 1.0 / py
        u_L, u_R, v = (px - cl) * iy, (px - cr) * iy, pz * iy
        if flow_only:
            out[f, 5] += weight * u_R
            out[f, 6] += weight * v
            out[f, 7] += weight * u_L
            out[f, 8] += weight * v
            continue
        # rho_dot = omega x r + rho0_dot (eq. 23)
        rx, ry, rz = px - r0[0], py - r0[1], pz - r0[2]
        xd = oy * rz - oz * ry + v0[0]
        yd = oz * rx - ox * rz + v0[1]
        zd = ox * ry - oy * rx + v0[2]
        out[f, 0] = u_R
        out[f, 1] = v
        out[f, 2] = u_L
        out[f, 3] = v
        out[f, 4] = u_L - u_R
        out[f, 5] = (xd - u_R * yd) * iy
        out[f, 6] = (zd - v * yd) * iy
        out[f, 7] = (xd - u_L * yd) * iy
        out[f, 8] = (zd - v * yd) * iy


@njit(cache=True, error_model="numpy")
def stencil_h(X, R_CI, rho0_C, rho0_dot_C, centres_x, dt, max_turn, max_n):  # pragma: no cover
    """:func:`~.observations.stencil_measurement_model` of the states ``X`` (S, nominal):
    (S, N, 9), the flow columns from eq. 27's stencil over the states propagated to
    ``t +- dt``, ``t +- 2 dt`` (the substeps chosen for the whole stack at each, as there)."""
    S, nom = X.shape
    N = (nom - 9) // 3
    out = np.empty((S, N, 9))
    R = np.empty((3, 3))
    Rq = np.empty((3, 3))
    cl, cr = centres_x[0], centres_x[1]
    for s in range(S):
        _project(X[s], R_CI, rho0_C, rho0_dot_C, cl, cr, R, Rq, out[s], False, 0.0)
        for f in range(N):
            for m in range(5, 9):
                out[s, f, m] = 0.0
    r0 = np.empty(3)
    for side in (1.0, -1.0):
        W = X[:, 0:3].copy()
        Q = X[:, 3:7].copy()
        K = X[:, 7:9].copy()
        Xs = X.copy()
        for step in (1.0, 2.0):
            _propagate(W, Q, K, side * dt, _substeps(W, side * dt, max_turn, max_n))
            Xs[:, 0:3] = W
            Xs[:, 3:7] = Q
            for i in range(3):
                r0[i] = rho0_C[i] + side * step * dt * rho0_dot_C[i]
            # Kabir 2025 eq. 27: (-w(t+2dt) + 8 w(t+dt) - 8 w(t-dt) + w(t-2dt)) / (12 dt),
            # summed in stencil_measurement_model's order (t+dt, t+2dt, t-dt, t-2dt)
            weight = side * (8.0 if step == 1.0 else -1.0)
            for s in range(S):
                _project(Xs[s], R_CI, r0, rho0_dot_C, cl, cr, R, Rq, out[s], True, weight)
    for s in range(S):
        for f in range(N):
            for m in range(5, 9):
                out[s, f, m] = out[s, f, m] / (12.0 * dt)
    return out
