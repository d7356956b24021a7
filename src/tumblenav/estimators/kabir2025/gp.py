"""Multi-output Gaussian process of Kabir 2025 Sec. 2.3: intrinsic coregionalisation (ICM) over
the outputs and a product of two periodic kernels over time, trained by maximum likelihood.

Model (Kabir 2025 eq. 26 and the ICM of its ref. [32]), for D outputs ``y(t)`` (D = 3:
``[u_R, v_R, u_L]`` of one feature)::

    cov(y_i(t), y_j(t')) = B_ij k(t - t') + delta_ij delta(t - t') sigma_i^2
    k(tau) = exp(-2 sin^2(pi tau / P1) / l1^2) * exp(-2 sin^2(pi tau / P2) / l2^2)

The paper's kernel amplitudes ``sigma_1^2 sigma_2^2`` multiply the coregionalisation matrix
``B`` and are not identifiable apart from it, so they are folded into ``B`` (full rank,
Cholesky-parametrised).  The outputs share one noise variance (the projections of a stereo
pair come with the same angular noise ``sigma_p``, Kabir 2025 Sec. 3); the data are centred,
scaled by one common factor and rotated onto their principal components before training, which
leaves isotropic noise isotropic and makes ``B`` nearly diagonal (a well-conditioned
optimisation).

Why this is written here instead of calling GPy/GPyTorch
--------------------------------------------------------
Exact GP likelihoods on ``N D = 4500`` correlated values cost seconds per evaluation
(issue #4 measured 3-8 s in GPy, 79-99 s per model in GPyTorch).  The structure of this
particular kernel makes it exact and cheap, and no library exploits it:

* A periodic kernel has a finite-precision Fourier expansion (modified Bessel functions)::

      exp(-2 sin^2(pi tau/P)/l^2) = sum_n ive(n, 1/l^2) cos(2 pi n tau / P)

  so the product kernel is a sum of cosines at the lattice frequencies ``n/P1 + m/P2``
  (``k = Phi S Phi^T`` with ``R = (2 M1 + 1)(2 M2 + 1)`` real features).  The expansion is
  truncated where a term's prior variance is below ``1e-13`` of the total (the dropped terms
  sum to about 1e-12, 6e-12 at the smallest lengthscale allowed), far below the noise floor:
  the same kernel to 11-12 digits (tests/test_gp.py checks 5e-12), not an approximation of it.
* Whitening by the noise and rotating the outputs by the eigenvectors of the whitened ``B``
  splits the ICM likelihood into D independent single-output problems that share ``Phi``
  (the Kronecker structure ``B (x) K + Sigma (x) I``).
* Woodbury turns each into an ``R x R`` problem; ``Phi^T Phi`` and its derivatives with
  respect to the periods are gathered from lattice sums ``sum_t t^a exp(i 2 pi (p/P1 + q/P2) t)``
  (one small complex matrix product), so the cost of an evaluation does not grow with N.

Likelihood and every gradient are analytic (checked against finite differences in
tests/test_gp.py); L-BFGS-B (scipy) optimises the log-hyper-parameters.

Periods: Kabir 2025 Algorithm 1 (FFT peaks, pairs scored by period difference times summed
magnitude) gives the initial guess.  Beyond the paper, the FFT peaks are refined by a
zero-padded, windowed FFT, and several candidate pairs (Algorithm 1's best ones and the
lattice-equivalent alternatives) are scored by a short optimisation before the full one
(a global step over the periods), so that a wrong local optimum is not accepted; a fitted
model whose noise estimate is far above the sensor noise is flagged as badly trained.
Each start is first sharpened by fitting the two periods alone (:func:`_refine_periods`, a
ridge harmonic fit within one FFT bin), which halves the evaluations of the full fit.
"""

from __future__ import annotations

import functools
import itertools
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg, optimize, special
from threadpoolctl import threadpool_limits

from tumblenav.errors import InputError

Array = NDArray[np.float64]

__all__ = [
    "GPFit",
    "fft_period_guess",
    "fit_icm_gp",
    "kernel",
    "nll_and_grad",
]

TRUNCATION = 1e-13  # dropped prior variance, relative to the kernel's total (1)
ELL_MARGIN = 0.8  # the feature set covers lengthscales down to this fraction of the start
SHRINK = 0.7  # re-build the feature set once the lengthscales allow one this much smaller
FLAT1 = 1.0  # nats gained over 10 iterations below which stage 1 (B diagonal) stops
ELL0 = (1.0, 2.0)  # initial lengthscales (long, short period); the feature set grows if l shrinks


# --- the kernel and its Fourier features --------------------------------------------------


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
    of one complex exponential (rounding grows as M eps, i.e. ~1e-14)."""
    z = []
    for P, M in zip(periods, orders, strict=True):
        base = np.exp(2j * np.pi * t / P)
        pos = np.cumprod(np.repeat(base[:, None], M, axis=1), axis=1)  # k = 1..M
        z.append(np.concatenate([np.conj(pos[:, ::-1]), np.ones((len(t), 1)), pos], axis=1))
    return z[0], z[1]


def _lattice(t: Array, Y: Array, periods: Array, feat: _Features) -> _Lattice:
    M1, M2 = feat.M1, feat.M2
    Z1, Z2 = _phases(t, periods, (2 * M1, 2 * M2))
    tZ2 = t[:, None] * Z2
    # Only p >= 0 is summed: the sums at (-p, -q) are the conjugates of those at (p, q).
    zp = Z1[:, 2 * M1 :]  # p = 0..2 M1
    half0, half1 = zp.T @ Z2, zp.T @ tZ2  # (2 M1 + 1, 4 M2 + 1)
    W0 = np.concatenate([np.conj(half0[:0:-1, ::-1]), half0], axis=0)
    W1 = np.concatenate([np.conj(half1[:0:-1, ::-1]), half1], axis=0)
    # Phi^T Y via complex sums S(n, m) = sum_t y(t) exp(i theta_nm(t)), theta = 2 pi (n/P1 + m/P2) t
    z1 = Z1[:, 2 * M1 : 3 * M1 + 1]  # n = 0..M1
    z2 = Z2[:, M2 : 3 * M2 + 1]  # m = -M2..M2
    tz2 = tZ2[:, M2 : 3 * M2 + 1]
    zy = (z1[:, :, None] * Y[:, None, :]).reshape(len(t), -1)  # (N, (M1+1) D)
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
    K = len(feat.n)
    R = feat.R
    W = np.stack([lat.W0.ravel(), lat.W1.ravel()])  # weights 1 and t
    Wd, Ws = W[:, idx_d], W[:, idx_s]  # (2, K, K) at a - b and a + b
    cc = 0.5 * (Wd.real + Ws.real)  # sum w cos_a cos_b
    ss = 0.5 * (Wd.real - Ws.real)  # sum w sin_a sin_b
    cs = 0.5 * (Ws.imag - Wd.imag)  # sum w cos_a sin_b
    sc = 0.5 * (Ws.imag + Wd.imag)  # sum w sin_a cos_b
    G = np.empty((R, R))
    G[:K, :K], G[:K, K:], G[K:, :K], G[K:, K:] = cc[0], cs[0, :, 1:], sc[0, 1:, :], ss[0, 1:, 1:]
    # d/dlogP_k of cos_b = sin_b * g_b t, of sin_b = -cos_b * g_b t (g_b = 2 pi idx_b / P_k):
    # E[a, b] = g_b * sum t phi_a {sin_b | -cos_b} = T[a, b] g_b
    T = np.empty((R, R))
    T[:K, :K], T[:K, K:], T[K:, :K], T[K:, K:] = cs[1], -cc[1, :, 1:], ss[1, 1:, :], -sc[1, 1:, 1:]
    g = np.empty((2, R))
    for k, (idx, P) in enumerate(((feat.n, periods[0]), (feat.m, periods[1]))):
        gk = 2.0 * np.pi * idx / P
        g[k] = np.concatenate([gk, gk[1:]])
    return G, T, g


# --- the likelihood ------------------------------------------------------------------------


@dataclass(frozen=True)
class _Theta:
    """Unpacked log-hyper-parameters: ``[log P1, log P2, log l1, log l2, L (lower, log diag),
    log sigma]`` with ``B = sigma^2 L L^T`` (L L^T is the noise-whitened ICM matrix)."""

    periods: Array
    ell: Array
    L: Array
    sigma: Array

    @classmethod
    def unpack(cls, theta: Array, D: int) -> _Theta:
        theta = np.asarray(theta, float)
        nL = D * (D + 1) // 2
        L = np.zeros((D, D))
        L[np.tril_indices(D)] = theta[4 : 4 + nL]
        di = np.diag_indices(D)
        L[di] = np.exp(L[di])
        return cls(np.exp(theta[:2]), np.exp(theta[2:4]), L, np.full(D, np.exp(theta[4 + nL])))

    @staticmethod
    def pack(periods, ell, L, sigma) -> Array:
        L = np.array(L, float)
        D = L.shape[0]
        di = np.diag_indices(D)
        L[di] = np.log(L[di])
        return np.concatenate(
            [np.log(periods), np.log(ell), L[np.tril_indices(D)], [np.log(sigma)]]
        )


@dataclass
class _Solve:
    """Per rotated output j: Cholesky of ``M_j = I + d_j U G U`` and ``alpha_j``."""

    d: Array
    V: Array
    u: Array
    chol: list[Array]
    alpha: Array  # (R, D)


def _cholesky_jittered(M: Array) -> Array:
    """Cholesky of ``M = I + d H``.  ``H = U G U`` is PSD in exact arithmetic, but its
    rounding-level negative eigenvalues (~1e-13 |H|) times a huge ``d`` (a degenerate
    optimiser step: signal-to-noise ratio 1e9) can break it; then add the smallest jitter
    that works (the likelihood there is far from the optimum anyway)."""
    try:
        return linalg.cholesky(M, lower=True, check_finite=False)
    except linalg.LinAlgError:
        scale = float(np.max(np.diag(M)))
        for rel in (1e-14, 1e-12, 1e-10, 1e-8, 1e-6):
            try:
                return linalg.cholesky(
                    M + rel * scale * np.eye(len(M)), lower=True, check_finite=False
                )
            except linalg.LinAlgError:
                continue
        raise


def _solve(G: Array, FY: Array, s: Array, th: _Theta, N: int) -> tuple[float, _Solve, Array]:
    D = FY.shape[1]
    Bt = th.L @ th.L.T
    d, V = np.linalg.eigh(Bt)
    d = np.maximum(d, 1e-300)
    u = np.sqrt(s)
    H = u[:, None] * G * u[None, :]
    br = (FY / th.sigma[None, :]) @ V  # (R, D) Phi^T Yr
    chol, alpha, nll = [], np.empty_like(br), N * float(np.sum(np.log(th.sigma)))
    quad = np.empty(D)
    for j in range(D):
        M = H * d[j]
        M[np.diag_indices_from(M)] += 1.0
        c = _cholesky_jittered(M)
        ub = u * br[:, j]
        alpha[:, j] = linalg.cho_solve((c, True), ub, check_finite=False)
        quad[j] = d[j] * ub @ alpha[:, j]
        nll += float(np.sum(np.log(np.diag(c))))
        chol.append(c)
    return nll - 0.5 * float(np.sum(quad)), _Solve(d, V, u, chol, alpha), br


def nll_and_grad(
    theta: ArrayLike, t: ArrayLike, Y: ArrayLike, feat: _Features | None = None
) -> tuple[float, Array]:
    """Negative log marginal likelihood of the ICM model (up to ``N D log(2 pi)/2``) and its
    gradient with respect to the log-hyper-parameters (see :class:`_Theta`)."""
    t, Y = np.asarray(t, float), np.asarray(Y, float)
    N, D = Y.shape
    th = _Theta.unpack(np.asarray(theta, float), D)
    feat = feat or _Features.build(th.ell)
    return _nll_grad(_prepare(t, Y, th, feat), th, Y, len(np.atleast_1d(theta)))


@dataclass(frozen=True)
class _Prepared:
    """Everything that depends on the periods and lengthscales only."""

    lat: _Lattice
    G: Array
    T: Array  # E_k = Phi^T d Phi / d log P_k = T diag(g[k])
    g: Array
    s: Array
    dlogs: Array


def _prepare(t: Array, Y: Array, th: _Theta, feat: _Features) -> _Prepared:
    lat = _lattice(t, Y, th.periods, feat)
    G, T, g = _gram(lat, feat, th.periods)
    s, dlogs = _prior_weights(feat, th.ell)
    return _Prepared(lat, G, T, g, s, dlogs)


def _nll_grad(pre: _Prepared, th: _Theta, Y: Array, n_theta: int) -> tuple[float, Array]:
    lat, G, s, dlogs = pre.lat, pre.G, pre.s, pre.dlogs
    N, D = Y.shape
    yw = Y / th.sigma[None, :]
    nll, so, br = _solve(G, lat.FY, s, th, N)
    nll += 0.5 * float(np.sum(yw * yw))
    d, V, u = so.d, so.V, so.u
    R = len(s)
    grad = np.zeros(n_theta)
    g_l = np.zeros(2)
    g_P = np.zeros(2)
    tvec = np.empty(D)
    Psi = np.empty((R, D))  # U Phi^T beta_j (rotated basis)
    dbr = np.einsum("krd,de->kre", lat.dFY / th.sigma[None, None, :], V)
    # tr(Minv X_k) with X_k = U E_k U = U T U diag(g_k) is g_k . w, w_b = sum_a Minv_ab Y_ab
    # (Y = U T U).  potri returns the lower triangle of the symmetric Minv (zeros above), so
    # w = colsum(Minv_low * Y) + rowsum(Minv_low * Y^T) - diag(Minv) diag(Y).
    Yt = u[:, None] * pre.T * u[None, :]
    YtT = np.ascontiguousarray(Yt.T)
    Yd = np.diagonal(Yt)
    for j in range(D):
        Minv, info = linalg.lapack.dpotri(so.chol[j], lower=1)
        if info != 0:
            raise np.linalg.LinAlgError("potri failed")
        aj = so.alpha[:, j]
        g = br[:, j] - d[j] * (G @ (u * aj))  # Phi^T beta_j
        Psi[:, j] = u * g
        diag_minv = np.diag(Minv)
        tvec[j] = (R - np.sum(diag_minv)) / d[j]
        # d nll / d log s_r = (1 - Minv_rr - d s_r g_r^2) / 2
        gs = 0.5 * ((1.0 - diag_minv) - d[j] * s * g * g)
        g_l += gs @ dlogs
        w = np.einsum("ab,ab->b", Minv, Yt) + np.einsum("ab,ab->a", Minv, YtT) - diag_minv * Yd
        Tv = pre.T.T @ (u * aj)  # E_k^T (u a_j) = g_k * T^T (u a_j)
        ug = u * g
        for k in range(2):
            dg = dbr[k, :, j] - d[j] * pre.g[k] * Tv
            g_P[k] += d[j] * (pre.g[k] @ w - ug @ (u * dg))
    grad[:2] = g_P
    grad[2:4] = g_l
    # B~ = L L^T: d nll / d B~ = V (diag(t) - Psi^T Psi) V^T / 2
    dB = 0.5 * V @ (np.diag(tvec) - Psi.T @ Psi) @ V.T
    dL = 2.0 * dB @ th.L
    di = np.diag_indices(D)
    dL[di] *= th.L[di]
    nL = D * (D + 1) // 2
    grad[4 : 4 + nL] = dL[np.tril_indices(D)]
    # noise: d nll / d log sigma = N D - sum_i sum_t yw_i beta_w_i
    yr = yw @ V
    ywr = yw.T @ yr  # (D, D): sum_t yw_i yr_j
    fyw = lat.FY / th.sigma[None, :]
    cross = ywr - (fyw.T @ (u[:, None] * so.alpha)) * d[None, :]  # sum_t yw_i beta_r_j
    grad[4 + nL] = N * D - np.sum(cross * V)
    return nll, grad


# --- periods from the FFT (Kabir 2025 Algorithm 1) ------------------------------------------


def _fft_peaks(t: Array, y: Array, count: int) -> list[tuple[float, float]]:
    """The ``count`` strongest local maxima (frequency Hz, magnitude) of a Hann-windowed,
    16x zero-padded FFT of one mean-removed series; the padding refines each peak's frequency
    beyond the ``1/T`` bin of the plain FFT of Algorithm 1."""
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    if len(grid) != len(t) or not np.allclose(grid, t, atol=1e-6 * dt):
        y = np.interp(grid, t, y)  # missed frames: the FFT needs a uniform grid
    yc = (y - y.mean()) * np.hanning(len(y))
    nfft = 16 * int(2 ** np.ceil(np.log2(len(y))))
    spec = np.abs(np.fft.rfft(yc, n=nfft))
    freq = np.fft.rfftfreq(nfft, dt)
    inner = (spec[1:-1] > spec[:-2]) & (spec[1:-1] >= spec[2:])
    idx = np.nonzero(inner)[0] + 1
    idx = idx[freq[idx] > 0.0]
    idx = idx[np.argsort(spec[idx])[::-1][:count]]
    return [(float(freq[i]), float(spec[i])) for i in idx]


def fft_period_guess(t: ArrayLike, Y: ArrayLike, peaks: int = 2) -> list[tuple[float, float]]:
    """Kabir 2025 Algorithm 1: candidate period pairs ``(P1, P2)`` (s), best first.

    For every output the ``peaks`` strongest FFT peaks give periods; each pair of distinct
    periods is scored by ``|P_a - P_b|`` times the sum of their magnitudes (steps 6-10), and
    the pairs are returned in decreasing score (the first is Algorithm 1's choice).
    """
    t, Y = np.asarray(t, float), np.atleast_2d(np.asarray(Y, float).T).T
    found: dict[float, float] = {}
    for j in range(Y.shape[1]):
        for f, mag in _fft_peaks(t, Y[:, j], peaks):
            P = 1.0 / f
            # "unique periods" (step 6): peaks of different outputs within 2% are one period
            key = next((k for k in found if abs(k - P) <= 0.02 * P), None)
            if key is None:
                found[P] = mag
            else:
                found[key] = max(found[key], mag)
    pairs = []
    for (Pa, ma), (Pb, mb) in itertools.combinations(found.items(), 2):
        pairs.append((abs(Pa - Pb) * (ma + mb), (max(Pa, Pb), min(Pa, Pb))))
    pairs.sort(key=lambda p: -p[0])
    return [p for _, p in pairs]


# --- training ------------------------------------------------------------------------------


@dataclass(frozen=True)
class GPFit:
    """A trained multi-output GP: hyper-parameters, training data and diagnostics.

    periods_s, lengthscales : (2,) the kernel's P1, P2 (s) and l1, l2.
    B : (D, D) output covariance (data units^2); noise_std : (D,) fitted noise (data units).
    nll : negative log marginal likelihood at the optimum.  ok : False when the model is
    judged badly trained (``reason`` says why).  train_time_s : wall time of :func:`fit_icm_gp`.
    """

    periods_s: Array
    lengthscales: Array
    B: Array
    noise_std: Array
    nll: float
    ok: bool
    reason: str
    train_time_s: float
    t_train: Array = field(repr=False)
    info: dict[str, Any] = field(default_factory=dict, repr=False)
    _theta: Array = field(repr=False, default_factory=lambda: np.zeros(0))
    _mean: Array = field(repr=False, default_factory=lambda: np.zeros(0))
    _scale: Array = field(repr=False, default_factory=lambda: np.zeros(0))
    _Y: Array = field(repr=False, default_factory=lambda: np.zeros(0))
    _rot: Array = field(repr=False, default_factory=lambda: np.zeros(0))

    def predict(self, t: ArrayLike, derivative: bool = False) -> tuple[Array, Array]:
        """Posterior mean and variance of the latent outputs at times ``t`` (s).

        Returns ``(mean, var)``, each (n, D), in data units.  With ``derivative=True`` it
        returns the mean and variance of ``dy/dt`` instead (exact derivative of the GP, an
        alternative to the finite differences of Kabir 2025 eq. 27).
        """
        with threadpool_limits(limits=1, user_api="blas"):
            return self._predict(np.asarray(t, float) - self.info["t0"], derivative)

    def _predict(self, t: Array, derivative: bool) -> tuple[Array, Array]:
        Yn = ((self._Y - self._mean) / self._scale) @ self._rot
        D = Yn.shape[1]
        th = _Theta.unpack(self._theta, D)
        feat = _Features.build(th.ell)
        lat = _lattice(self.t_train, Yn, th.periods, feat)
        G, _, _ = _gram(lat, feat, th.periods)
        s, _ = _prior_weights(feat, th.ell)
        _, so, _ = _solve(G, lat.FY, s, th, len(self.t_train))
        phi = _feature_matrix(t, feat, th.periods, derivative)  # (n, R)
        A = phi * so.u[None, :]
        mean_r = A @ so.alpha * so.d[None, :]  # (n, D) rotated, whitened
        var_r = np.empty_like(mean_r)
        for j in range(D):
            X = linalg.solve_triangular(so.chol[j], A.T, lower=True, check_finite=False)
            var_r[:, j] = so.d[j] * np.sum(X * X, axis=0)
        C = so.V.T @ self._rot.T  # rotated-whitened -> data axes
        scale = float(self._scale) * th.sigma[0]
        mean = (mean_r @ C) * scale
        var = (var_r @ C**2) * scale**2
        if not derivative:
            mean = mean + self._mean[None, :]
        return mean, var


def _feature_matrix(t: Array, feat: _Features, periods: Array, derivative: bool) -> Array:
    w = 2.0 * np.pi * (feat.n / periods[0] + feat.m / periods[1])
    ph = np.outer(t, w)
    if not derivative:
        return np.concatenate([np.cos(ph), np.sin(ph[:, 1:])], axis=1)
    return np.concatenate([-np.sin(ph) * w, (np.cos(ph) * w)[:, 1:]], axis=1)


def check_training_data(t: ArrayLike, Y: ArrayLike, min_span_s: float | None = None) -> None:
    """Reject data a GP cannot be trained on, with a message that says why (InputError)."""
    t, Y = np.asarray(t, float), np.asarray(Y, float)
    if Y.ndim != 2 or t.ndim != 1 or len(t) != len(Y):
        raise InputError(f"GP training data must be t (N,) and Y (N, D), got {t.shape}, {Y.shape}")
    if len(t) < 16:
        raise InputError(f"GP training data has {len(t)} samples; at least 16 are needed")
    if not np.all(np.isfinite(t)) or not np.all(np.isfinite(Y)):
        raise InputError(
            "GP training data contains NaN/inf (drop the missed frames and pass their times)"
        )
    if np.any(np.diff(t) <= 0):
        raise InputError("GP training times must be strictly increasing")
    if np.any(np.std(Y, axis=0) == 0.0):
        raise InputError("GP training data has a constant output; nothing to learn")
    dt = np.diff(t)
    if dt.max() > 1.5 * np.median(dt):
        warnings.warn(
            f"GP training data has gaps (largest {dt.max():.3g} s vs step {np.median(dt):.3g} s);"
            " the model uses the samples it has",
            stacklevel=2,
        )
    if min_span_s is not None and t[-1] - t[0] < min_span_s:
        raise InputError(
            f"GP training span {t[-1] - t[0]:.1f} s is shorter than one tumbling period "
            f"({min_span_s:.1f} s); the periodic kernel cannot be identified"
        )


def _initial_theta(Yn: Array, periods: tuple[float, float], noise0: float) -> Array:
    D = Yn.shape[1]
    C = np.cov(Yn.T).reshape(D, D) / noise0**2
    L = np.linalg.cholesky(C + 1e-9 * np.trace(C) / D * np.eye(D))
    return _Theta.pack(np.asarray(periods), np.array(ELL0), L, noise0)


def _noise_guess(Yn: Array) -> float:
    """Noise std from third differences (robust median; white noise passes with gain 20)."""
    d3 = np.diff(Yn, 3, axis=0)
    return float(max(np.median(np.abs(d3)) / 0.6745 / np.sqrt(20.0), 1e-9))


def _bounds(t: Array, D: int, ell_min: Array) -> list[tuple[float, float]]:
    nL = D * (D + 1) // 2
    span = t[-1] - t[0]
    b = [(np.log(2.5 * np.median(np.diff(t))), np.log(1e3 * span))] * 2  # periods
    b += [(np.log(lo), np.log(20.0)) for lo in ell_min]  # lengthscales
    for r, c in zip(*np.tril_indices(D), strict=True):  # Cholesky of the whitened B
        b.append((np.log(1e-6), np.log(1e9)) if r == c else (-1e9, 1e9))
    b.append((np.log(1e-10), np.log(10.0)))  # noise std / data scale
    assert len(b) == 4 + nL + 1
    return b


@dataclass(frozen=True)
class _Eigen:
    """For fixed periods and lengthscales: ``U G U = Q diag(lam) Q^T`` and the data in that
    basis, which make the likelihood in ``B`` and ``sigma`` an O(R D) function."""

    lam: Array  # (R,)
    C0: Array  # (R, D) Q^T (u * Phi^T Y)
    YY: Array  # (D, D) Y^T Y
    N: int

    @classmethod
    def build(cls, pre: _Prepared, Y: Array) -> _Eigen:
        u = np.sqrt(pre.s)
        lam, Q = np.linalg.eigh(u[:, None] * pre.G * u[None, :])
        return cls(np.maximum(lam, 0.0), Q.T @ (u[:, None] * pre.lat.FY), Y.T @ Y, len(Y))


def _inner_nll(x: Array, eig: _Eigen) -> tuple[float, Array]:
    """NLL and gradient in ``x = [Cholesky of the whitened B (log diagonal), log sigma]``
    at fixed periods and lengthscales (the same model as :func:`nll_and_grad`)."""
    D = eig.C0.shape[1]
    nL = D * (D + 1) // 2
    L = np.zeros((D, D))
    L[np.tril_indices(D)] = x[:nL]
    di = np.diag_indices(D)
    L[di] = np.exp(L[di])
    sig = float(np.exp(x[nL]))
    d, V = np.linalg.eigh(L @ L.T)
    d = np.maximum(d, 1e-300)
    c = eig.C0 @ V / sig
    den = 1.0 + eig.lam[:, None] * d[None, :]
    psi = c / den
    nll = (
        eig.N * D * np.log(sig)
        + 0.5 * np.trace(eig.YY) / sig**2
        - 0.5 * float(np.sum(d[None, :] * c * psi))
        + 0.5 * float(np.sum(np.log(den)))
    )
    tvec = np.sum(eig.lam[:, None] / den, axis=0)
    dB = 0.5 * V @ (np.diag(tvec) - psi.T @ psi) @ V.T
    dL = 2.0 * dB @ L
    dL[di] *= L[di]
    cross = eig.YY @ V / sig**2 - (eig.C0.T @ psi / sig) * d[None, :]
    g = np.empty_like(x)
    g[:nL] = dL[np.tril_indices(D)]
    g[nL] = eig.N * D - float(np.sum(cross * V))
    return nll, g


def _score_periods(theta0: Array, t: Array, Yn: Array) -> tuple[float, Array]:
    """The likelihood maximised over ``B`` and ``sigma`` only, at the given periods and
    lengthscales (one eigendecomposition, then O(R D) evaluations): a cheap score of a period
    pair, and the warm start of ``B`` and ``sigma`` for the full optimisation."""
    D = Yn.shape[1]
    th = _Theta.unpack(theta0, D)
    feat = _Features.build(th.ell)
    eig = _Eigen.build(_prepare(t, Yn, th, feat), Yn)
    r = optimize.minimize(
        _inner_nll,
        theta0[4:],
        args=(eig,),
        jac=True,
        method="L-BFGS-B",
        bounds=_bounds(t, D, th.ell)[4:],
        options={"maxiter": 500},
    )
    return float(r.fun), np.concatenate([theta0[:4], r.x])


def _curvature_scale(grad, x0: Array, steps: Array) -> Array:
    """Diagonal preconditioning for L-BFGS-B: ``1 / sqrt(|curvature|)`` of every coordinate,
    from forward differences of the gradient ``grad(x)`` with the given steps.  The likelihood
    is orders of magnitude stiffer in the periods (a phase error grows over the whole span)
    than in the other log-parameters."""
    g0 = grad(x0)
    curv = np.empty(len(x0))
    for k, h in enumerate(steps):
        e = np.zeros(len(x0))
        e[k] = h
        curv[k] = (grad(x0 + e)[k] - g0[k]) / h
    return 1.0 / np.sqrt(np.maximum(np.abs(curv), 1e-6))


def _refine_periods(t: Array, Yn: Array, periods: tuple[float, float]) -> tuple[float, float]:
    """Sharpen a period pair from the FFT before the full optimisation.

    Algorithm 1's periods are good to a fraction of an FFT bin (about 0.4% at T_train =
    1500 s), but over the span that is a phase error of a tenth of a radian per harmonic, which
    the likelihood at the start explains as noise (fitted noise ~300x the sensor's): L-BFGS
    then spends half of its evaluations walking the noise back down.  Here the periods alone are
    fitted first, by the same likelihood with a small fixed noise (1e-3 of the data's RMS, i.e.
    a ridge-regularised harmonic least-squares fit) and a small feature set (lengthscales
    ``ELL0``, truncation 1e-6: R ~ 80), which costs a few tens of milliseconds.
    """
    D = Yn.shape[1]
    feat = _Features.build(np.array(ELL0), eps=1e-6)
    sig = 1e-3
    theta = _Theta.pack(
        np.asarray(periods, float), np.array(ELL0), np.diag(np.std(Yn, 0) / sig), sig
    )
    x0 = theta[:2].copy()

    def fg(x: Array) -> tuple[float, Array]:
        th = theta.copy()
        th[:2] = x
        f, g = nll_and_grad(th, t, Yn, feat)
        return f, g[:2]

    scale = _curvature_scale(lambda x: fg(x)[1], x0, np.full(2, 1e-7))
    # A refinement, not a search: each frequency stays within one FFT bin (1 / span) of the
    # start (on short spans the fit could otherwise wander onto another basis of the lattice).
    lo, hi = _bounds(t, D, np.array(ELL0))[0]
    half = np.minimum(np.exp(x0) / (t[-1] - t[0]), 0.5)  # |d log P| = P |df| <= P / span
    box = np.stack([np.maximum(x0 - half, lo), np.minimum(x0 + half, hi)], axis=1)

    def fg_scaled(z: Array) -> tuple[float, Array]:
        f, g = fg(z * scale)
        return f, g * scale

    res = optimize.minimize(
        fg_scaled,
        x0 / scale,
        jac=True,
        method="L-BFGS-B",
        bounds=[(a / sc, b / sc) for (a, b), sc in zip(box, scale, strict=True)],
        options={"maxiter": 60},
    )
    P = np.exp(res.x * scale)
    return (float(P[0]), float(P[1]))


def _lbfgs_round(
    theta: Array,
    t: Array,
    Yn: Array,
    maxiter: int,
    free: NDArray[np.bool_],
    ell_min: Array,
    flat_nats: float,
    scale: Array | None = None,
    ell_floor: float = 0.25,
) -> tuple[Array, Any, int, Array, bool]:
    """One L-BFGS-B run over the ``free`` log-hyper-parameters with the feature set of
    ``ell_min``.  Returns the new theta, scipy's result, the number of evaluations, the
    preconditioning scales (``scale``: reuse them instead of estimating) and whether the run
    stopped early because the lengthscales grew enough for a much smaller feature set."""
    D = Yn.shape[1]
    feat = _Features.build(ell_min)
    bounds = [b for b, f in zip(_bounds(t, D, ell_min), free, strict=True) if f]

    def full(x: Array) -> Array:
        th = theta.copy()
        th[free] = x
        return th

    x0 = theta[free]
    nfev = 0
    if scale is None:
        steps = np.where(np.nonzero(free)[0] >= 2, 1e-4, 1e-7)  # periods are the stiff ones
        scale = _curvature_scale(lambda x: nll_and_grad(full(x), t, Yn, feat)[1][free], x0, steps)
        nfev += len(x0) + 1

    def fun(z: Array) -> tuple[float, Array]:
        f, g = nll_and_grad(full(z * scale), t, Yn, feat)
        return f, g[free] * scale

    hist: list[float] = []
    shrink = [False]
    ell_cols = [k for k, i in enumerate(np.nonzero(free)[0]) if i in (2, 3)]

    def callback(intermediate_result: optimize.OptimizeResult) -> None:
        # Stop once 10 iterations gained less than `flat_nats` of log-likelihood:
        # hyper-parameters that move it less than that are not determined by the data.
        hist.append(float(intermediate_result.fun))
        if len(hist) > 10 and hist[-11] - hist[-1] < flat_nats:
            raise StopIteration
        # The cost of an evaluation grows as R^3: once the lengthscales have grown so far
        # that the feature set for them is 30% smaller, stop and continue with that one.
        if len(hist) >= 5 and len(ell_cols) == 2:
            ell = np.exp(intermediate_result.x[ell_cols] * scale[ell_cols])
            smaller = _Features.build(np.maximum(ELL_MARGIN * ell, ell_floor))
            if smaller.R <= SHRINK * feat.R:
                shrink[0] = True
                raise StopIteration

    res = optimize.minimize(
        fun,
        x0 / scale,
        jac=True,
        method="L-BFGS-B",
        bounds=[(lo / sc, hi / sc) for (lo, hi), sc in zip(bounds, scale, strict=True)],
        options={"maxiter": maxiter, "ftol": 1e-15, "gtol": 1e-8},
        callback=callback,
    )
    return full(res.x * scale), res, nfev + int(res.nfev), scale, shrink[0]


def _optimise(
    theta0: Array,
    t: Array,
    Yn: Array,
    maxiter: int,
    free: NDArray[np.bool_] | None = None,
    ell_floor: float = 0.25,
    flat_nats: float = 0.05,
) -> tuple[Array, float, int, Any]:
    """L-BFGS-B over the ``free`` log-hyper-parameters (the others stay at ``theta0``); the
    feature set is re-built (and the optimisation continued) if the lengthscales shrink to
    its truncation level, or grow enough for a much smaller (cheaper) one."""
    theta = theta0.copy()
    free = np.ones(len(theta), bool) if free is None else free
    nfev = 0
    res = None
    scale = None
    for _ in range(8):
        ell_min = np.maximum(ELL_MARGIN * np.exp(theta[2:4]), ell_floor)
        theta, res, n, scale, shrunk = _lbfgs_round(
            theta, t, Yn, maxiter, free, ell_min, flat_nats, scale, ell_floor
        )
        nfev += n
        at_floor = np.isclose(theta[2:4], np.log(ell_min), atol=1e-6) & (
            ell_min > ell_floor * 1.0001
        )
        if not (shrunk or (free[2:4] & at_floor).any()):
            break
        if not shrunk:
            scale = None  # the lengthscales hit the truncation level: estimate afresh
    assert res is not None
    return theta, float(res.fun), nfev, res


def _staged(th0: Array, t: Array, Yn: Array, maxiter: int) -> tuple[Array, float, int, Any]:
    """Stage 1: B diagonal in the principal-component basis (outputs independent, sharing the
    kernel): few, well-scaled parameters.  Stage 2: the full ICM from there."""
    D = Yn.shape[1]
    nL = D * (D + 1) // 2
    diag_only = np.ones(4 + nL + 1, bool)
    offdiag = [4 + i for i, (r, c) in enumerate(zip(*np.tril_indices(D), strict=True)) if r != c]
    diag_only[offdiag] = False
    th1 = th0.copy()
    _, th1 = _score_periods(th1, t, Yn)  # B and sigma at their optimum for the start periods
    th1[offdiag] = 0.0
    th1, _, n1, _ = _optimise(th1, t, Yn, maxiter=maxiter, free=diag_only, flat_nats=FLAT1)
    theta, nll, n2, res = _optimise(th1, t, Yn, maxiter=maxiter)
    return theta, nll, n1 + n2, res


def fit_icm_gp(
    t: ArrayLike,
    Y: ArrayLike,
    *,
    periods_init: tuple[float, float] | None = None,
    candidates: int = 4,
    sensor_noise_std: ArrayLike | None = None,
    min_span_s: float | None = None,
    maxiter: int = 300,
) -> GPFit:
    """Train the ICM GP of Kabir 2025 Sec. 2.3 on ``Y`` (N, D) sampled at ``t`` (N,) s.

    Parameters
    ----------
    periods_init : (P1, P2), optional
        Initial periods (s); by default from Kabir 2025 Algorithm 1 (:func:`fft_period_guess`).
    candidates : int
        How many period pairs (Algorithm 1's best ones, each also tried with the pair
        re-expressed on the same frequency lattice) are scored by a short optimisation before
        the full one: the global step over the periods.  1 reproduces the paper's single start.
    sensor_noise_std : (D,) or float, optional
        The sensor's noise (data units).  If given, a model whose fitted noise exceeds it by
        more than 50% is flagged ``ok=False``: it explains signal as noise, i.e. it is badly
        trained.
    min_span_s : float, optional
        Shortest acceptable training span (e.g. one tumbling period); shorter data is refused.
    """
    # One BLAS thread: the matrices are a few hundred wide, where OpenBLAS threading costs more
    # than it gains (2x slower measured on 2 cores); parallelism is across features/runs.
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit(t, Y, periods_init, candidates, sensor_noise_std, min_span_s, maxiter)


def _fit(t, Y, periods_init, candidates, sensor_noise_std, min_span_s, maxiter) -> GPFit:
    t0 = time.perf_counter()
    t, Y = np.asarray(t, float), np.asarray(Y, float)
    check_training_data(t, Y, min_span_s)
    N, D = Y.shape
    mean = Y.mean(axis=0)
    scale = float(np.sqrt(np.mean((Y - mean) ** 2)))
    _, rot_ = np.linalg.eigh(np.cov(((Y - mean) / scale).T).reshape(D, D))
    rot_ = rot_[:, ::-1]  # largest variance first: the Cholesky factor of B is then well scaled
    Yn = ((Y - mean) / scale) @ rot_  # principal components, common scale
    tc = t - t[0]  # origin at the first sample: keeps the phases well conditioned
    noise0 = _noise_guess(Yn)
    starts: list[tuple[float, float]]
    if periods_init is not None:
        P1_init, P2_init = periods_init
        starts = [(float(P1_init), float(P2_init))]
    else:
        starts = []
        for P1, P2 in fft_period_guess(tc, Yn)[: max(candidates, 1)]:
            starts.append((P1, P2))
            # the same lattice, other basis: (f1, f2) -> (f1, f2 - f1) and (f1, f2 + f1)
            if candidates > 1:
                f1, f2 = 1.0 / P1, 1.0 / P2
                for g in (f2 - f1, f2 + f1):
                    if g > 0 and abs(g - f1) > 1e-6:
                        starts.append((1.0 / min(f1, g), 1.0 / max(f1, g)))
        if not starts:
            raise InputError("no periodicity found in the GP training data (flat spectrum)")
    # Multi-start on failure: Algorithm 1's pair first (the paper's single start); the next
    # candidates only if the fit explains signal as noise (fitted noise > 1.5x the reference:
    # the sensor's noise if given, else the white-noise level of the data's third differences).
    ref = (
        np.max(np.asarray(sensor_noise_std, float)) / scale
        if sensor_noise_std is not None
        else noise0
    )
    tries: list[dict[str, Any]] = []
    best: tuple[float, Array, Any] | None = None
    nfev = 0
    for P in starts[: max(candidates, 1) * 3]:
        try:
            P_fit = _refine_periods(tc, Yn, P)
            th_, nll_, n_, res_ = _staged(_initial_theta(Yn, P_fit, noise0), tc, Yn, maxiter)
        except (linalg.LinAlgError, np.linalg.LinAlgError, FloatingPointError) as exc:
            tries.append({"start_periods_s": list(P), "error": str(exc)})
            continue
        nfev += n_
        noise_ratio = float(np.exp(th_[-1]) / ref)
        tries.append(
            {
                "start_periods_s": list(P),
                "refined_periods_s": list(P_fit),
                "nll": nll_,
                "noise_ratio": noise_ratio,
            }
        )
        if best is None or nll_ < best[0]:
            best = (nll_, th_, res_)
        if noise_ratio <= 1.5:
            break
    if best is None:
        raise InputError(
            f"GP training failed from every start ({len(tries)}): {tries[-1].get('error')}"
        )
    nll, theta, res = best
    th = _Theta.unpack(theta, D)
    noise_std = th.sigma * scale
    B = rot_ @ (th.L @ th.L.T) @ rot_.T * (th.sigma[0] * scale) ** 2
    ok, reason = True, ""
    ratio = float(th.sigma[0] / ref)
    if not np.isfinite(nll):
        ok, reason = False, "likelihood is not finite"
    elif tc[-1] < float(th.periods.max()):
        ok = False
        reason = (
            f"training span {tc[-1]:.0f} s is shorter than the fitted long period "
            f"{th.periods.max():.0f} s: the periodic kernel is not identified"
        )
    elif ratio > 1.5:
        ok = False
        what = "sensor" if sensor_noise_std is not None else "data's white"
        reason = (
            f"fitted noise is {ratio:.1f}x the {what} noise after {len(tries)} start(s): the "
            "model explains signal as noise (badly trained)"
        )
    return GPFit(
        periods_s=th.periods.copy(),
        lengthscales=th.ell.copy(),
        B=B,
        noise_std=noise_std,
        nll=nll,
        ok=ok,
        reason=reason,
        train_time_s=time.perf_counter() - t0,
        t_train=tc,
        info={
            "starts": tries,
            "nfev": nfev,
            "message": str(res.message),
            "t0": float(t[0]),
        },
        _theta=theta,
        _mean=mean,
        _scale=np.array(scale),
        _rot=rot_,
        _Y=Y,
    )
