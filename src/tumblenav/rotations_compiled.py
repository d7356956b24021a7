"""Compiled (numba) twins of :mod:`tumblenav.rotations` for the compiled loops.

Same convention as the reference ([x, y, z, w], Hamilton; see :mod:`tumblenav.rotations`),
one quaternion or matrix at a time, results written into ``out`` arguments so that the loops
allocate nothing.  Each function is tested against its numpy reference in
``tests/test_rotations_compiled.py``.

The single-quaternion functions are inlined into their callers (``inline="always"``), so each
runs under the caller's floating-point licence: the EKF kernel's ``fastmath`` there, exact
IEEE arithmetic in the front end's loops and in the tests.  :func:`matrix_to_quat` works on
stacks and is an ordinary compiled call.

numba's on-disk cache of a kernel follows the kernel's own file only: after editing this
module, clear the callers' caches (``__pycache__/*.nbi``, ``*.nbc`` beside
``estimators/hu2024/kernels.py`` and ``frontends/_points_kernel.py``) or they keep the old code.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "boxminus",
    "boxplus",
    "exp_quat",
    "log_quat",
    "matrix_to_quat",
    "quat_multiply",
    "quat_to_matrix",
]


@njit(cache=True, inline="always", error_model="numpy")
def quat_multiply(a, b, out):
    """``rotations.quat_multiply``: ``out = a (x) b`` (``out`` may be ``a`` or ``b``)."""
    ax, ay, az, aw = a[0], a[1], a[2], a[3]
    bx, by, bz, bw = b[0], b[1], b[2], b[3]
    out[0] = aw * bx + bw * ax + (ay * bz - az * by)
    out[1] = aw * by + bw * ay + (az * bx - ax * bz)
    out[2] = aw * bz + bw * az + (ax * by - ay * bx)
    out[3] = aw * bw - (ax * bx + ay * by + az * bz)


@njit(cache=True, inline="always", error_model="numpy")
def quat_to_matrix(q, R):
    """``rotations.quat_to_matrix`` (normalises ``q``) into ``R`` (3, 3)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x, y, z, w = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    R[0, 0] = 1 - 2 * (yy + zz)
    R[0, 1] = 2 * (xy - wz)
    R[0, 2] = 2 * (xz + wy)
    R[1, 0] = 2 * (xy + wz)
    R[1, 1] = 1 - 2 * (xx + zz)
    R[1, 2] = 2 * (yz - wx)
    R[2, 0] = 2 * (xz - wy)
    R[2, 1] = 2 * (yz + wx)
    R[2, 2] = 1 - 2 * (xx + yy)


@njit(cache=True, inline="always", error_model="numpy")
def exp_quat(phi, out):
    """``rotations.exp_quat`` of the rotation vector ``phi`` (3,) into ``out`` (4,)."""
    ang = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    if ang < 1e-8:
        k = 0.5 - ang * ang / 48.0
    else:
        k = math.sin(0.5 * ang) / ang
    out[0] = k * phi[0]
    out[1] = k * phi[1]
    out[2] = k * phi[2]
    out[3] = math.cos(0.5 * ang)


@njit(cache=True, inline="always", error_model="numpy")
def log_quat(q, out):
    """``rotations.log_quat`` (normalises, scalar part made non-negative) into ``out`` (3,)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sg = -1.0 if q[3] / n < 0.0 else 1.0
    vx, vy, vz, w = sg * q[0] / n, sg * q[1] / n, sg * q[2] / n, sg * q[3] / n
    s = math.sqrt(vx * vx + vy * vy + vz * vz)
    if s < 1e-8:
        k = 2.0 / w
    else:
        k = 2.0 * math.atan2(s, w) / s
    out[0] = k * vx
    out[1] = k * vy
    out[2] = k * vz


@njit(cache=True, inline="always", error_model="numpy")
def boxplus(q_hat, dtheta, out):
    """``rotations.boxplus``: ``out = exp_quat(dtheta) (x) q_hat`` (``out`` may be ``q_hat``)."""
    e = np.empty(4)
    exp_quat(dtheta, e)
    quat_multiply(e, q_hat, out)


@njit(cache=True, inline="always", error_model="numpy")
def boxminus(q, q_hat, out):
    """``rotations.boxminus``: ``out = log(q (x) conj(q_hat))`` (3,)."""
    c = np.empty(4)
    c[0], c[1], c[2], c[3] = -q_hat[0], -q_hat[1], -q_hat[2], q_hat[3]
    m = np.empty(4)
    quat_multiply(q, c, m)
    log_quat(m, out)


@njit(cache=True, error_model="numpy")
def matrix_to_quat(R):
    """``rotations.matrix_to_quat`` for stacks (M,3,3) of rotation matrices: Shepperd's method
    (the largest of trace and diagonal picks the stable formula), normalised, scalar part
    made non-negative. Unlike scipy it does not first project a non-orthogonal matrix onto
    SO(3): use it only on products of rotation matrices."""
    M = R.shape[0]
    q = np.empty((M, 4))
    for m in range(M):
        r = R[m]
        tr = r[0, 0] + r[1, 1] + r[2, 2]
        big = max(tr, r[0, 0], r[1, 1], r[2, 2])
        if big == tr:
            w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
            f = 0.25 / w
            x, y, z = (r[2, 1] - r[1, 2]) * f, (r[0, 2] - r[2, 0]) * f, (r[1, 0] - r[0, 1]) * f
        elif big == r[0, 0]:
            x = 0.5 * math.sqrt(max(1.0 + 2 * r[0, 0] - tr, 0.0))
            f = 0.25 / x
            w, y, z = (r[2, 1] - r[1, 2]) * f, (r[0, 1] + r[1, 0]) * f, (r[0, 2] + r[2, 0]) * f
        elif big == r[1, 1]:
            y = 0.5 * math.sqrt(max(1.0 + 2 * r[1, 1] - tr, 0.0))
            f = 0.25 / y
            w, x, z = (r[0, 2] - r[2, 0]) * f, (r[0, 1] + r[1, 0]) * f, (r[1, 2] + r[2, 1]) * f
        else:
            z = 0.5 * math.sqrt(max(1.0 + 2 * r[2, 2] - tr, 0.0))
            f = 0.25 / z
            w, x, y = (r[1, 0] - r[0, 1]) * f, (r[0, 2] + r[2, 0]) * f, (r[1, 2] + r[2, 1]) * f
        n = math.sqrt(x * x + y * y + z * z + w * w)
        if w < 0:
            n = -n
        q[m, 0], q[m, 1], q[m, 2], q[m, 3] = x / n, y / n, z / n, w / n
    return q
