"""The exact negative log marginal likelihood of the ICM GP and its gradient through the\nlattice's Woodbury identity (Kabir 2025 eq. 11)."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg

from tumblenav.estimators.kabir2025.gp import compiled
from tumblenav.estimators.kabir2025.gp.kernel import (
    _Features,
    _gram,
    _Lattice,
    _lattice,
    _prior_weights,
)

Array = NDArray[np.float64]


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


def _factor(G: Array, u: Array, dj: float) -> Array:
    """Lower Cholesky factor (Fortran order, zeros above) of ``M = I + d_j U G U``: ``M``'s
    lower triangle is written in place for ``potrf`` (no temporaries, no copy: the same LAPACK
    call on the same numbers as ``scipy.linalg.cholesky``); on failure,
    :func:`_cholesky_jittered` of the full ``M``."""
    R = len(u)
    M = compiled.lower_system(G, u, dj, np.empty((R, R), order="F"))
    c, info = linalg.lapack.dpotrf(M, lower=1, clean=1, overwrite_a=1)
    if info == 0:
        return cast(Array, c)
    if info < 0:
        raise ValueError(f"LAPACK reported an illegal value in argument {-info} of potrf")
    M = (u[:, None] * G * u[None, :]) * dj
    M[np.diag_indices_from(M)] += 1.0
    return _cholesky_jittered(M)


def _solve(G: Array, FY: Array, s: Array, th: _Theta, N: int) -> tuple[float, _Solve, Array]:
    D = FY.shape[1]
    Bt = th.L @ th.L.T
    d, V = np.linalg.eigh(Bt)
    d = np.maximum(d, 1e-300)
    u = np.sqrt(s)
    br = (FY / th.sigma[None, :]) @ V  # (R, D) Phi^T Yr
    chol, alpha, nll = [], np.empty_like(br), N * float(np.sum(np.log(th.sigma)))
    quad = np.empty(D)
    for j in range(D):
        c = _factor(G, u, float(d[j]))  # M_j = I + d_j H, H = U G U
        ub = u * br[:, j]
        alpha[:, j], info = linalg.lapack.dpotrs(c, ub, lower=1)  # scipy's cho_solve
        if info != 0:
            raise ValueError(f"LAPACK reported an illegal value in argument {-info} of potrs")
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


class _Objective:
    """:func:`nll_and_grad` on one data set ``(t, Y)``, remembering its last evaluations: the
    optimisation returns to points it has evaluated (a line search's last point, a round
    starting where the previous stopped), and the lattice and Gram matrix depend on the
    periods only, the prior weights on the lengthscales only (the preconditioning's finite
    differences in the other parameters share them).  Bit for bit :func:`nll_and_grad`'s
    results (the same computation on the same numbers, or its stored output)."""

    def __init__(self, t: Array, Y: Array, results: int = 32, prepared: int = 4) -> None:
        self.t, self.Y = np.asarray(t, float), np.asarray(Y, float)
        # how many evaluations (a few numbers each) and lattices (a few R x R arrays each)
        # are kept: the repeats come within ~20 evaluations, the shared periods in a row
        self.sizes = {"results": results, "prepared": prepared}
        # key -> (feat, value): the feature set is held so that its id is not reused
        self._results: OrderedDict[tuple[bytes, int], tuple[_Features, float, Array]] = (
            OrderedDict()
        )
        self._gram: OrderedDict[tuple[bytes, int], tuple[_Features, Any]] = OrderedDict()
        self._prior: OrderedDict[tuple[bytes, int], tuple[_Features, Any]] = OrderedDict()

    def _remember(self, store: OrderedDict, key: Any, value: Any) -> None:
        store[key] = value
        if len(store) > self.sizes["results" if store is self._results else "prepared"]:
            store.popitem(last=False)

    def __call__(self, theta: Array, feat: _Features) -> tuple[float, Array]:
        theta = np.asarray(theta, float)
        key = (theta.tobytes(), id(feat))
        hit = self._results.get(key)
        if hit is not None:
            self._results.move_to_end(key)
            return hit[1], hit[2].copy()
        D = self.Y.shape[1]
        th = _Theta.unpack(theta, D)
        kp = (th.periods.tobytes(), id(feat))
        lg = self._gram.get(kp)
        if lg is None:
            lat = _lattice(self.t, self.Y, th.periods, feat)
            lg = (feat, (lat, *_gram(lat, feat, th.periods)))
            self._remember(self._gram, kp, lg)
        kl = (th.ell.tobytes(), id(feat))
        sw = self._prior.get(kl)
        if sw is None:
            sw = (feat, _prior_weights(feat, th.ell))
            self._remember(self._prior, kl, sw)
        pre = _Prepared(*lg[1], *sw[1])
        f, g = _nll_grad(pre, th, self.Y, len(theta))
        self._remember(self._results, key, (feat, f, g.copy()))
        return f, g


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
    # w = colsum(Minv_low * Y) + rowsum(Minv_low * Y^T) - diag(Minv) diag(Y)
    # (compiled.trace_weights: numpy's sums, in their order, without forming Y).
    TT = np.ascontiguousarray(pre.T.T)
    for j in range(D):
        # in place: the factor is not needed after (Fortran order: no copy either)
        Minv, info = linalg.lapack.dpotri(so.chol[j], lower=1, overwrite_c=1)
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
        w = compiled.trace_weights(Minv, pre.T, TT, u, diag_minv)
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
