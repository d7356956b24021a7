"""Hu 2024 measurement updates: the DPACF attitude (eq. 31) and the triangulated features
(eq. 32-35), batch with a gate or sequential per feature (the compiled kernel's order)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot

Array = NDArray[np.float64]


def _update(x, P, fe, k, lay, use_att, gate, att_inflation, active):
    """One batched measurement update at epoch k (Hu 2024 eq. 40-44).

    All visible feature blocks (eq. 32-35) and the DPACF attitude (eq. 31) are processed
    together; the sparsity of H is used so that the cost is O(d^2 m), not O(d^3).
    Covariance: the Joseph form of eq. 41, ``(I-KH)P(I-KH)^T + K R K^T``, equals
    ``P - (HP)^T S^-1 (HP)`` for the optimal gain of eq. 42 (expand it and use
    ``K S = P H^T``); that expression is evaluated (symmetrised), which avoids the two
    O(d^3) products. Rows of measurements that are missing (or runs not started) are
    zeroed, so they change nothing.
    """
    B, N = fe.usable.shape[0], fe.usable.shape[2]
    d = lay.dim
    m = 3 + 3 * N
    sa, sr = lay.err("attitude"), lay.err("position")
    sf0 = lay.err("features").start
    q = x[:, lay.nom("attitude")]
    f = x[:, lay.nom("features")].reshape(B, N, 3)
    R_LT = fe.R_LI[:, k] @ np.swapaxes(rot.quat_to_matrix(q), -1, -2)
    Hth = R_LT[:, None] @ rot.skew(f)  # (B,N,3,3): dy_i/dtheta = R_LT [f_i x]
    y_hat = x[:, None, lay.nom("position")] + f @ np.swapaxes(R_LT, -1, -2)
    u = fe.usable[:, k] & active[:, None]
    ok0 = np.all(np.isfinite(fe.q_TI[:, k]), axis=-1) & active & use_att
    rows = np.concatenate([np.repeat(ok0[:, None], 3, 1), np.repeat(u, 3, axis=1)], axis=1)
    # innovations
    nu = np.zeros((B, m))
    q_hat = x[:, lay.nom("attitude")]
    qm = np.where(ok0[:, None], fe.q_TI[:, k], q_hat)
    nu[:, :3] = rot.boxminus(qm, q_hat)
    nu[:, 3:] = (np.nan_to_num(fe.p_L[:, k]) - y_hat).reshape(B, -1)
    nu *= rows
    # H P, using the structure of H
    Pth = P[:, sa, :]
    HPf = Hth @ Pth[:, None] + P[:, None, sr, :] + R_LT[:, None] @ P[:, sf0:, :].reshape(B, N, 3, d)
    HP = np.concatenate([Pth, HPf.reshape(B, 3 * N, d)], axis=1) * rows[..., None]
    # S = H P H^T + R, again from the structure of H (columns: attitude, then features)
    HPth, HPr = HP[:, :, sa], HP[:, :, sr]
    S_f = HPth @ np.transpose(Hth, (0, 3, 1, 2)).reshape(B, 3, 3 * N)
    S_f += np.tile(HPr, (1, 1, N))
    S_f += _feature_cols(HP[:, :, sf0:], R_LT, B, m, N)
    S = np.concatenate([HPth, S_f], axis=2)
    Rm = np.zeros((B, m, m))
    if use_att:
        R0 = np.nan_to_num(fe.cov_TI[:, k] + (att_inflation - 1.0) * fe.cov_frame[:, k])
        Rm[:, :3, :3] = R0
    covL = np.nan_to_num(fe.cov_L[:, k])
    for i in range(N):
        Rm[:, 3 + 3 * i : 6 + 3 * i, 3 + 3 * i : 6 + 3 * i] = covL[:, i]
    both = rows[:, :, None] & rows[:, None, :]
    S = np.where(both, S + Rm, 0.0) + (~rows)[:, :, None] * np.eye(m)
    keep_blocks = rows[:, ::3].copy()
    rejected = np.zeros(B, dtype=np.int64)
    if np.isfinite(gate):  # per-block chi-square gate on the innovations (optional)
        Sb = np.stack([S[:, 3 * j : 3 * j + 3, 3 * j : 3 * j + 3] for j in range(N + 1)], 1)
        nb = nu.reshape(B, N + 1, 3)
        d2 = np.einsum("bji,bji->bj", nb, np.linalg.solve(Sb, nb[..., None])[..., 0])
        reject = keep_blocks & (d2 > gate)
        if reject.any():
            keep_blocks &= ~reject
            rejected = reject.sum(axis=1)
            rows = np.repeat(keep_blocks, 3, axis=1)
            both = rows[:, :, None] & rows[:, None, :]
            S = np.where(both, S, 0.0) + (~rows)[:, :, None] * np.eye(m)
            HP = HP * rows[..., None]
            nu = nu * rows
    sol = np.linalg.solve(S, np.concatenate([HP, nu[..., None]], axis=2))
    Kt, Sinv_nu = sol[..., :d], sol[..., d]  # S^-1 H P (= K^T) and S^-1 nu
    dx = (nu[:, None, :] @ Kt)[:, 0]  # K nu, eq. 40
    P_new = P - np.swapaxes(HP, -1, -2) @ Kt  # eq. 41 for the optimal gain (see above)
    P_new = 0.5 * (P_new + np.swapaxes(P_new, -1, -2))
    x_new = lay.boxplus(x, dx)  # eq. 43-44
    nis_k = np.sum(nu * Sinv_nu, axis=1)
    return x_new, P_new, nis_k, 3 * keep_blocks.sum(axis=1), rejected


def _inv3(S: Array) -> tuple[Array, Array]:
    """Inverse and determinant of stacks of 3x3 matrices by cofactors (vectorised, no LAPACK
    call per matrix: the batched solve dominated the update's cost)."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    d, e, f = S[..., 1, 0], S[..., 1, 1], S[..., 1, 2]
    g, h, i = S[..., 2, 0], S[..., 2, 1], S[..., 2, 2]
    A, B_, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B_ + c * C
    adj = np.stack(
        [
            np.stack([A, -(b * i - c * h), b * f - c * e], -1),
            np.stack([B_, a * i - c * g, -(a * f - c * d)], -1),
            np.stack([C, -(a * h - b * g), a * e - b * d], -1),
        ],
        -2,
    )
    return adj / det[..., None, None], det


def frame_measurement(f: Array, g: Array, use: NDArray[np.bool_], jac: bool = False):
    """The rotation ``R_TG`` between the filter's features in T and their template in G.

    ``f`` (B,N,3) features in T, ``g`` (B,N,3) template in G, ``use`` (B,N). Least-squares
    rigid alignment (Kabsch) of the centred sets. With ``jac``, also ``dphi/df_i`` (B,N,3,3)
    for the rotation error ``R_TG = Exp(dphi) R_TG_hat`` (in T): with ``b_i`` the centred
    template rotated into T and ``M = sum (|b_i|^2 I - b_i b_i^T)``,
    ``dphi/df_i = M^-1 [b_i x]`` (centring cancels because ``sum b_i = 0``).
    """
    w = use.astype(float)
    n = np.maximum(w.sum(axis=1), 1.0)[:, None]
    fc = np.nan_to_num(f) - (w[..., None] * np.nan_to_num(f)).sum(1)[:, None] / n[..., None]
    gc = np.nan_to_num(g) - (w[..., None] * np.nan_to_num(g)).sum(1)[:, None] / n[..., None]
    fc, gc = fc * w[..., None], gc * w[..., None]
    Hm = np.swapaxes(gc, -1, -2) @ fc  # sum g f^T
    U, _, Vt = np.linalg.svd(Hm)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros_like(Hm)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    R_TG = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    if not jac:
        return R_TG, None
    b = gc @ np.swapaxes(R_TG, -1, -2)
    M = np.sum(w * np.sum(b * b, -1), 1)[:, None, None] * np.eye(3) - np.swapaxes(b, -1, -2) @ b
    Minv, _ = _inv3(M)
    J = (Minv[:, None] @ rot.skew(b)) * w[..., None, None]
    return R_TG, J


def _update_sequential(x, P, fe, k, lay, use_att, att_inflation, active, f_lin=None, x_lin=None):
    """The update of :func:`_update` processed block by block (DPACF attitude, then each
    feature), all linearised at the prior, or at ``x_lin`` (an iterate of the iterated
    update: each innovation then adds ``H (x_lin boxminus x)``): for independent
    measurement blocks this equals the batch update exactly, and it needs only 3x3
    inverses."""
    B, N = fe.usable.shape[0], fe.usable.shape[2]
    sa, sr = lay.err("attitude"), lay.err("position")
    sf0 = lay.err("features").start
    xl = x if x_lin is None else x_lin
    q_hat = xl[:, lay.nom("attitude")]
    f = xl[:, lay.nom("features")].reshape(B, N, 3)
    R_LT = fe.R_LI[:, k] @ np.swapaxes(rot.quat_to_matrix(q_hat), -1, -2)
    R_TL = np.swapaxes(R_LT, -1, -2)
    # dy_i/dtheta = R_LT [f_i x]; optionally at the features' first estimates (FEJ)
    Hth = R_LT[:, None] @ rot.skew(f if f_lin is None else np.where(np.isfinite(f_lin), f_lin, f))
    HthT = np.swapaxes(Hth, -1, -2)
    y_hat = xl[:, None, lay.nom("position")] + f @ R_TL
    if x_lin is not None:  # + H delta, delta = x_lin boxminus x
        dl = lay.boxminus(x_lin, x)
        dlf = dl[:, sf0:].reshape(B, N, 3)
        y_hat = y_hat - (Hth @ dl[:, None, sa, None])[..., 0] - dl[:, None, sr] - dlf @ R_TL
    u = fe.usable[:, k] & active[:, None]
    nu_f = np.where(u[..., None], np.nan_to_num(fe.p_L[:, k]) - y_hat, 0.0)
    covL = np.nan_to_num(fe.cov_L[:, k])
    dx = np.zeros((B, P.shape[-1]))  # P may carry consider parameters after the state
    nis = np.zeros(B)
    eye3 = np.eye(3)

    def absorb(HP, S, nu, ok):
        nonlocal P, dx, nis
        HP = HP * ok[:, None, None]
        S = np.where(ok[:, None, None], S, eye3)
        Sinv, _ = _inv3(S)
        Kt = Sinv @ HP  # (B,3,d) = K^T
        nu = nu * ok[:, None]
        dx += (nu[:, None, :] @ Kt)[:, 0]
        P = P - np.swapaxes(HP, -1, -2) @ Kt
        nis += np.sum(nu * (Sinv @ nu[..., None])[..., 0], axis=1)

    if use_att == "frame":  # DPACF frame R_TG against the filter's own features
        use = fe.known_at[:, k] & active[:, None]
        ok0 = np.all(np.isfinite(fe.R_GT[:, k]), axis=(-1, -2)) & (use.sum(1) >= 3) & active
        R_hat, J = frame_measurement(f, fe.template_at(k), use, jac=True)
        R_meas = np.swapaxes(np.where(ok0[:, None, None], fe.R_GT[:, k], np.eye(3)), -1, -2)
        nu0 = rot.log_map(R_meas @ np.swapaxes(R_hat, -1, -2))
        if x_lin is not None:  # + H delta (R_hat and J at x_lin's features)
            nu0 = nu0 + np.einsum("bnij,bnj->bi", J, dlf)
        HP = np.zeros((B, 3, P.shape[-1]))
        Hdx = np.zeros((B, 3))
        for i in range(N):
            fi = slice(sf0 + 3 * i, sf0 + 3 * i + 3)
            HP += J[:, i] @ P[:, fi, :]
        S = np.zeros((B, 3, 3))
        for i in range(N):
            fi = slice(sf0 + 3 * i, sf0 + 3 * i + 3)
            S += HP[:, :, fi] @ np.swapaxes(J[:, i], -1, -2)
        R0 = np.nan_to_num(fe.cov_frame[:, k]) * att_inflation
        absorb(HP, S + R0, nu0 - Hdx, ok0)
    elif use_att:
        ok0 = np.all(np.isfinite(fe.q_TI[:, k]), axis=-1) & active
        qm = np.where(ok0[:, None], fe.q_TI[:, k], q_hat)
        R0 = np.nan_to_num(fe.cov_TI[:, k] + (att_inflation - 1.0) * fe.cov_frame[:, k])
        HP = P[:, sa, :]
        nu0 = rot.boxminus(qm, q_hat) + (0.0 if x_lin is None else dl[:, sa])
        absorb(HP, HP[:, :, sa] + R0, nu0 - dx[:, sa], ok0)
    else:
        ok0 = np.zeros(B, dtype=bool)
    for i in range(N):
        fi = slice(sf0 + 3 * i, sf0 + 3 * i + 3)
        HP = Hth[:, i] @ P[:, sa, :] + P[:, sr, :] + R_LT @ P[:, fi, :]
        S = HP[:, :, sa] @ HthT[:, i] + HP[:, :, sr] + HP[:, :, fi] @ R_TL + covL[:, i]
        Hdx = (Hth[:, i] @ dx[:, sa, None])[..., 0] + dx[:, sr] + (R_LT @ dx[:, fi, None])[..., 0]
        absorb(HP, S, nu_f[:, i] - Hdx, u[:, i])
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    dof = 3 * (ok0.astype(int) + u.sum(axis=1))
    return lay.boxplus(x, dx[:, : lay.dim]), P, nis, dof, np.zeros(B, dtype=np.int64)


def _feature_cols(HPf_cols: Array, R_LT: Array, B: int, m: int, N: int) -> Array:
    """``(HP)[:, :, f_j] R_LT^T`` for every feature j: (B, m, 3N)."""
    X = HPf_cols.reshape(B, m * N, 3) @ np.swapaxes(R_LT, -1, -2)
    return X.reshape(B, m, 3 * N)
