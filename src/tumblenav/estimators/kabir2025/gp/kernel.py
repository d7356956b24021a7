"""The product of periodic kernels (Kabir 2025 eq. 9-10) and its Fourier lattice: the\nfeatures whose Gram matrix approximates it to TRUNCATION."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from tumblenav.estimators.kabir2025.gp import compiled

Array = NDArray[np.float64]


TRUNCATION = 1e-13  # dropped prior variance, relative to the kernel's total (1)


ELL_MARGIN = 0.8  # the feature set covers lengthscales down to this fraction of the start


SHRINK = 0.7  # re-build the feature set once the lengthscales allow one this much smaller


FLAT1 = 1.0  # nats gained over 10 iterations below which stage 1 (B diagonal) stops


ELL0 = (1.0, 2.0)  # initial lengthscales (long, short period); the feature set grows if l shrinks


def kernel(tau: ArrayLike, periods: ArrayLike, lengthscales: ArrayLike) -> Array:
    """Kabir 2025 eq. 26 with unit amplitudes: product of two periodic kernels of ``tau`` (s)."""
    tau = np.asarray(tau, float)
    out = np.ones_like(tau)
    for P, ell in zip(np.asarray(periods, float), np.asarray(lengthscales, float), strict=True):
        out = out * np.exp(-2.0 * np.sin(np.pi * tau / P) ** 2 / ell**2)
    return out


def _order(ell: float, eps: float = TRUNCATION) -> int:
    """Smallest M with ``ive(M, 1/l^2) < eps`` (the Bessel coefficients fall monotonically)."""
    x = 1.0 / ell**2
    n = np.arange(0, 400)
    c = special.ive(n, x)
    return int(np.argmax(c < eps))


@dataclass(frozen=True)
class _Features:
    """Lattice indices of the real Fourier features: cosines of every pair, sines of all but
    the constant (0, 0) one.  ``n`` (0..M1) and ``m`` (-M2..M2) index the two periods."""

    n: NDArray[np.int64]  # (K,) pairs in the half plane (n > 0, or n = 0 and m >= 0)
    m: NDArray[np.int64]
    M1: int
    M2: int

    @property
    def R(self) -> int:
        return 2 * len(self.n) - 1

    @functools.cached_property
    def lattice_index(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Flat indices into the (4 M1 + 1, 4 M2 + 1) lattice sums of ``a - b`` and ``a + b``
        for every pair of features (K, K)."""
        n, m = self.n, self.m
        cols = 4 * self.M2 + 1

        def flat(dn: NDArray[np.int64], dm: NDArray[np.int64]) -> NDArray[np.int64]:
            return (dn + 2 * self.M1) * cols + (dm + 2 * self.M2)

        return (
            flat(n[:, None] - n[None, :], m[:, None] - m[None, :]),
            flat(n[:, None] + n[None, :], m[:, None] + m[None, :]),
        )

    @classmethod
    def build(cls, ell_min: ArrayLike, eps: float = TRUNCATION) -> _Features:
        l1, l2 = np.asarray(ell_min, float)
        M1, M2 = _order(l1, eps), _order(l2, eps)
        c1 = special.ive(np.arange(M1 + 1), 1.0 / l1**2)
        c2 = special.ive(np.abs(np.arange(-M2, M2 + 1)), 1.0 / l2**2)
        nn, mm = np.meshgrid(np.arange(M1 + 1), np.arange(-M2, M2 + 1), indexing="ij")
        keep = (nn > 0) | (mm >= 0)
        keep &= c1[nn] * c2[mm + M2] * np.where((nn == 0) & (mm == 0), 1.0, 2.0) >= eps
        n, m = nn[keep], mm[keep]
        order = np.lexsort((m, n))  # (0, 0) first
        return cls(n=n[order], m=m[order], M1=M1, M2=M2)


def _prior_weights(feat: _Features, ell: Array) -> tuple[Array, Array]:
    """Prior variances ``s`` (R,) of the features and ``d log s / d log l`` (R, 2)."""
    x = 1.0 / np.asarray(ell, float) ** 2
    s_parts, dlog = [], []
    for idx, xk in ((np.abs(feat.n), x[0]), (np.abs(feat.m), x[1])):
        c = special.ive(idx, xk)
        dc_dx = 0.5 * (special.ive(idx - 1, xk) + special.ive(idx + 1, xk)) - c
        s_parts.append(c)
        dlog.append(dc_dx / c * (-2.0 * xk))  # x = l^-2: dx/dlog l = -2x
    pair = s_parts[0] * s_parts[1] * np.where((feat.n == 0) & (feat.m == 0), 1.0, 2.0)
    s = np.concatenate([pair, pair[1:]])
    d = np.stack(dlog, axis=1)
    return s, np.concatenate([d, d[1:]], axis=0)


@dataclass(frozen=True)
class _Lattice:
    """Sums over the sample times of ``w(t) exp(i 2 pi (p/P1 + q/P2) t)`` for
    ``|p| <= 2 M1``, ``|q| <= 2 M2`` and weights ``w = 1`` and ``w = t``; and the feature-data
    products ``Phi^T Y`` with their derivatives.  Everything Woodbury needs from the data."""

    W0: NDArray[np.complex128]  # (4M1+1, 4M2+1)
    W1: NDArray[np.complex128]
    FY: Array  # (R, D) Phi^T Y
    dFY: Array  # (2, R, D) d Phi^T Y / d log P_k


def _phases(t: Array, periods: Array, orders: tuple[int, int]) -> tuple[Array, Array]:
    """``exp(i 2 pi k t / P)`` for ``k = -M..M`` (N, 2M+1) per period, by repeated products
    of one complex exponential (rounding grows as M eps, i.e. ~1e-14).  :func:`_lattice`
    takes the same numbers from :mod:`.compiled` (``phase_powers``, ``lattice_phases``)."""
    z = []
    for P, M in zip(periods, orders, strict=True):
        base = np.exp(2j * np.pi * t / P)
        pos = np.cumprod(np.repeat(base[:, None], M, axis=1), axis=1)  # k = 1..M
        z.append(np.concatenate([np.conj(pos[:, ::-1]), np.ones((len(t), 1)), pos], axis=1))
    return z[0], z[1]


def _lattice(t: Array, Y: Array, periods: Array, feat: _Features) -> _Lattice:
    M1, M2 = feat.M1, feat.M2
    # _phases' products (compiled, the same bits), of which only p >= 0 is summed: the sums at
    # (-p, -q) are the conjugates of those at (p, q).
    base1, base2 = (np.exp(2j * np.pi * t / P) for P in periods)
    zp, Z2 = compiled.lattice_phases(
        compiled.phase_powers(base1, 2 * M1), compiled.phase_powers(base2, 2 * M2)
    )  # p = 0..2 M1; q = -2 M2..2 M2
    tZ2 = t[:, None] * Z2
    half0, half1 = zp.T @ Z2, zp.T @ tZ2  # (2 M1 + 1, 4 M2 + 1)
    W0 = np.concatenate([np.conj(half0[:0:-1, ::-1]), half0], axis=0)
    W1 = np.concatenate([np.conj(half1[:0:-1, ::-1]), half1], axis=0)
    # Phi^T Y via complex sums S(n, m) = sum_t y(t) exp(i theta_nm(t)), theta = 2 pi (n/P1 + m/P2) t
    z1 = zp[:, : M1 + 1]  # n = 0..M1
    z2 = Z2[:, M2 : 3 * M2 + 1]  # m = -M2..M2
    tz2 = tZ2[:, M2 : 3 * M2 + 1]
    zy = compiled.weighted_phases(z1, Y)  # (N, (M1+1) D): z1[:, :, None] * Y[:, None, :]
    S = (zy.T @ z2).reshape(M1 + 1, -1, 2 * M2 + 1)[feat.n, :, feat.m + M2]  # (K, D)
    ST = (zy.T @ tz2).reshape(M1 + 1, -1, 2 * M2 + 1)[feat.n, :, feat.m + M2]
    FY = np.concatenate([S.real, S.imag[1:]], axis=0)
    dFY = np.empty((2,) + FY.shape)
    for k, (idx, P) in enumerate(((feat.n, periods[0]), (feat.m, periods[1]))):
        # d theta / d log P = -2 pi idx t / P: d cos = sin * 2 pi idx t/P, d sin = -cos * (...)
        g = (2.0 * np.pi * idx / P)[:, None]
        dFY[k] = np.concatenate([g * ST.imag, (-g * ST.real)[1:]], axis=0)
    return _Lattice(W0=W0, W1=W1, FY=FY, dFY=dFY)


def _gram(lat: _Lattice, feat: _Features, periods: Array) -> tuple[Array, Array, Array]:
    """``G = Phi^T Phi`` (R, R) from the lattice sums (cos a cos b = (cos(a-b) + cos(a+b))/2
    and so on), and the derivatives ``E_k = Phi^T d Phi / d log P_k = T diag(g_k)`` in factored
    form: ``T`` (R, R) and the column scalings ``g`` (2, R)."""
    idx_d, idx_s = feat.lattice_index
    R = feat.R
    # With Wd, Ws the lattice sums at a - b and a + b (weights w = 1 and t):
    #   sum w cos_a cos_b = (Wd + Ws).real / 2    sum w sin_a sin_b = (Wd - Ws).real / 2
    #   sum w cos_a sin_b = (Ws - Wd).imag / 2    sum w sin_a cos_b = (Ws + Wd).imag / 2
    # G = [[cc, cs], [sc, ss]] (weight 1), the sines without the constant feature.
    # d/dlogP_k of cos_b = sin_b * g_b t, of sin_b = -cos_b * g_b t (g_b = 2 pi idx_b / P_k):
    # E[a, b] = g_b * sum t phi_a {sin_b | -cos_b} = T[a, b] g_b, T = [[cs, -cc], [ss, -sc]]
    # (weight t). Gathered in one compiled pass (compiled.gram_blocks).
    G, T = compiled.gram_blocks(lat.W0.ravel(), lat.W1.ravel(), idx_d, idx_s)
    g = np.empty((2, R))
    for k, (idx, P) in enumerate(((feat.n, periods[0]), (feat.m, periods[1]))):
        gk = 2.0 * np.pi * idx / P
        g[k] = np.concatenate([gk, gk[1:]])
    return G, T, g
