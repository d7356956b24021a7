"""The inertia least squares' noise model (compiled; beyond Hu 2024, whose eq. 13 treats the
epochs as independent and the motion as torque-free). The estimate stays the least squares
of eq. 13 (bias-compensated, below); what changes is the covariance it reports.

* **The disturbance torque.** Hu 2024 eq. 10-11 rest on a constant angular momentum:
  ``I_bar omega_G(t) = R_GI(t) H`` with ``H = H_I / I_xx`` (eq. 9's normalisation by the
  G-frame ``I_xx``). Under the scenario's isotropic random torque of spectral density
  ``q_r I_max^2`` per axis (:mod:`tumblenav.dynamics.disturbances`), ``H_I`` random-walks,
  isotropically in I, with ``d(H_I / I_xx)`` of variance ``q_r (I_max / I_xx)^2 dt =
  q_r lambda_1^2 dt`` per axis, ``lambda_1`` the largest eigenvalue of ``I_bar``. Row j
  then carries ``R_GI(j) W(t_j)``, ``W`` that walk, and ``r = sum_j a_j^T b_j`` the noise
  ``sum_m F_m w_m``, ``F_m = sum_{j >= m} a_j^T L_j^-1 R_GI(j)`` (``w_m`` the walk's step to
  epoch m), of covariance ``M = sum_m q_m F_m F_m^T``, kept in running sums. (A Kalman
  filter with the momentum as a random-walk state was tried first: it leans on the rows'
  short-term changes, where the rates' noise in the regressors biases it, 17-56 deg frame
  errors against 2 deg for eq. 13 on a synthetic slow tumble.)

* **The rates' correlation.** The rate of epoch j is the slope ``-sum_i c_i phi_{j+i} / dt``
  of the attitudes over ``j - h .. j + h`` (``rates.rates_and_covariance``; ``c`` the line's
  or the cubic's coefficients, ``sum_i c_i = 0``), and its error ``-sum_i c_i psi_{j+i} /
  dt - [omega x] psi_j`` for G attitude errors ``psi``; the row's noise is ``I_bar`` times
  it plus ``[I_bar omega x] psi_j`` (the momentum's column). With ``psi`` independent
  between epochs (covariance ``cov_G``) the rows up to ``2h`` apart share noise whose sum
  over the lags nearly cancels (a derivative of white noise); ``V``, the covariance of
  ``r``'s noise, is kept exactly through ``Z_e = Cov(r, psi_e)`` for the attitudes later
  rows still use.

* **Errors in variables.** The rows' own terms hold the noisy rate, so ``N`` and ``r`` carry
  ``E[da^T da]`` and ``E[da^T db]`` (``Nc``, ``rc``): the solution leans to a smaller
  ``I_bar`` by about ``var(omega) / omega^2`` (the frame error grew as the noise squared);
  the caller subtracts them (bias-compensated least squares).

The covariance is then ``N^-1 (V + M) N^-1`` (``inertia_ls._solve_and_dpacf``), ``V``
either this model's or ``N`` (independent unit rows: ``FrontEndSettings.rate_noise``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_H = 5  # the momentum's first column in X = [l (5), H (3)]


@njit(cache=True, error_model="numpy")
def whitening(C_all, ok):  # pragma: no cover - compiled
    """``L^-1`` (B,n,3,3) with ``L L^T = C`` (plus 1e-12 of its trace on the diagonal),
    lower triangular; zero (and ``ok`` cleared, in place) where C is not positive definite
    (the same factor as ``_points_kernel.whiten_rows``)."""
    B, n = ok.shape
    out = np.zeros((B, n, 3, 3))
    L = np.zeros((3, 3))
    for bi in range(B):
        for k in range(n):
            if not ok[bi, k]:
                continue
            tr = C_all[bi, k, 0, 0] + C_all[bi, k, 1, 1] + C_all[bi, k, 2, 2]
            c00 = C_all[bi, k, 0, 0] + 1e-12 * tr
            if not c00 > 0.0:
                ok[bi, k] = False
                continue
            L[0, 0] = math.sqrt(c00)
            L[1, 0] = C_all[bi, k, 1, 0] / L[0, 0]
            L[2, 0] = C_all[bi, k, 2, 0] / L[0, 0]
            d1 = C_all[bi, k, 1, 1] + 1e-12 * tr - L[1, 0] ** 2
            if not d1 > 0.0:
                ok[bi, k] = False
                continue
            L[1, 1] = math.sqrt(d1)
            L[2, 1] = (C_all[bi, k, 2, 1] - L[2, 0] * L[1, 0]) / L[1, 1]
            d2 = C_all[bi, k, 2, 2] + 1e-12 * tr - L[2, 0] ** 2 - L[2, 1] ** 2
            if not d2 > 0.0:
                ok[bi, k] = False
                continue
            L[2, 2] = math.sqrt(d2)
            # inverse of the lower triangular L
            out[bi, k, 0, 0] = 1.0 / L[0, 0]
            out[bi, k, 1, 1] = 1.0 / L[1, 1]
            out[bi, k, 2, 2] = 1.0 / L[2, 2]
            out[bi, k, 1, 0] = -L[1, 0] * out[bi, k, 0, 0] / L[1, 1]
            out[bi, k, 2, 1] = -L[2, 1] * out[bi, k, 1, 1] / L[2, 2]
            out[bi, k, 2, 0] = -(L[2, 0] * out[bi, k, 0, 0] + L[2, 1] * out[bi, k, 1, 0]) / L[2, 2]
    return out


@njit(cache=True, error_model="numpy")
def gls_sums_at(
    a, b, ok, Linv, S, coef, extra, Cn, Ibar, R_GI, delay, sel, q_step
):  # pragma: no cover
    """The least squares' sums and its noise model (module docstring), read at epochs
    ``sel`` over the rows ``0 .. k - delay``.

    a (B,n,3,8), b (B,n,3): rows whitened by ``Linv`` (B,n,3,3; unit weight on ``ok`` rows);
    S (B,n,3,3): covariance of each epoch's G attitude error (rad^2); coef (B,n,2h+1): the
    rate fit's coefficients at each epoch, divided by dt (the rate's noise is ``sum_i
    coef[j, i] psi_{j-h+i} - [omega_j x] psi_j``); extra (B,n,3,3): the rate's covariance
    not from ``psi`` (independent between epochs); Cn (B,n,3,3): the covariance of the rate's
    zero-mean noise, the regressors' errors (errors in variables; the whitening's, ``(Linv^T
    Linv)^-1``, unless the caller knows better); Ibar (B,n,4,3): the normalised inertia
    (rows 0-2) and the rate (row 3) the row's noise is taken at: ``Ibar (rate noise) +
    [Ibar omega x] psi_j``; R_GI (B,n,3,3): the rows' G attitudes; q_step
    (B,n): the momentum's random-walk variance per axis over the step to each epoch.

    Returns N, r, bb, cnt (as ``_points_kernel.normal_equations_at``), V (B,S,8,8), the
    covariance of ``r``'s noise from the rates' noise, the expected sum of the whitened rows' squared noise,
    ``E`` (B,S), and the noise's expected share of N, r and bb, ``Nc`` (B,S,8,8), ``rc``
    (B,S,8), ``bbc`` (B,S) (the rates' noise in the rows' own terms: errors in variables),
    and ``M`` (B,S,8,8), the covariance of ``r``'s noise from the momentum's random walk;
    last, ``Ew`` (B,S), the random walk's share of ``E``, and ``Sw`` (B,S,3,3), that share per
    axis of the momentum (in I): ``Ew = tr(Sw)``."""
    B, n = ok.shape
    nS = sel.shape[0]
    L = coef.shape[2]  # 2h + 1
    h = (L - 1) // 2
    nb = L + 1  # ring buffer of Z_e = Cov(r, psi_e), e = j - h .. j + h
    N = np.zeros((B, nS, 8, 8))
    r = np.zeros((B, nS, 8))
    bbo = np.zeros((B, nS))
    cnt = np.zeros((B, nS), dtype=np.int64)
    Vo = np.zeros((B, nS, 8, 8))
    Eo = np.zeros((B, nS))
    Ewo = np.zeros((B, nS))
    Swo = np.zeros((B, nS, 3, 3))
    Sw = np.zeros((3, 3))
    Mo = np.zeros((B, nS, 8, 8))
    Nco = np.zeros((B, nS, 8, 8))
    rco = np.zeros((B, nS, 8))
    bbco = np.zeros((B, nS))
    Nc = np.zeros((8, 8))
    rc = np.zeros(8)
    # d I_bar / d X_k (k < 5) and the constant part (I_xx = 1), Hu 2024 eq. 9
    Eb = np.zeros((6, 3, 3))
    Eb[5, 0, 0] = 1.0
    Eb[0, 1, 1] = Eb[1, 2, 2] = 1.0
    Eb[2, 0, 1] = Eb[2, 1, 0] = 1.0
    Eb[3, 0, 2] = Eb[3, 2, 0] = 1.0
    Eb[4, 1, 2] = Eb[4, 2, 1] = 1.0
    PEC = np.zeros((6, 3, 3))
    Y = np.zeros((8, 8))
    y = np.zeros(8)
    V = np.zeros((8, 8))
    Z = np.zeros((nb, 8, 3))
    D = np.zeros((8, 3))
    AL = np.zeros((8, 3))
    Sg = np.zeros((8, 3))  # running sum of A^T Linv R_GI (the momentum's columns' noise)
    A1 = np.zeros((8, 3))
    A2 = np.zeros((8, 8))
    for bi in range(B):
        Y[:, :] = 0.0
        y[:] = 0.0
        V[:, :] = 0.0
        Z[:, :, :] = 0.0
        Sg[:, :] = 0.0
        A1[:, :] = 0.0
        A2[:, :] = 0.0
        A0 = 0.0
        Nc[:, :] = 0.0
        rc[:] = 0.0
        bbc = 0.0
        bb = 0.0
        Esum = 0.0
        Ewalk = 0.0
        Sw[:, :] = 0.0
        cc = 0
        zmax = -1  # highest attitude epoch whose Z slot is initialised
        j = 0
        for si in range(nS):
            last = sel[si] - delay
            while j <= last and j < n:
                # the attitudes row j uses get their (zero) slots
                while zmax < min(j + h, n - 1):
                    zmax += 1
                    Z[zmax % nb, :, :] = 0.0
                # the momentum's increment over the step to j acts on rows j, j+1, ...
                qj = q_step[bi, j]
                if qj > 0.0:
                    A0 += qj
                    A1 += qj * Sg
                    A2 += qj * (Sg @ Sg.T)
                if ok[bi, j]:
                    A = a[bi, j]  # (3,8)
                    Y += A.T @ A
                    y += A.T @ b[bi, j]
                    for m in range(3):
                        bb += b[bi, j, m] ** 2
                    cc += 1
                    Lj = Linv[bi, j]
                    AL[:, :] = A.T @ Lj  # the row's whitened noise enters r through AL
                    Sg += AL @ R_GI[bi, j]
                    LL = 0.0
                    for p in range(3):
                        for q in range(3):
                            LL += Lj[p, q] ** 2
                    Esum += A0 * LL  # the momentum's walk since the first row (diagonal)
                    Ewalk += A0 * LL
                    # errors in variables: the row's noise is Linv I_bar(X) d_omega, so
                    # E[da^T da]_kk' = tr(E_k P E_k' C), P = Linv^T Linv, C = Cov(d_omega)
                    P = Lj.T @ Lj
                    Cw = Cn[bi, j]
                    if A0 > 0.0:  # the walk's share per axis of I: A0 R^T P R
                        Rj = R_GI[bi, j]
                        Sw += A0 * (Rj.T @ P @ Rj)
                    for k in range(6):
                        PEC[k] = P @ Eb[k] @ Cw
                    for k in range(5):
                        for k2 in range(5):
                            Nc[k, k2] += np.trace(Eb[k] @ PEC[k2])
                        rc[k] -= np.trace(Eb[k] @ PEC[5])
                    bbc += np.trace(Eb[5] @ PEC[5])
                    Ib = np.ascontiguousarray(Ibar[bi, j, :3])
                    w = Ibar[bi, j, 3]
                    Iw = Ib @ w
                    # centre = [Ibar omega x] - Ibar [omega x]
                    centre = np.zeros((3, 3))
                    centre[0, 1], centre[0, 2], centre[1, 2] = -Iw[2], Iw[1], -Iw[0]
                    centre[1, 0], centre[2, 0], centre[2, 1] = Iw[2], -Iw[1], Iw[0]
                    wx = np.zeros((3, 3))
                    wx[0, 1], wx[0, 2], wx[1, 2] = -w[2], w[1], -w[0]
                    wx[1, 0], wx[2, 0], wx[2, 1] = w[2], -w[1], w[0]
                    centre -= Ib @ wx
                    Ex = Ib @ extra[bi, j] @ Ib.T
                    Esum += np.trace(Lj @ Ex @ Lj.T)
                    V += AL @ Ex @ AL.T
                    # the fit's noise, sum_e coef psi_e, and the centre's, centre psi_j
                    for i in range(L):
                        e = j - h + i
                        if e < 0 or e >= n:
                            continue
                        Ce = coef[bi, j, i] * Ib
                        if e == j:
                            Ce = Ce + centre
                        D[:, :] = AL @ Ce
                        DS = D @ S[bi, e]
                        cross = Z[e % nb] @ D.T
                        V += cross + cross.T + DS @ D.T
                        Z[e % nb] += DS
                        LC = Lj @ Ce
                        Esum += np.trace(LC @ S[bi, e] @ LC.T)
                j += 1
            N[bi, si] = Y
            r[bi, si] = y
            bbo[bi, si] = bb
            cnt[bi, si] = cc
            # the momentum's random walk: sum_m q_m (Sg - S_{m-1}) (Sg - S_{m-1})^T
            M = A0 * (Sg @ Sg.T) - Sg @ A1.T - A1 @ Sg.T + A2
            Vo[bi, si] = V
            Mo[bi, si] = M
            Eo[bi, si] = Esum
            Ewo[bi, si] = Ewalk
            Swo[bi, si] = Sw
            Nco[bi, si] = Nc
            rco[bi, si] = rc
            bbco[bi, si] = bbc
    return N, r, bbo, cnt, Vo, Eo, Nco, rco, bbco, Mo, Ewo, Swo


def fit_coefficients(h: int) -> tuple[np.ndarray, np.ndarray]:
    """The line's and the line-plus-cubic's slope coefficients over ``j = -h..h`` (the rate
    is ``-sum_j c_j phi_j / dt``, ``_points_kernel.rate_fit``)."""
    j = np.arange(-h, h + 1, dtype=float)
    cl = j / np.sum(j**2)
    cc = np.linalg.pinv(np.stack([j, j**3], 1))[0] if h >= 2 else np.zeros_like(j)
    return cl, cc
