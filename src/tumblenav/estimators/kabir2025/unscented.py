"""The scaled unscented transform (Julier 2002; Kabir 2025 Sec. 3.2) with a guarded square root."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, cast

import numpy as np
from numpy.typing import NDArray

from tumblenav.errors import InputError

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


@dataclass(frozen=True)
class _Unscented:
    """Scaled unscented transform (Julier 2002; Kabir 2025 Sec. 3.2 alpha, beta, kappa)."""

    Wm: Array  # (2n+1,)
    Wc: Array
    c: float  # sqrt(n + lambda)

    @classmethod
    def make(cls, n: int, alpha: float, beta: float, kappa: float) -> _Unscented:
        lam = alpha**2 * (n + kappa) - n
        if not n + lam > 0:
            raise InputError("estimator.tuning: alpha^2 (n + kappa) must be positive")
        Wm = np.full(2 * n + 1, 0.5 / (n + lam))
        Wm[0] = lam / (n + lam)
        Wc = Wm.copy()
        Wc[0] += 1.0 - alpha**2 + beta
        return cls(Wm=Wm, Wc=Wc, c=float(np.sqrt(n + lam)))

    def offsets(self, P: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Sigma-point offsets (B, 2n+1, n): 0, +c columns of sqrt(P), -c columns; and the
        runs whose covariance needed a repair (see :func:`_sqrt_psd`)."""
        L, repaired = _sqrt_psd(P)
        Lt = self.c * np.swapaxes(L, -1, -2)
        return np.concatenate([np.zeros_like(Lt[:, :1]), Lt, -Lt], axis=1), repaired

    def cov(self, A: Array, B_: Array) -> Array:
        """``sum_i Wc_i A_i B_i^T`` for (B, S, a), (B, S, b) -> (B, a, b)."""
        return np.swapaxes(A * self.Wc[:, None], -1, -2) @ B_


def _sqrt_psd(P: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Square roots ``L L^T = P`` of (B, n, n): Cholesky, or for a run where that fails the
    symmetric square root with eigenvalues clipped at 1e-15 of the largest (the negative
    zeroth weight of the scaled transform can leave a slightly indefinite covariance); NaN for
    a run whose P is not finite.  Returns also which runs were repaired."""
    try:
        # cast: numpy's stubs type linalg results of float input as floating[Any] (float64 here)
        return cast(Array, np.linalg.cholesky(P)), np.zeros(P.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    L = np.full_like(P, np.nan)
    repaired = np.zeros(P.shape[0], dtype=bool)
    for b in range(P.shape[0]):
        if not np.all(np.isfinite(P[b])):
            continue
        try:
            L[b] = np.linalg.cholesky(P[b])
        except np.linalg.LinAlgError:
            lam, V = np.linalg.eigh(0.5 * (P[b] + P[b].T))
            lam = np.maximum(lam, 1e-15 * np.abs(lam).max())
            L[b] = V * np.sqrt(lam)
            repaired[b] = True
    return L, repaired
