"""The rate of G from its attitudes: local line and line-plus-cubic fits with their covariance\n(Hu 2024 eq. 6-9, beyond the paper: the fit's choice and its bias)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends import _points_kernel
from tumblenav.frontends.stereo_points.gls import fit_coefficients

Array = NDArray[np.float64]


def rates_and_covariance(
    R_GI: Array,
    cov_G: Array,
    dt: float,
    h: int,
    bias_epochs: int = 100,
    unbiased: bool | NDArray[np.bool_] = False,
    details: dict | None = None,
) -> tuple[Array, Array, Array]:
    """Rate of G w.r.t. I in G (B,n,3) and its covariance (B,n,3,3), from the G attitudes.

    Hu 2024 eq. 15-16 take a numerical derivative. Here the rotation vectors
    ``phi_j = log(R_GI(k+j) R_GI(k)^T) = -omega j dt + O(j^3)`` over ``j = -h..h`` are fitted
    by least squares, symmetric so that the second-order term cancels, with two models:

    * a line: variance ``sigma^2 / (dt^2 sum_j j^2)`` for attitudes of covariance
      ``sigma^2`` (the errors of the ``2h`` attitudes enter once each; the centre's cancels),
      but biased by the third-order term, ``omega'' h^2 dt^2 / 10`` in order of magnitude:
      about 5e-4 rad/s for this tumble at h = 10;
    * a line plus a cubic term: no third-order bias, 2.5 times the standard deviation.

    Beyond the paper: the symmetric fits' difference ``d = omega_line - omega_cubic``
    estimates the line's bias (its covariance is the difference of the two variances, the
    fits being nested); its square, less that variance, averaged over the last
    ``bias_epochs`` epochs, is the bias's mean square. Each epoch uses the fit with the
    smaller expected mean square error: the cubic one where the attitudes are precise (near
    range, where the bias dominates by a factor 10), the line where they are noisy, with the
    bias's mean square added to its covariance. The fit's variance sums each attitude's
    covariance with its coefficient squared (``_window_sum``; before issue 18's twenty-fourth
    session the centre's was taken for the whole window, which at a change of the visible
    features, where G's covariance grows twentyfold from one epoch to the next, stated the
    rates of the epochs before it far too precise: hu_selfocc run 96, 94.5 s, rate errors up
    to 0.12 rad/s at up to 3400 times their stated variance entered the inertia least
    squares at full weight and moved its moments by 0.025).

    ``unbiased`` (bool or (B,)): the cubic fit wherever it exists, in those runs (the rows of
    a growing least-squares batch: there the noise averages out but the line's bias does
    not; ``process`` uses it after the template's last refinement).

    Returns the rate, the covariance of the fit's noise (the ``2h`` attitudes other than
    the centre's) and the full covariance, which adds the centre attitude's part: every
    ``phi_j`` is taken relative to ``R_GI(k)``, whose error ``psi`` enters turned by
    ``j dt omega``, which leaves ``-[omega x] psi`` in the slope (``[omega x] cov_G [omega
    x]^T``; a fifth of the line's variance for this tumble). NaN unless all ``2h + 1``
    epochs have a G attitude. ``details``, if given, receives ``cubic`` (B,n), the epochs
    that took the cubic fit, and ``bias_cov`` (B,n,3,3), the line's bias allowance in the
    covariance (zero for the cubic fit): the inertia least squares' correlation model
    (``gls``)."""
    q = _quats(_finite_or_identity(R_GI))
    valid = np.all(np.isfinite(R_GI), axis=(-1, -2))
    # phi_j = log(q(k+j) (x) conj(q(k))), j = -h..h (compiled loop)
    om_l, om_c = _points_kernel.rate_fit(q, valid, h, dt)
    good = np.all(np.isfinite(om_l), axis=-1) & np.all(np.isfinite(cov_G), axis=(-1, -2))
    C = np.nan_to_num(cov_G) / dt**2
    cl, cc = fit_coefficients(h)
    Cl = np.where(good[..., None, None], _window_sum(C, cl**2), 0.0)  # the line's variance
    Cc = np.where(good[..., None, None], _window_sum(C, cc**2), 0.0)  # the cubic's
    # the nested fits' difference: its variance
    var_diff = np.diagonal(_window_sum(C, (cl - cc) ** 2), axis1=-2, axis2=-1)  # (B,n,3)
    var_diff = np.where(good[..., None], var_diff, 0.0)
    d2 = np.where(good[..., None], np.nan_to_num((om_l - om_c) ** 2 - var_diff), 0.0)
    # trailing mean over the last `bias_epochs` epochs with a rate (causal)
    cs = np.cumsum(np.concatenate([np.zeros_like(d2[:, :1]), d2], 1), axis=1)
    cn = np.cumsum(np.concatenate([np.zeros_like(good[:, :1], int), good], 1), axis=1)
    n = d2.shape[1]
    lo = np.maximum(np.arange(n) + 1 - bias_epochs, 0)
    hi = np.arange(n) + 1
    cnt = np.maximum(cn[:, hi] - cn[:, lo], 1)
    b2 = np.maximum((cs[:, hi] - cs[:, lo]) / cnt[..., None], 0.0)
    cubic = (np.sum(b2, -1) > np.trace(Cc - Cl, axis1=-2, axis2=-1)) & np.all(np.isfinite(om_c), -1)
    # per run (B,): the cubic fit wherever it exists
    unb = np.broadcast_to(np.asarray(unbiased, dtype=bool), good.shape[:1])[:, None]
    cubic = np.where(unb, np.all(np.isfinite(om_c), -1), cubic)
    omega = np.where(cubic[..., None], om_c, om_l)
    eye = np.eye(3)
    cov = np.where(cubic[..., None, None], Cc, Cl + b2[..., None] * eye)
    omega = np.where(good[..., None], omega, np.nan)
    cov = np.where(good[..., None, None], cov, np.nan)
    if details is not None:
        details["cubic"] = cubic & good
        details["bias_cov"] = np.where((good & ~cubic)[..., None, None], b2[..., None] * eye, 0.0)
    wx = _skew(np.nan_to_num(omega))
    return omega, cov, cov + wx @ np.nan_to_num(cov_G) @ np.swapaxes(wx, -1, -2)


def rates_noise_cov(cov_G_noise: Array, cubic: NDArray[np.bool_], dt: float, h: int) -> Array:
    """The covariance of the rate fit's noise (as ``rates_and_covariance``'s second output,
    the fit ``cubic`` (B,n) chose at each epoch) from the G attitudes' covariance share that
    is independent between epochs, the points' own noise (``photogrammetric_frames``'
    ``cov_G_noise``), without the line's bias allowance: the rates' zero-mean noise.

    Why (issue 18): the G attitudes' covariance also holds the template's errors, stated
    conservatively (bounded by their trace) and fixed in G, so they turn into rate errors
    only as the view changes. Propagated as if independent between epochs they made the
    rates' stated noise 1.3-2 times its variance against the truth on ordinary hu_selfocc
    runs and 3-6 times on run 173 (docs/results/consistency/prototype/hu_rate_errors.py),
    and the inertia least squares'
    errors-in-variables compensation, which takes that noise as the regressors', took away
    more than all of the information along one direction (``inertia_ls``)."""
    C = np.nan_to_num(cov_G_noise) / dt**2
    cl, cc = fit_coefficients(h)
    return np.where(cubic[..., None, None], _window_sum(C, cc**2), _window_sum(C, cl**2))


def _window_sum(C: Array, w: Array) -> Array:
    """``sum_i w_i C[:, k - h + i]`` at every epoch k (B,n,...), ``w`` of length ``2h + 1``;
    epochs beyond the ends count as zero (the rates there are NaN anyway)."""
    h = (len(w) - 1) // 2
    n = C.shape[1]
    out = np.zeros_like(C)
    for i, wi in enumerate(w):
        if wi == 0.0:
            continue
        o = i - h  # the attitude of epoch k + o
        if o >= 0:
            out[:, : n - o] += wi * C[:, o:]
        else:
            out[:, -o:] += wi * C[:, : n + o]
    return out


def _skew(v: Array) -> Array:
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def _quats(R: Array) -> Array:
    """Quaternions of a stack of rotation matrices (products of rotations, so orthogonal):
    compiled Shepperd conversion, the same as :func:`tumblenav.rotations.matrix_to_quat`."""
    R = np.ascontiguousarray(R, dtype=float)
    return _points_kernel.matrix_to_quat(R.reshape(-1, 3, 3)).reshape(R.shape[:-2] + (4,))


def _finite_or_identity(R: Array) -> Array:
    """Rotation stacks with the unavailable (non-finite) entries replaced by the identity."""
    bad = ~np.all(np.isfinite(R), axis=(-1, -2))
    return np.where(bad[..., None, None], np.eye(3), R)


def _fit_factors(h: int) -> tuple[float, float, float]:
    """For the slope fits over ``j = -h..h``: the variance factors ``sum_j c_j^2`` of the
    linear and the linear-plus-cubic fit (the slope's variance is that times
    ``sigma_psi^2 / dt^2``) and the (-dimensionless) bias of the linear fit per unit cubic
    coefficient, ``sum_j c_j j^3`` (from :func:`gls.fit_coefficients`; the fits themselves
    now weight each attitude's covariance, ``_window_sum``)."""
    j = np.arange(-h, h + 1, dtype=float)
    cl, cc = fit_coefficients(h)
    return float(np.sum(cl**2)), float(np.sum(cc**2)), float(np.sum(cl * j**3))
