"""Compiled (numba) loops of the GP likelihood (:mod:`.kernel`, :mod:`.likelihood`): the same
arithmetic as the numpy they replace, operation for operation, to the last bit.

Why bit for bit: L-BFGS-B's path over the hyper-parameters is chaotic in the last bits of the
gradient (a summation reordered in one term moved a fitted kabir2025 feature model to another
local optimum, 386 nats away), so these loops add no speed at the price of other fits. They
save what numpy spends on temporaries, gathers and copies: the lattice phases, the Gram
matrix's four blocks (:func:`gram_blocks`) and the systems ``I + d_j U G U`` written straight
into the Fortran-ordered lower triangle that LAPACK's ``potrf`` factorises in place
(:func:`lower_system`). No ``fastmath``: a fused multiply-add or a reassociation would change
the bits.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def phase_powers(base, M):  # pragma: no cover - compiled
    """``base**k`` for ``k = 1..M`` (N, M) by repeated products, as
    ``np.cumprod(np.repeat(base[:, None], M, axis=1), axis=1)``."""
    n = base.shape[0]
    out = np.empty((n, M), np.complex128)
    for i in range(n):
        b = base[i]
        z = b
        if M > 0:
            out[i, 0] = z
        for k in range(1, M):
            z = z * b
            out[i, k] = z
    return out


@njit(cache=True, error_model="numpy")
def lattice_phases(pos1, pos2):  # pragma: no cover - compiled
    """``zp = [1, pos1]`` (N, M1' + 1): the non-negative harmonics of the first period, and
    ``Z2 = [conj(pos2) reversed, 1, pos2]`` (N, 2 M2' + 1): all harmonics of the second
    (:func:`~.kernel._phases`' arrays, of which ``_lattice`` uses these parts)."""
    n, m1 = pos1.shape
    m2 = pos2.shape[1]
    zp = np.empty((n, m1 + 1), np.complex128)
    Z2 = np.empty((n, 2 * m2 + 1), np.complex128)
    for i in range(n):
        zp[i, 0] = 1.0
        for k in range(m1):
            zp[i, k + 1] = pos1[i, k]
        Z2[i, m2] = 1.0
        for k in range(m2):
            z = pos2[i, k]
            Z2[i, m2 + 1 + k] = z
            Z2[i, m2 - 1 - k] = np.conj(z)
    return zp, Z2


@njit(cache=True, error_model="numpy")
def gram_blocks(W0, W1, idx_d, idx_s):  # pragma: no cover - compiled
    """``G`` and ``T`` (R, R), R = 2K - 1, from the lattice sums with weights 1 (``W0``) and
    ``t`` (``W1``), flattened, at the index pairs ``a - b`` (``idx_d``) and ``a + b``
    (``idx_s``) (K, K): :func:`~.kernel._gram`'s blocks (cos a cos b = (cos(a-b) +
    cos(a+b))/2 and so on)."""
    K = idx_d.shape[0]
    R = 2 * K - 1
    G = np.empty((R, R))
    T = np.empty((R, R))
    for a in range(K):
        for b in range(K):
            i = idx_d[a, b]
            j = idx_s[a, b]
            d0, s0, d1, s1 = W0[i], W0[j], W1[i], W1[j]
            G[a, b] = 0.5 * (d0.real + s0.real)  # sum cos_a cos_b
            T[a, b] = 0.5 * (s1.imag - d1.imag)  # sum t cos_a sin_b
            if b >= 1:
                G[a, K + b - 1] = 0.5 * (s0.imag - d0.imag)  # sum cos_a sin_b
                T[a, K + b - 1] = -(0.5 * (d1.real + s1.real))  # -sum t cos_a cos_b
            if a >= 1:
                G[K + a - 1, b] = 0.5 * (s0.imag + d0.imag)  # sum sin_a cos_b
                T[K + a - 1, b] = 0.5 * (d1.real - s1.real)  # sum t sin_a sin_b
                if b >= 1:
                    G[K + a - 1, K + b - 1] = 0.5 * (d0.real - s0.real)  # sum sin_a sin_b
                    T[K + a - 1, K + b - 1] = -(0.5 * (s1.imag + d1.imag))  # -sum t sin_a cos_b
    return G, T


@njit(cache=True, error_model="numpy")
def lower_system(G, u, d, out):  # pragma: no cover - compiled
    """The lower triangle of ``M = (u u^T * G) d + I`` into ``out`` (R, R, Fortran order), as
    numpy's ``H = u[:, None] * G * u[None, :]; M = H * d; M[diag] += 1``; the upper triangle
    is left as it is (``potrf`` reads the lower one only)."""
    R = G.shape[0]
    for b in range(R):
        ub = u[b]
        for a in range(b, R):
            out[a, b] = ((u[a] * G[a, b]) * ub) * d
        out[b, b] += 1.0
    return out


@njit(cache=True, error_model="numpy")
def trace_weights(Minv, T, TT, u, diag_minv):  # pragma: no cover - compiled
    """``w = colsum(Minv * Y) + rowsum(Minv * Y^T) - diag(Minv) diag(Y)`` with
    ``Y = U T U`` (``Y_ab = (u_a T_ab) u_b``), ``Minv`` (R, R, Fortran order) and ``TT = T^T``
    (C order), as numpy's ``np.einsum("ab,ab->b", Minv, Y) + np.einsum("ab,ab->a", Minv,
    Y^T) - diag_minv * diag(Y)``: every sum in ascending index order from 0, without forming
    ``Y``. The column sums run four columns at a time (independent sums)."""
    R = u.shape[0]
    e1 = np.empty(R)
    b = 0
    while b + 4 <= R:  # e1_b = sum_a Minv_ab Y_ab: Minv's columns, TT's rows (contiguous)
        u0, u1, u2, u3 = u[b], u[b + 1], u[b + 2], u[b + 3]
        s0 = s1 = s2 = s3 = 0.0
        for a in range(R):
            ua = u[a]
            s0 += Minv[a, b] * ((ua * TT[b, a]) * u0)
            s1 += Minv[a, b + 1] * ((ua * TT[b + 1, a]) * u1)
            s2 += Minv[a, b + 2] * ((ua * TT[b + 2, a]) * u2)
            s3 += Minv[a, b + 3] * ((ua * TT[b + 3, a]) * u3)
        e1[b], e1[b + 1], e1[b + 2], e1[b + 3] = s0, s1, s2, s3
        b += 4
    while b < R:
        ub = u[b]
        s = 0.0
        for a in range(R):
            s += Minv[a, b] * ((u[a] * TT[b, a]) * ub)
        e1[b] = s
        b += 1
    e2 = np.zeros(R)  # e2_a = sum_b Minv_ab Y_ba, b ascending for every a
    for b in range(R):
        ub = u[b]
        for a in range(R):
            e2[a] += Minv[a, b] * ((ub * T[b, a]) * u[a])
    w = np.empty(R)
    for a in range(R):
        w[a] = (e1[a] + e2[a]) - diag_minv[a] * ((u[a] * T[a, a]) * u[a])
    return w


@njit(cache=True, error_model="numpy")
def weighted_phases(z1, Y):  # pragma: no cover - compiled
    """``(z1[:, :, None] * Y[:, None, :]).reshape(N, -1)`` (N, M D): numpy's complex product
    with ``Y`` as ``Y + 0j``, ``(a + ib)(y + 0i) = (a y - b 0) + i (a 0 + b y)``."""
    n, m = z1.shape
    D = Y.shape[1]
    out = np.empty((n, m * D), np.complex128)
    for t in range(n):
        for k in range(m):
            a = z1[t, k].real
            b = z1[t, k].imag
            for d in range(D):
                y = Y[t, d]
                out[t, k * D + d] = complex(a * y - b * 0.0, a * 0.0 + b * y)
    return out
