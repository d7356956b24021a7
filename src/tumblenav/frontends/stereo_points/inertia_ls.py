"""The inertia least squares on the rates of G (Hu 2024 eq. 10-16) and the DPACF frame from\nits solution (eq. 17)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from tumblenav.frontends import _points_kernel
from tumblenav.frontends.inertia import inertia_design, principal_frame
from tumblenav.frontends.stereo_points import gls
from tumblenav.frontends.stereo_points.rates import _finite_or_identity, _quats
from tumblenav.frontends.stereo_points.settings import FrontEndSettings

Array = NDArray[np.float64]

# the compiled sums (numba's dispatcher types its call with a fixed arity)
_gls_sums: Any = gls.gls_sums_at


def _inertia_from_l(l: Array) -> Array:
    """Normalised inertia in G from l = [Iyy, Izz, Ixy, Ixz, Iyz] (Ixx = 1), Hu 2024 eq. 9."""
    one = np.ones(l.shape[:-1])
    return np.stack(
        [
            np.stack([one, l[..., 2], l[..., 3]], -1),
            np.stack([l[..., 2], l[..., 0], l[..., 4]], -1),
            np.stack([l[..., 3], l[..., 4], l[..., 1]], -1),
        ],
        -2,
    )


_E = np.zeros((5, 3, 3))  # d I_G / d l_j


_E[0, 1, 1] = _E[1, 2, 2] = 1.0


_E[2, 0, 1] = _E[2, 1, 0] = 1.0


_E[3, 0, 2] = _E[3, 2, 0] = 1.0


_E[4, 1, 2] = _E[4, 2, 1] = 1.0


def identify_and_dpacf(
    omega_G: Array,
    var_w: Array,
    R_GI: Array,
    cov_G: Array,
    s: FrontEndSettings,
    delay: int = 0,
    cov_w: Array | None = None,
    R_GI_report: Array | None = None,
    before: list[tuple] | None = None,
    fit: dict | None = None,
    dt: float = 1.0,
    cov_G_rows: Array | None = None,
    cov_w_noise: Array | None = None,
) -> tuple[Array, Array, Array, Array, Array, Array, Array]:
    """Growing-batch weighted least squares (Hu 2024 eq. 13-14), DPACF (eq. 17) and the
    attitude measurement q_TI = q_TG (x) q_GI (eq. 31) with its covariance; last, the
    covariance of the inertia ratios (eq. 19). With the covariances of the rates' fit noise
    ``cov_w`` (B,n,3,3) the least squares is generalised (rows whitened), else weighted by
    ``1 / var_w``. ``R_GI_report``: the G attitudes of the attitude measurement, if not
    ``R_GI``. ``before``: a list of ``(omega, var_w, R_GI, cov_w, k_from, k_to[, fit,
    cov_G])``, the rows of the first epochs (as many as given) as they were between two of
    the template's refinements: the solutions at epochs ``k_from <= k < k_to`` ((B,) each)
    use these rows instead of the main ones.

    The rows' noise and the momentum's random walk under the scenario's disturbance torque
    (``s.q_r``) are modelled as in :mod:`~tumblenav.frontends.stereo_points.gls`: ``fit``
    (``rates_and_covariance``'s ``details``, the rate fit chosen at each epoch) and ``cov_G``
    (``cov_G_rows``: the G attitudes' covariance of the rows' version, if not ``cov_G``) give the rates' correlation over
    ``dt``-spaced epochs; without ``fit``, every epoch is taken as the cubic fit.
    ``cov_w_noise`` (B,n,3,3): the rates' zero-mean noise (``rates.rates_noise_cov``), what the
    errors-in-variables compensation takes as the regressors' (else ``cov_w``; ``before``'s
    items may carry theirs ninth)."""
    B, n = omega_G.shape[:2]
    # The identification is re-solved every `ls_every` epochs and held in between (the
    # attitude measurement still uses the G attitude of every epoch).
    held = (np.arange(n) // s.ls_every) * s.ls_every
    sel = np.unique(held)
    cG_rows = cov_G if cov_G_rows is None else cov_G_rows
    rows = _gls_rows(omega_G, var_w, R_GI, cov_w, cG_rows, fit, s, dt, cov_w_noise)
    N, r, bb, cnt, V, E, Nc, rc, M, Ew, Sw = _version_sums(rows, omega_G, R_GI, s, dt, delay, sel)
    for item in before or []:
        om_o, var_o, R_o, cw_o, k_from, k_to = item[:6]
        fit_o = item[6] if len(item) > 6 else None
        cG_o = item[7] if len(item) > 7 else cov_G
        cn_o = item[8] if len(item) > 8 else None
        # the solutions between two refinements: the sums of the rows as they were then
        m = min(int(k_to.max()), n)
        early = sel < m
        if not early.any():
            continue
        sub = None if fit_o is None else {k: v[:, :m] for k, v in fit_o.items()}
        rows_o = _gls_rows(om_o[:, :m], var_o[:, :m], R_o[:, :m],
                           None if cw_o is None else cw_o[:, :m], cG_o[:, :m], sub, s, dt,
                           None if cn_o is None else cn_o[:, :m])  # fmt: skip
        se = sel[early]
        # the sums of a solution before k_to cover epochs up to k_to - h - 1 < m only
        so = _version_sums(rows_o, om_o[:, :m], R_o[:, :m], s, dt, delay, se)
        use = (se[None, :] >= k_from[:, None]) & (se[None, :] < k_to[:, None])  # (B, S_early)
        for full, part in zip((N, r, bb, cnt, V, E, Nc, rc, M, Ew, Sw), so, strict=True):
            u = use.reshape(use.shape + (1,) * (part.ndim - 2))
            full[:, early] = np.where(u, part, full[:, early])
    return _solve_and_dpacf(N, r, bb, cnt, sel, held, s,
                            R_GI if R_GI_report is None else R_GI_report, cov_G, V, E,
                            Nc, rc, M, Ew, Sw)  # fmt: skip


def _version_sums(rows, omega_G, R_GI, s, dt, delay, sel):
    """The sums of one version's rows at epochs ``sel`` (``gls.gls_sums_at``): N, r, bb,
    cnt, V, E, Nc, rc, M, Ew, Sw. Causality: the rate at epoch j uses attitudes up to j + h, so
    epoch k may only use the sums up to k - delay (compiled loop)."""
    n = omega_G.shape[1]
    N, r, _, cnt = _points_kernel.normal_equations_at(
        rows[0], rows[1], rows[2].astype(float), rows[2], delay, sel
    )
    # The noise model needs the normalised inertia (gls): each row takes the latest one
    # solved from these rows by then (the rows before the first one take the first: they
    # enter no solution before it)
    I_sel, lam1 = _inertia_at(N, r, cnt, s)
    at = np.maximum(np.searchsorted(sel, np.arange(n) + delay, "right") - 1, 0)
    q_step = s.q_r * dt * lam1[:, at] ** 2
    out = _gls_sums(*rows, _with_rate(I_sel[:, at], omega_G), np.ascontiguousarray(R_GI),
                    delay, sel, q_step)  # fmt: skip
    return out[:8] + out[9:]


def _with_rate(I_row, omega):
    """(B,n,4,3): the normalised inertia with the rate below it (gls.gls_sums_at's Ibar)."""
    return np.ascontiguousarray(np.concatenate([I_row, np.nan_to_num(omega)[..., None, :]], -2))


def _gls_rows(omega_G, var_w, R_GI, cov_w, cov_G, fit, s, dt, cov_noise=None):
    """The arguments of :func:`gls.gls_sums_at` before ``Ibar``: whitened rows, their
    whitening, the attitudes' covariance, the rate fit's coefficients, its independent
    part and the rates' zero-mean noise (``cov_noise``, else the whitening's)."""
    B, n = omega_G.shape[:2]
    h = s.rate_half_window
    a, b, w, ok = _ls_rows(omega_G, var_w, R_GI, cov_w)
    if cov_w is None:  # weighted rows: scale them to unit weight
        sw = np.sqrt(w)
        a = a * sw[..., None, None]
        b = b * sw[..., None]
        Linv = sw[..., None, None] * np.eye(3)
        Cn = np.nan_to_num(var_w)[..., None, None] * np.eye(3)
    else:
        ok = ok.copy()
        Linv = gls.whitening(np.ascontiguousarray(np.nan_to_num(cov_w)), ok)
        Cn = np.nan_to_num(cov_w)
    if cov_noise is not None:
        Cn = np.nan_to_num(cov_noise)
    cl, cc = gls.fit_coefficients(h)
    cubic = np.ones((B, n), bool) if fit is None else fit["cubic"]
    # the rate's noise from the attitudes: -sum_i c_i psi_{j+i} / dt (rates_and_covariance)
    coef = -np.where(cubic[..., None], cc, cl) / dt
    extra = np.zeros((B, n, 3, 3)) if fit is None else np.nan_to_num(fit["bias_cov"])
    S = np.ascontiguousarray(np.nan_to_num(cov_G))
    return (np.ascontiguousarray(a), np.ascontiguousarray(b), ok, np.ascontiguousarray(Linv),
            S, np.ascontiguousarray(coef), np.ascontiguousarray(extra),
            np.ascontiguousarray(Cn, dtype=float))  # fmt: skip


def _inertia_at(N, r, cnt, s):
    """The normalised inertia (B,S,3,3) solved from the sums and its largest eigenvalue
    (B,S), where solvable; the runs' first such values before it, the identity where none."""
    d = np.sqrt(np.maximum(np.diagonal(N, axis1=-2, axis2=-1), 1e-300))
    Ns = N / (d[..., :, None] * d[..., None, :])
    ev = np.linalg.eigvalsh(Ns)
    ok = (cnt >= s.min_ls_epochs) & (ev[..., -1] < s.max_condition * np.maximum(ev[..., 0], 1e-300))
    Ninv = np.linalg.inv(np.where(ok[..., None, None], Ns, np.eye(8))) / (
        d[..., :, None] * d[..., None, :]
    )
    X = np.einsum("...ij,...j->...i", Ninv, r)
    I_G = _inertia_from_l(np.where(ok[..., None], X[..., :5], 0.0))
    ev_I = np.linalg.eigvalsh(I_G)
    ok &= np.all(np.isfinite(ev_I), -1) & (ev_I[..., 0] > 0) & (ev_I[..., -1] < 100.0)
    I_out = np.broadcast_to(np.eye(3), I_G.shape).copy()
    lam = np.ones(ok.shape)
    for bi in range(len(ok)):
        idx = np.flatnonzero(ok[bi])
        if len(idx):
            last = np.maximum.accumulate(np.where(ok[bi], np.arange(ok.shape[1]), idx[0]))
            I_out[bi] = I_G[bi, last]
            lam[bi] = ev_I[bi, last, -1]
    return I_out, lam


def _ls_rows(
    omega_G: Array, var_w: Array, R_GI: Array, cov_w: Array | None
) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
    """Rows a (B,n,3,8), b (B,n,3), weights and mask of the least squares (Hu 2024 eq. 11-12),
    whitened (see identify_and_dpacf)."""
    ok = np.all(np.isfinite(omega_G), axis=-1) & np.all(np.isfinite(R_GI), axis=(-1, -2))
    a, b = inertia_design(np.nan_to_num(omega_G), np.nan_to_num(R_GI))
    if cov_w is None:
        w = np.where(ok, 1.0 / np.maximum(np.nan_to_num(var_w, nan=1.0), 1e-30), 0.0)
    else:
        # Generalised least squares (beyond the paper's eq. 13): each epoch's three rows are
        # whitened by the covariance of their residual a X - b = I_bar d_omega + [R H x] psi,
        # psi the G attitude error at k, R H = I_bar omega. The rate's error is its fit's
        # noise plus -[omega x] psi (rates_and_covariance), so psi enters as
        # ([I_bar omega x] - I_bar [omega x]) psi, which vanishes at I_bar = 1: with I_bar = 1
        # (the moments differ by less than a factor 2, the rate error's axes by orders of
        # magnitude) C = cov_w, the fit's noise only.
        # (compiled loop; the numpy batched Cholesky and solves cost a fifth of the front end)
        ok = ok & np.all(np.isfinite(cov_w), axis=(-1, -2))
        a = np.ascontiguousarray(a)
        b = np.ascontiguousarray(b)
        _points_kernel.whiten_rows(a, b, np.ascontiguousarray(np.nan_to_num(cov_w)), ok)
        w = ok.astype(float)
    return a, b, w, ok


def _solve_and_dpacf(
    N,
    r,
    bb,
    cnt,
    sel,
    held,
    s,
    R_GI,
    cov_G,
    V=None,
    E=None,
    Nc=None,
    rc=None,
    M=None,
    Ew=None,
    Sw=None,
):
    """identify_and_dpacf from the least-squares sums at the solved epochs ``sel``."""
    d = np.sqrt(np.maximum(np.diagonal(N, axis1=-2, axis2=-1), 1e-300))
    Ns = N / (d[..., :, None] * d[..., None, :])
    ev = np.linalg.eigvalsh(Ns)
    cond = ev[..., -1] / np.maximum(ev[..., 0], 1e-300)
    valid = (cnt >= s.min_ls_epochs) & (cond < s.max_condition)
    eye8 = np.eye(8)
    Nreg = np.where(valid[..., None, None], Ns, eye8)
    Ninv_s = np.linalg.inv(Nreg)
    Ninv = Ninv_s / (d[..., :, None] * d[..., None, :])
    X = np.einsum("...ij,...j->...i", Ninv, r)
    if Nc is not None and rc is not None:
        # errors in variables (beyond Hu 2024): the rates' noise in the rows' own terms adds
        # E[da^T da] to N and E[da^T db] to r, which biases the solution towards a smaller
        # I_bar by about var(omega) / omega^2 (measured: the frame error grew as the noise
        # squared, NEES/dof 7 at 2e-4 rad of G attitude noise); subtract them
        # (bias-compensated least squares) where the result stays well conditioned
        Nb = N - Nc
        Nbs = Nb / (d[..., :, None] * d[..., None, :])
        evb = np.linalg.eigvalsh(Nbs)
        good = valid & (evb[..., 0] > 0) & (evb[..., -1] < s.max_condition * evb[..., 0])
        Nbinv = np.linalg.inv(np.where(good[..., None, None], Nbs, eye8))
        Nbinv = Nbinv / (d[..., :, None] * d[..., None, :])
        Xb = np.einsum("...ij,...j->...i", Nbinv, r - rc)
        X = np.where(good[..., None], Xb, X)
        Ninv = np.where(good[..., None, None], Nbinv, Ninv)
    rss = bb - 2 * np.einsum("...i,...i->...", X, r) + np.einsum("...i,...ij,...j->...", X, N, X)
    dof = np.maximum(3 * cnt - 8, 1)
    s2 = np.maximum(rss / dof, 1e-30)
    gate = np.ones_like(rss)
    if V is None or E is None:
        # independent epochs (Hu 2024 eq. 13), scaled by the reduced chi-square
        cov_X = s2[..., None, None] * Ninv
    else:
        # the rows' noise model (gls: the rates' correlation, the disturbance torque): the
        # sandwich N^-1 V N^-1, scaled up where the residuals exceed what that model
        # expects, E - tr(N^-1 V) (tumblenav default): see _residual_scale
        if s.rate_noise == "independent":
            V = N  # each row's noise independent of the others' (see FrontEndSettings)
        walk = np.zeros_like(rss)
        axes = np.ones_like(rss)
        if M is not None:
            V = V + M
            if Ew is not None:  # the momentum's walk's share of the expected residuals
                walk = Ew - np.trace(Ninv @ M, axis1=-2, axis2=-1)
            if Sw is not None:  # over how many of the momentum's axes it is spread
                tr = np.trace(Sw, axis1=-2, axis2=-1)
                tr2 = np.sum(Sw * Sw, axis=(-2, -1))
                axes = np.where(tr2 > 0, tr**2 / np.where(tr2 > 0, tr2, 1.0), 1.0)
        cov_X = Ninv @ V @ Ninv
        expect = E - np.trace(Ninv @ V, axis1=-2, axis2=-1)
        scale, gate = _residual_scale(
            rss, expect, walk, 3 * cnt - 8, 2 * s.rate_half_window + 1, axes
        )
        cov_X = scale[..., None, None] * cov_X
    cov_l = cov_X[..., :5, :5]
    I_G = _inertia_from_l(X[..., :5])
    lam = np.linalg.eigvalsh(np.where(valid[..., None, None], I_G, np.diag([3.0, 2.0, 1.0])))
    lam = lam[..., ::-1]
    gaps = np.minimum(lam[..., 0] - lam[..., 1], lam[..., 1] - lam[..., 2]) / np.abs(lam[..., 0])
    physical = (lam[..., 2] > 0) & (lam[..., 1] + lam[..., 2] >= lam[..., 0] * (1 - 1e-3))
    valid &= (gaps > s.min_eigengap) & physical
    R_GT = principal_frame(np.where(valid[..., None, None], I_G, np.diag([3.0, 2.0, 1.0])))
    # Eigenvector perturbation: rotation error of T relative to G, in T (derivation in docs).
    r1, r2, r3 = R_GT[..., :, 0], R_GT[..., :, 1], R_GT[..., :, 2]
    l1, l2, l3 = lam[..., 0], lam[..., 1], lam[..., 2]
    Jphi = np.stack(
        [
            np.einsum("...i,jik,...k->...j", r3, _E, r2) / (l2 - l3)[..., None],
            -np.einsum("...i,jik,...k->...j", r3, _E, r1) / (l1 - l3)[..., None],
            np.einsum("...i,jik,...k->...j", r2, _E, r1) / (l1 - l2)[..., None],
        ],
        -2,
    )  # (...,3,5)
    cov_phi = Jphi @ cov_l @ np.swapaxes(Jphi, -1, -2)
    # Covariance of the inertia ratios p (Hu 2024 eq. 19) by first-order perturbation of the
    # eigenvalues, d lambda_i = r_i^T dI r_i (beyond the paper: the filter's initial
    # covariance of p; the moments themselves are scale-free, p is a function of them).
    # d lambda_i / d l_j = r_i^T E_j r_i, l = [Iyy, Izz, Ixy, Ixz, Iyz] (written out: an
    # einsum over the basis _E cost a tenth of the front end)
    rx, ry, rz = R_GT[..., 0, :], R_GT[..., 1, :], R_GT[..., 2, :]  # (..., 3): row a, col i
    Jlam = np.stack([ry * ry, rz * rz, 2 * rx * ry, 2 * rx * rz, 2 * ry * rz], -1)
    zero = np.zeros_like(l1)
    Jp = (
        np.stack(
            [
                np.stack([-(l2 - l3) / l1**2, 1 / l1, -1 / l1], -1),
                np.stack([-1 / l2, -(l3 - l1) / l2**2, 1 / l2], -1),
                np.stack([1 / l3, -1 / l3, -(l1 - l2) / l3**2], -1),
            ],
            -2,
        )
        + zero[..., None, None]
    )
    Jpl = Jp @ Jlam
    cov_p = Jpl @ cov_l @ np.swapaxes(Jpl, -1, -2)
    sig_phi = np.sqrt(np.max(np.linalg.eigvalsh(np.nan_to_num(cov_phi, nan=1e6)), axis=-1))
    valid &= gate * sig_phi < s.max_dpacf_sigma_rad
    # back to every epoch (hold the latest solution)
    pos = np.searchsorted(sel, held)
    R_GT, lam, cov_phi, valid = R_GT[:, pos], lam[:, pos], cov_phi[:, pos], valid[:, pos]
    gate = gate[:, pos]
    cov_p = cov_p[:, pos]
    R_TG = np.swapaxes(R_GT, -1, -2)
    R_TI = R_TG @ _finite_or_identity(R_GI)
    cov_TI = cov_phi + R_TG @ np.nan_to_num(cov_G) @ R_GT
    q_TI = _quats(R_TI)
    meas_ok = valid & np.all(np.isfinite(R_GI), axis=(-1, -2))
    q_TI = np.where(meas_ok[..., None], q_TI, np.nan)
    cov_TI = np.where(meas_ok[..., None, None], cov_TI, np.nan)
    R_GT = np.where(valid[..., None, None], R_GT, np.nan)
    moments = np.where(valid[..., None], lam / lam[..., :1], np.nan)
    cov_phi = np.where(valid[..., None, None], cov_phi, np.nan)
    cov_p = np.where(valid[..., None, None], cov_p, np.nan)
    gate = np.where(valid, gate, np.nan)
    return R_GT, moments, q_TI, cov_TI, cov_phi, cov_p, gate


# The effective degrees of freedom of the residuals' share from the momentum's random walk, per
# axis of the momentum: a Brownian motion less its mean over the window (the momentum column
# fits the mean) has the Karhunen-Loeve variances 1 / (pi k)^2, k = 1, 2, ..., so its squared
# norm has (sum 1/(pi k)^2)^2 / sum 1/(pi k)^4 = (1/6)^2 / (1/90) = 2.5 degrees of freedom.
WALK_DOF_PER_AXIS = 2.5


def _residual_scale(
    rss: Array, expect: Array, walk: Array, rows: Array, corr_rows: int, axes: Array | float = 3.0
) -> tuple[Array, Array]:
    """The least squares' residual scale (beyond Hu 2024): ``(scale, gate)``, the factor on
    the reported covariance and the factor on the frame's sigma in the thresholds on it.

    ``rss / expect`` estimates how much the rows' noise model understates their noise. Its
    spread under the right model depends on what the residuals hold: the momentum's random
    walk (``walk`` of ``expect``) has :data:`WALK_DOF_PER_AXIS` degrees of freedom per axis
    it is spread over (``axes``, 1-3: the participation ratio ``tr(S)^2 / tr(S^2)`` of its
    share per axis ``S``, gls' ``Sw``; the whitening and the rows' turning weigh the axes
    unequally) whatever the window, the rows' own noise ``rows / corr_rows`` (rows
    correlated over the rate fit's window): ``Var(rss) / expect^2 = 2 (w^2 / nu_walk + (1 -
    w)^2 / nu_rows)``, ``w = walk / expect``. Where the walk dominates the ratio varies by a
    factor of several from run to run (hu_occ20's 20 runs, late solutions: 0.25-3.0, an
    effective 5.3 degrees of freedom; hu_occ30's 4.3), and ``max(ratio, 1)``, applied until
    the twenty-third session, kept only the upward draws: the frame and everything turned by
    it conservative (hu_occ20 attitude NEES/dof 0.66, without the scale 0.94). So the
    covariance is scaled by the ratio only where it exceeds its 95 % quantile under the model
    (a misfit detected; ``chi2(nu) / nu`` with ``nu = 2 / (Var(rss) / expect^2)``); where the
    rows' own noise dominates that quantile is near 1 and the scale is the ratio as before
    (torque-free synthetic frames, tests/test_frontends.py). The gate keeps ``sqrt(max(ratio,
    1))``: a frame waits until it is good enough even under the excess (on hu_conv30 frames
    trusted sooner ended a run on the half-turn branch)."""
    e = np.maximum(expect, 1e-30)
    ratio = rss / e
    w = np.clip(walk / e, 0.0, 1.0)
    nu_walk = WALK_DOF_PER_AXIS * np.clip(axes, 1.0, 3.0)
    nu_rows = np.maximum(np.asarray(rows, float) / max(corr_rows, 1), 1.0)
    rel_var = 2.0 * (w**2 / nu_walk + (1.0 - w) ** 2 / nu_rows)
    nu = 2.0 / np.maximum(rel_var, 1e-12)
    q95 = stats.chi2.ppf(0.95, nu) / nu
    scale = np.where(ratio > q95, ratio, 1.0)
    return scale, np.sqrt(np.maximum(ratio, 1.0))
