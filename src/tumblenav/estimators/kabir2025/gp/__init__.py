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

import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from tumblenav.estimators.kabir2025.gp.fit import (  # noqa: F401
    GPFit,
    _bounds,
    _curvature_scale,
    _Eigen,
    _feature_matrix,
    _fit,
    _initial_theta,
    _inner_nll,
    _lbfgs_round,
    _noise_guess,
    _optimise,
    _refine_periods,
    _score_periods,
    _staged,
    check_training_data,
)

# every name of the submodules, as when this was one module
from tumblenav.estimators.kabir2025.gp.kernel import (  # noqa: F401
    ELL0,
    ELL_MARGIN,
    FLAT1,
    SHRINK,
    TRUNCATION,
    _Features,
    _gram,
    _Lattice,
    _lattice,
    _order,
    _phases,
    _prior_weights,
    kernel,
)
from tumblenav.estimators.kabir2025.gp.likelihood import (  # noqa: F401
    _cholesky_jittered,
    _factor,
    _nll_grad,
    _Objective,
    _prepare,
    _Prepared,
    _Solve,
    _solve,
    _Theta,
    nll_and_grad,
)
from tumblenav.estimators.kabir2025.gp.periods import (  # noqa: F401
    _fft_peaks,
    fft_period_guess,
)

__all__ = ["GPFit", "fft_period_guess", "fit_icm_gp", "kernel", "nll_and_grad"]

Array = NDArray[np.float64]


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
