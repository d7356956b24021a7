"""Quaternion and rotation conventions of tumblenav (the one module that owns them).

Convention
----------
* Quaternions are stored ``[x, y, z, w]`` (scalar last), exactly as
  :class:`scipy.spatial.transform.Rotation`, and multiplied with the **Hamilton** product.
  Every function accepts stacks of shape ``(..., 4)`` / ``(..., 3)``.
* ``q_AB`` is the quaternion whose matrix ``R_AB = quat_to_matrix(q_AB)`` maps coordinates
  expressed in frame B into frame A: ``v_A = R_AB @ v_B``.  Then ``q_AC = q_AB (x) q_BC``
  (Hamilton) matches ``R_AC = R_AB @ R_BC``, and ``quat_to_matrix`` equals scipy's
  ``Rotation.from_quat(q).as_matrix()``, so scipy is the test oracle with no reordering.
* Kinematics: for ``q_TI`` (maps I into T) and ``omega_TI_T`` (rate of T w.r.t. I expressed in
  T), ``dq_TI/dt = -1/2 [omega; 0] (x) q_TI`` and ``dR_TI/dt = -[omega x] R_TI``.
  Hu 2024 eq. 2 writes ``+1/2 [omega; 0] (x) q`` in the JPL convention; it is the same motion.
* Small-angle error state (left, "global" perturbation, as Hu 2024 eq. 27 orders it):
  ``q_TI = exp_quat(dtheta) (x) q_hat_TI``, i.e. ``R_TI = Exp(dtheta) R_hat_TI`` with
  ``Exp(dtheta) ~ I + [dtheta x]`` (Hamilton sign; the JPL sign of Hu 2024 is ``I - [dtheta x]``).
  ``dtheta`` is expressed in the frame on the left (T for ``q_TI``).

Papers that write quaternions scalar-first (Yu 2019, Kabir 2025) are converted with
:func:`from_scalar_first` / :func:`to_scalar_first` where their equations are implemented.

Twins
-----
* ``*_fast`` (below the references, this module): the same functions written as small matrix
  products, for the large stacks of the unscented filters (2-6x faster there: no
  ``np.cross``, no temporaries per component); equal to the references to rounding
  (tests/test_rotations.py).
* :mod:`tumblenav.rotations_compiled`: numba versions for compiled loops, one quaternion or
  matrix at a time (tests/test_rotations_compiled.py).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

Array = NDArray[np.float64]

__all__ = [
    "IDENTITY",
    "boxminus",
    "boxplus",
    "exp_map",
    "exp_quat",
    "from_scalar_first",
    "log_map",
    "log_quat",
    "matrix_to_quat",
    "quat_angle",
    "boxminus_fast",
    "boxplus_fast",
    "quat_conjugate",
    "quat_derivative",
    "quat_derivative_fast",
    "quat_multiply",
    "quat_multiply_fast",
    "quat_normalize",
    "quat_rotate",
    "quat_to_matrix",
    "quat_to_matrix_fast",
    "skew",
    "to_scalar_first",
]

IDENTITY: Array = np.array([0.0, 0.0, 0.0, 1.0])


def skew(v: ArrayLike) -> Array:
    """Cross-product matrix ``[v x]`` so that ``skew(a) @ b == cross(a, b)``; shape (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def quat_normalize(q: ArrayLike) -> Array:
    """Unit quaternion with non-negative scalar part (the canonical sign of the double cover)."""
    qa = np.asarray(q, dtype=float)
    u = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    return np.where(u[..., 3:4] < 0.0, -u, u)


def quat_conjugate(q: ArrayLike) -> Array:
    """Conjugate (inverse for a unit quaternion): ``q_BA`` from ``q_AB``."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def quat_multiply(p: ArrayLike, q: ArrayLike) -> Array:
    """Hamilton product ``p (x) q`` of [x, y, z, w] quaternions (broadcasts over leading axes)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pv, pw = p[..., :3], p[..., 3:]
    qv, qw = q[..., :3], q[..., 3:]
    vec = pw * qv + qw * pv + np.cross(pv, qv)
    sca = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    return np.concatenate([vec, sca], axis=-1)


def quat_to_matrix(q: ArrayLike) -> Array:
    """Rotation matrix ``R_AB`` of ``q_AB`` (same as scipy's ``as_matrix``); shape (..., 3, 3)."""
    qa = np.asarray(q, dtype=float)
    u = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    x, y, z, w = u[..., 0], u[..., 1], u[..., 2], u[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return np.stack(
        [
            np.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)], -1),
            np.stack([2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)], -1),
            np.stack([2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], -1),
        ],
        -2,
    )


def matrix_to_quat(R: ArrayLike) -> Array:
    """Unit quaternion (scalar part >= 0) of a rotation matrix, stacks of shape (..., 3, 3).

    Delegates to scipy (Shepperd/Markley's method), which also projects a slightly
    non-orthogonal matrix onto the nearest rotation.
    """
    R = np.asarray(R, dtype=float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    return quat_normalize(q.reshape(*R.shape[:-2], 4))


def quat_rotate(q: ArrayLike, v: ArrayLike) -> Array:
    """``R(q) @ v`` for stacks of quaternions and/or vectors."""
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    qv, qw = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(qv, v)
    return v + qw * t + np.cross(qv, t)


def exp_map(phi: ArrayLike) -> Array:
    """Rotation matrix ``Exp(phi) = exp([phi x])`` of a rotation vector (rad); (..., 3, 3)."""
    return quat_to_matrix(exp_quat(phi))


def exp_quat(phi: ArrayLike) -> Array:
    """Unit quaternion of the rotation vector ``phi`` (rad): angle ``|phi|`` about ``phi/|phi|``."""
    phi = np.asarray(phi, dtype=float)
    ang = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * ang
    # sin(a/2)/a with its Taylor series near zero (no division by a tiny angle).
    small = ang < 1e-8
    safe = np.where(small, 1.0, ang)
    k = np.where(small, 0.5 - ang**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([k * phi, np.cos(half)], axis=-1)


def log_quat(q: ArrayLike) -> Array:
    """Rotation vector (rad, angle in [0, pi]) of a unit quaternion; inverse of :func:`exp_quat`."""
    q = quat_normalize(q)
    v, w = q[..., :3], q[..., 3:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, w)
    small = s < 1e-8
    k = np.where(small, 2.0 / np.where(small, w, 1.0), ang / np.where(small, 1.0, s))
    return k * v


def log_map(R: ArrayLike) -> Array:
    """Rotation vector of a rotation matrix; inverse of :func:`exp_map`."""
    return log_quat(matrix_to_quat(R))


def quat_angle(q: ArrayLike) -> Array:
    """Rotation angle (rad, in [0, pi]) of a quaternion, e.g. of ``q_err = q (x) conj(q_hat)``."""
    q = np.asarray(q, dtype=float)
    s = np.linalg.norm(q[..., :3], axis=-1)
    return 2.0 * np.arctan2(s, np.abs(q[..., 3]))


def boxplus(q_hat: ArrayLike, dtheta: ArrayLike) -> Array:
    """``q = exp_quat(dtheta) (x) q_hat``: the error-state composition of Hu 2024 eq. 27/44."""
    return quat_multiply(exp_quat(dtheta), q_hat)


def boxminus(q: ArrayLike, q_hat: ArrayLike) -> Array:
    """``dtheta = log(q (x) conj(q_hat))``, inverse of :func:`boxplus`."""
    return log_quat(quat_multiply(q, quat_conjugate(q_hat)))


def quat_derivative(q_TI: ArrayLike, omega_TI_T: ArrayLike) -> Array:
    """``dq_TI/dt = -1/2 [omega; 0] (x) q_TI`` (Hamilton form of Hu 2024 eq. 2)."""
    omega = np.asarray(omega_TI_T, dtype=float)
    w4 = np.concatenate([omega, np.zeros(omega.shape[:-1] + (1,))], axis=-1)
    return -0.5 * quat_multiply(w4, q_TI)


def from_scalar_first(q_wxyz: ArrayLike) -> Array:
    """Convert a paper's ``[w, x, y, z]`` quaternion into tumblenav's ``[x, y, z, w]``."""
    q = np.asarray(q_wxyz, dtype=float)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def to_scalar_first(q_xyzw: ArrayLike) -> Array:
    """Convert tumblenav's ``[x, y, z, w]`` into a paper's ``[w, x, y, z]``."""
    q = np.asarray(q_xyzw, dtype=float)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


# --------------------------------------------------------------------------------------------
# Fast twins for large stacks: the same values (to rounding) as small matrix products
# --------------------------------------------------------------------------------------------
# The Hamilton product is bilinear: _QMUL[i, 4 j + k] = (e_i (x) e_j)_k, taken once from
# quat_multiply (so the convention is the reference's), makes the product two small matrix
# products (np.cross inside quat_multiply dominates on stacks of sigma points).
_QMUL = np.stack([quat_multiply(np.eye(4)[i], np.eye(4)) for i in range(4)]).reshape(4, 16)

# dq/dt = -1/2 [omega; 0] (x) q is bilinear in omega and q: _KIN[i, 4 j + k] =
# quat_derivative(e_j, e_i)_k, taken once from the reference.
_KIN = np.stack([quat_derivative(np.eye(4), np.eye(3)[i]) for i in range(3)]).reshape(3, 16)


def _rotation_coefficients() -> Array:
    """(16, 9) ``C`` with ``R(q) = (q q^T).ravel() @ C / |q|^2`` equal to
    :func:`quat_to_matrix` (a quadratic form of the unit quaternion): the symmetric bilinear
    form by polarisation of the reference."""
    E = np.eye(4)
    M = quat_to_matrix
    C = np.zeros((4, 4, 9))
    for a in range(4):
        for b in range(4):
            # H(q) = |q|^2 M(q) is quadratic: C[a, b] = (H(e_a + e_b) - H(e_a) - H(e_b)) / 2,
            # and C[a, a] = H(e_a); here |e_a + e_b|^2 = 2 for a != b
            if a == b:
                C[a, a] = M(E[a]).ravel()
            else:
                C[a, b] = (2.0 * M(E[a] + E[b]) - M(E[a]) - M(E[b])).ravel() / 2.0
    return C.reshape(16, 9)


_ROT = _rotation_coefficients()


def quat_multiply_fast(p: Array, q: Array) -> Array:
    """:func:`quat_multiply` ``p (x) q`` for stacks (broadcasts), as two matrix products."""
    W = (p @ _QMUL).reshape(p.shape[:-1] + (4, 4))
    return (q[..., None, :] @ W)[..., 0, :]


def quat_derivative_fast(q_TI: Array, omega_TI_T: Array) -> Array:
    """:func:`quat_derivative` (``q`` (..., 4), ``omega`` (..., 3)), as two matrix products."""
    W = (omega_TI_T @ _KIN).reshape(omega_TI_T.shape[:-1] + (4, 4))  # [j] = derivative of e_j
    return (q_TI[..., None, :] @ W)[..., 0, :]


def quat_to_matrix_fast(q: Array) -> Array:
    """:func:`quat_to_matrix` for stacks of (not necessarily unit) ``q``, as a quadratic form."""
    qq = (q[..., :, None] * q[..., None, :]).reshape(q.shape[:-1] + (16,))
    return ((qq @ _ROT) / np.sum(q * q, axis=-1, keepdims=True)).reshape(q.shape[:-1] + (3, 3))


def boxplus_fast(q_hat: Array, dtheta: Array) -> Array:
    """:func:`boxplus` with :func:`quat_multiply_fast`."""
    return quat_multiply_fast(exp_quat(dtheta), q_hat)


def boxminus_fast(q: Array, q_hat: Array) -> Array:
    """:func:`boxminus` with :func:`quat_multiply_fast`."""
    return log_quat(quat_multiply_fast(q, quat_conjugate(q_hat)))
