"""The photogrammetric frame G (Hu 2024 Sec. 3.1): its definition from three features, each\nepoch's attitude of G fitted to the visible features (weighted Kabsch, then the\nfull-covariance fit), and the joint fit of the features' G coordinates."""

from __future__ import annotations

from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends import _points_kernel
from tumblenav.frontends.photogrammetric import g_frame_from_points, triplet_score
from tumblenav.frontends.stereo_points.rates import _skew

Array = NDArray[np.float64]


def weighted_kabsch(
    p_C: Array,
    g_G: Array,
    w: Array,
    cov_C: Array | None = None,
    cov_g: Array | None = None,
    run_len: int = 1,
    noise: dict | None = None,
) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
    """Rigid alignment ``p_C ~ R_CG g_G + o_C`` (weighted least squares), batched.

    p_C, g_G : (B,K,3); w : (B,K) weights (0 = not used). Returns R_GC (B,3,3), o_C (B,3),
    the covariance of the G attitude error (in G, rad^2), and a validity mask (>= 3
    non-collinear points).

    Without ``cov_C`` the fit is the isotropically weighted Kabsch solution and its
    covariance the information form ``(sum w (|a|^2 I - a a^T))^-1`` (points of variance
    ``1/w`` per axis). With the points' covariances ``cov_C`` (B,K,3,3), and optionally the
    template's ``cov_g`` (B // run_len, K, 3, 3; in G), that fit is refined by Gauss-Newton
    in the metric of the residuals' covariance (``_points_kernel.align_rigid``;
    ``run_len``: the alignments are runs of that many consecutive epochs, each started from
    the previous one's result) and the covariance is the fit's. Why (beyond the paper, whose eq. 6-7
    build G from three points): a stereo point's error is an ellipsoid along its line of
    sight, ``range^2 sigma / b`` deep and ``range sigma`` wide; the isotropic fit lets the
    depth error tilt the frame (tens of degrees at 190 m with b = 1 m, sigma = 2e-5 rad),
    while the lateral positions of points spread in depth fix the tilt to a fraction of a
    degree, as in a perspective pose fit. Alignments whose refined cost fails its
    chi-square gate keep the Kabsch fit and covariance. ``noise``, if given, receives
    ``cov_G``, the points' own noise's share of the covariance (in G; the whole of it without
    ``cov_g`` or where no fit passed its gate): the share that is independent between
    epochs.
    """
    p_C = np.ascontiguousarray(p_C, dtype=float)
    g_G = np.ascontiguousarray(g_G, dtype=float)
    w = np.ascontiguousarray(w, dtype=float)
    if cov_C is not None:
        cov_g = np.zeros((len(w) // run_len,) + w.shape[1:] + (3, 3)) if cov_g is None else cov_g
        R_CG, o, cov_t, ok, _, cov_n = _points_kernel.align_rigid(
            p_C,
            g_G,
            np.ascontiguousarray(cov_C, dtype=float),
            np.ascontiguousarray(cov_g, dtype=float),
            w,
            4,
            run_len,
        )
        eye = np.eye(3)
        R_CG = np.where(ok[:, None, None], R_CG, eye)
        o = np.where(ok[:, None], o, 0.0)
        cov_t = np.where(ok[:, None, None], cov_t, eye)
        R_GC = np.swapaxes(R_CG, -1, -2)
        cov_G = R_GC @ cov_t @ np.swapaxes(R_GC, -1, -2)
        if noise is not None:
            cov_n = np.where(ok[:, None, None], cov_n, eye)
            noise["cov_G"] = R_GC @ cov_n @ np.swapaxes(R_GC, -1, -2)
        return R_GC, o, cov_G, ok
    # sums over the points in a compiled loop (the numpy version of these few lines made
    # full-size temporaries of every (run, epoch, feature) vector; same formulas below)
    Hm, pc, gc, info, cnt, sw = _points_kernel.kabsch_moments(p_C, g_G, w)
    # Hm = sum w g p^T of the centred points, info = sum w (|a|^2 I - a a^T), a = p - pc
    ok = (cnt >= 3) & (sw > 0)
    # the proper rotation of the SVD solution (V diag(1, 1, det) U^T), by Horn's quaternion
    # method in a compiled loop (twice as fast as the batched SVD; test against it)
    R_CG, sv_ratio = _points_kernel.kabsch_rotation(Hm)
    ok &= sv_ratio > 1e-9  # not collinear
    o = pc - np.einsum("bij,bj->bi", R_CG, gc)
    # info: information of a small rotation of the lever arms a_i (C frame),
    # sum w [a x]^T [a x] with [a x]^T [a x] = |a|^2 I - a a^T
    eye = np.eye(3)
    info = np.where(ok[:, None, None], info, eye)
    cov_t = np.linalg.inv(info + 1e-12 * eye)
    R_GC = np.swapaxes(R_CG, -1, -2)
    cov_G = R_GC @ cov_t @ np.swapaxes(R_GC, -1, -2)
    if noise is not None:
        noise["cov_G"] = cov_G
    return R_GC, o, cov_G, ok


def _best_triplet_batch(
    p: Array, usable: NDArray[np.bool_]
) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Per run, the visible triplet with the largest smallest-altitude; (B,3) indices."""
    B, N, _ = p.shape
    trip = np.array(list(combinations(range(N), 3))) if N >= 3 else np.zeros((0, 3), int)
    if len(trip) > 4000:  # many features: search among the 20 farthest from the centroid
        c = np.nanmean(p, axis=1, keepdims=True)
        dist = np.where(usable, np.linalg.norm(p - c, axis=-1), -1.0)
        far = np.argsort(-dist, axis=1)[:, :20]
        sub = np.take_along_axis(p, far[..., None], axis=1)
        subu = np.take_along_axis(usable, far, axis=1)
        idx, ok = _best_triplet_batch(sub, subu)
        return np.take_along_axis(far, idx, axis=1), ok
    m1, m2, m3 = p[:, trip[:, 0]], p[:, trip[:, 1]], p[:, trip[:, 2]]
    score = np.where(np.all(usable[:, trip], axis=-1), triplet_score(m1, m2, m3), -1.0)
    score = np.nan_to_num(score, nan=-1.0)
    best = np.argmax(score, axis=1)
    return trip[best], score[np.arange(B), best] > 1e-6


def photogrammetric_frames(
    p_C: Array,
    cov_C: Array,
    usable: NDArray[np.bool_],
    full_cov: bool = True,
    stop_after: int = 0,
    info: dict | None = None,
    stop_every: int = 1,
) -> tuple[Array, Array, Array, NDArray[np.bool_], NDArray[np.bool_]]:
    """G attitude R_GC (B,n,3,3) with covariance, the G template (B,N,3), its final mask and
    the mask of features catalogued by each epoch (B,n,N). With ``stop_after`` > 0 the
    attitudes are computed for the first ``stop_after`` epochs from G's definition only,
    rounded up to a multiple of ``stop_every`` (NaN after; see ``process``, the template's
    refinement). ``info``, if given, receives ``cov_template`` (B,N,3,3), the template's
    covariance in G, ``cov_G_noise`` (B,n,3,3), the points' own noise's share of the G
    attitudes' covariance (``weighted_kabsch``'s ``noise``), and with ``stop_after``: ``first`` (B,), G's first epoch (n where
    none), and ``stop`` (B,), the first epoch without an attitude."""
    B, n, N, _ = p_C.shape
    template = np.full((B, N, 3), np.nan)
    # covariance of the template coordinates (in G): the point's at its first sighting,
    # plus what that epoch's G attitude error does to it (for features catalogued later)
    cov_tmpl = np.zeros((B, N, 3, 3))
    known = np.zeros((B, N), dtype=bool)
    has_G = np.zeros(B, dtype=bool)
    w_all = np.where(usable, 1.0 / np.maximum(np.trace(cov_C, axis1=-2, axis2=-1), 1e-30), 0.0)
    known_at = np.zeros((B, n, N), dtype=bool)  # catalogued by epoch k (causal)
    # Pass 1 (cheap loop): define G where it is not defined yet (Hu 2024 eq. 6-7), and give
    # features seen for the first time their G coordinates from the G recovered at that epoch.
    for k in range(n):
        u = usable[:, k]
        new = ~has_G & (u.sum(axis=1) >= 3)
        if new.any():
            idx, okt = _best_triplet_batch(p_C[new, k], u[new])
            runs = np.flatnonzero(new)[okt]
            idx = idx[okt]
            if len(runs):
                pk = p_C[runs, k]
                m = [pk[np.arange(len(runs)), idx[:, j]] for j in range(3)]
                Rg = g_frame_from_points(m[0], m[1], m[2])
                g = (pk - m[0][:, None]) @ np.swapaxes(Rg, -1, -2)
                template[runs] = np.where(u[runs][..., None], g, np.nan)
                Rg3 = Rg[:, None]
                cg_ = Rg3 @ np.nan_to_num(cov_C[runs, k]) @ np.swapaxes(Rg3, -1, -2)
                cov_tmpl[runs] = np.where(u[runs][..., None, None], cg_, 0.0)
                known[runs] = u[runs]
                has_G[runs] = True
        fresh_runs = has_G & np.any(u & ~known, axis=1) & ((u & known).sum(axis=1) >= 3)
        if fresh_runs.any():
            r_ = np.flatnonzero(fresh_runs)
            w = np.where(u[r_] & known[r_], w_all[r_, k], 0.0)
            Rgc, o, cgk, ok = weighted_kabsch(
                p_C[r_, k],
                template[r_],
                w,
                cov_C[r_, k] if full_cov else None,
                cov_tmpl[r_] if full_cov else None,
            )
            r_, Rgc, o, cgk = r_[ok], Rgc[ok], o[ok], cgk[ok]
            fresh = u[r_] & ~known[r_]
            g = (p_C[r_, k] - o[:, None]) @ np.swapaxes(Rgc, -1, -2)
            template[r_] = np.where(fresh[..., None], g, template[r_])
            Rg3 = Rgc[:, None]
            lever = _skew(
                g - np.nanmean(np.where(known[r_][..., None], template[r_], np.nan), 1)[:, None]
            )
            cg_ = Rg3 @ np.nan_to_num(cov_C[r_, k]) @ np.swapaxes(Rg3, -1, -2) + lever @ cgk[
                :, None
            ] @ np.swapaxes(lever, -1, -2)
            cov_tmpl[r_] = np.where(fresh[..., None, None], np.nan_to_num(cg_), cov_tmpl[r_])
            known[r_] |= fresh
        known_at[:, k] = known
    # Pass 2 (vectorised over runs and epochs): G at every epoch from the visible features
    # catalogued by then (Kabsch), so G is kept through occlusions of the defining triplet.
    use = usable & known_at
    if stop_after > 0:
        first = np.where(
            np.any(known_at, axis=2).any(axis=1), np.argmax(known_at.any(axis=2), 1), n
        )
        stop = -(-(first + stop_after) // stop_every) * stop_every
        use &= (np.arange(n)[None, :] < stop[:, None])[..., None]
        if info is not None:
            info["first"], info["stop"] = first, stop
    if info is not None:
        info["cov_template"] = cov_tmpl
    w = np.where(use, w_all, 0.0).reshape(B * n, N)
    tmpl = np.broadcast_to(template[:, None], (B, n, N, 3)).reshape(B * n, N, 3)
    noise: dict = {}
    Rgc, _, cg, ok = weighted_kabsch(
        p_C.reshape(B * n, N, 3),
        tmpl,
        w,
        cov_C.reshape(B * n, N, 3, 3) if full_cov else None,
        # The template's errors are fixed in G, so the fit's error from them is a bias that
        # changes only as the weights turn with the view, and then it reads as rotation
        # (near range, where they dominate the lateral point noise: attitude 0.28 deg at a
        # constant 17 m against 0.05 deg with the Kabsch fit). Isotropic in the fit's metric,
        # with their largest variance bounded by the trace (per axis, conservative; the
        # mean variance, trace / 3, measured worse: NEES/dof 1.6 at 17 m), their effect
        # stays nearly constant in G, which the principal frame absorbs.
        np.trace(cov_tmpl, axis1=-2, axis2=-1)[..., None, None] * np.eye(3),
        run_len=n,
        noise=noise,
    )
    ok = ok.reshape(B, n)
    R_GC = np.where(ok[..., None, None], Rgc.reshape(B, n, 3, 3), np.nan)
    cov_G = np.where(ok[..., None, None], cg.reshape(B, n, 3, 3), np.nan)
    if info is not None:
        info["cov_G_noise"] = np.where(
            ok[..., None, None], noise["cov_G"].reshape(B, n, 3, 3), np.nan
        )
    return R_GC, cov_G, template, known, known_at


def joint_features(
    Phi: Array,
    R_LG: Array,
    p: Array,
    cov: Array,
    cov_G: Array,
    use: NDArray[np.bool_],
    f0: Array,
    passes: int = 2,
    cov_dev: Array | None = None,
    free_attitudes: bool = False,
) -> tuple[Array, Array, Array, NDArray[np.int64]] | None:
    """Batch least squares for a rigid body's features about its mass centre, from m epochs
    of points ``p`` (m,N,3) in a frame L, covariances ``cov`` (m,N,3,3), the measured
    attitudes ``R_LG`` (m,3,3) of G (covariance ``cov_G`` (m,3,3), error in G) and a
    translation model linear in K parameters, ``r(j) = Phi[j] a`` (Phi (m,3,K)):

        ``p_i(j) = Phi[j] a + R_LG(j) f_i``

    linear in ``[a, f_1 .. f_N]``. The rotation separates the features' common shift (the
    mass centre) from the translation; each feature is fitted to all its views, so the
    depth errors of a stereo point average over the viewing directions. Weights: each
    point's covariance plus what the G attitude error does to it through its lever arm
    ``f_i`` (``f0`` (N,3) at first, then the solution: ``passes`` solutions, one
    re-linearisation by default; one pass where ``f0`` is already about the mass centre); the
    covariance is scaled by the reduced chi-square when that exceeds one (beyond Hu 2024,
    which takes the features from one stereo sighting).

    ``cov_dev`` (m,3,m,3): the covariance of the translation model's error at the epochs,
    ``r(j) - Phi[j] a`` (what a random force does to the Hill motion over the window, common
    to every point of an epoch and correlated between epochs). The estimate stays the one
    above; its covariance gains what that error does to it, ``N^-1 S Q S^T N^-1`` with
    ``S = sum_i A_ij^T W_ij`` per epoch, and the reduced chi-square is taken against the
    residuals' expectation with it (beyond Hu 2024: a fit that takes the Hill motion as
    exact over 30 s while a force of 1e-9 m^2/s^3 moves the mass centre by 3 mm reported
    the features' common shift to 0.3 mm, issue 18).

    ``free_attitudes``: each epoch's attitude is an unknown too, ``R_LG(j) exp([psi_j x])``
    (:func:`_joint_features_free`), rather than taken as measured with independent errors
    ``cov_G``: the measured attitudes come from the same points and from the template,
    whose errors are fixed in G and so correlated over the window; taken as independent
    they made the features' shape over-confident (NEES/dof 2.5 at the filter's start on
    hu2024 with small disturbances, 0.7-1.0 with the true G attitudes; issue 18).

    Uses the features seen (``use`` (m,N)) at 3 epochs or more. Returns the translation
    parameters ``a`` (K,), the features ``f`` (nf,3), their covariance (3nf,3nf) and their
    indices (nf,), or None (fewer than 3 such features or 12 points, singular)."""
    K = Phi.shape[2]
    fitted = use.sum(axis=0) >= 3
    use = use & fitted[None, :]
    if use.sum() < 12 or fitted.sum() < 3:
        return None
    idx = np.flatnonzero(fitted)
    nf = len(idx)
    dim = K + 3 * nf
    col = np.where(use, np.cumsum(fitted) - 1, -1).astype(np.int64)  # feature's block
    if free_attitudes:
        return _joint_features_free(Phi, R_LG, p, cov, cov_G, col, f0[idx], idx, passes, cov_dev)
    args = (
        np.ascontiguousarray(Phi, dtype=float),
        np.ascontiguousarray(R_LG, dtype=float),
        np.ascontiguousarray(np.nan_to_num(p), dtype=float),
        np.ascontiguousarray(np.nan_to_num(cov), dtype=float),
        np.ascontiguousarray(np.nan_to_num(cov_G), dtype=float),
        col,
    )
    f = np.nan_to_num(f0[idx])
    for _ in range(passes):
        lever = f  # the lever arms of this pass's weights
        # sums in a compiled loop (the numpy form made (M,3,3) temporaries: 4 ms per run)
        Nm, rhs, bb, cnt = _points_kernel.joint_normal_equations(*args, np.ascontiguousarray(f), nf)
        try:
            Ninv = np.linalg.inv(Nm)
        except np.linalg.LinAlgError:
            return None
        if not (np.all(np.isfinite(Ninv)) and np.all(np.isfinite(rhs))):
            return None
        x = Ninv @ rhs
        f = x[K:].reshape(nf, 3)
    chi2 = bb - x @ rhs  # at the solution, in the last weights
    dof = max(3 * cnt - dim, 1)
    cov_x = Ninv
    expect = float(dof)
    if cov_dev is not None:
        S, Wsum = _epoch_sums(Phi, R_LG, cov, cov_G, col, lever, K, dim)
        m = len(col)
        Q = cov_dev.reshape(3 * m, 3 * m)
        SQS = S @ Q @ S.T
        cov_x = Ninv + Ninv @ SQS @ Ninv
        # E[residual' W residual] with the error: tr(W Q) over the epochs less the fit's share
        Qd = np.einsum("jajb->jab", cov_dev)
        expect += float(np.einsum("jab,jba->", Wsum, Qd) - np.trace(Ninv @ SQS))
    cov_f = cov_x[K:, K:] * max(1.0, chi2 / max(expect, 1.0))
    if not np.all(np.isfinite(cov_f)):
        return None
    return x[:K], f, cov_f, idx


def _epoch_sums(
    Phi: Array,
    R_LG: Array,
    cov: Array,
    cov_G: Array,
    col: NDArray[np.int64],
    f: Array,
    K: int,
    dim: int,
) -> tuple[Array, Array]:
    """Per epoch j of :func:`joint_features`' rows: ``S[:, j] = sum_i A_ij^T W_ij`` (dim, m, 3,
    returned as (dim, 3m)) and ``sum_i W_ij`` (m,3,3), with the weights of the lever arms
    ``f`` (as ``_points_kernel.joint_normal_equations``, points whose covariance is not
    positive definite left out)."""
    m = len(col)
    jj, ii = np.nonzero(col >= 0)
    c = col[jj, ii]
    lev = R_LG[jj] @ _skew(f[c])
    C = np.nan_to_num(cov)[jj, ii] + lev @ np.nan_to_num(cov_G)[jj] @ np.swapaxes(lev, -1, -2)
    ok = np.linalg.det(C) > 0
    jj, c, C = jj[ok], c[ok], C[ok]
    W = np.linalg.inv(C)
    S = np.zeros((m, dim, 3))
    PW = np.swapaxes(Phi[jj], -1, -2) @ W  # (M, K, 3)
    for q in range(K):
        np.add.at(S, (jj, q), PW[:, q])
    RW = np.swapaxes(R_LG[jj], -1, -2) @ W
    for a in range(3):
        np.add.at(S, (jj, K + 3 * c + a), RW[:, a])
    Wsum = np.zeros((m, 3, 3))
    np.add.at(Wsum, jj, W)
    return np.transpose(S, (1, 0, 2)).reshape(dim, 3 * m), Wsum


def _joint_features_free(
    Phi: Array,
    R_LG: Array,
    p: Array,
    cov: Array,
    cov_G: Array,
    col: NDArray[np.int64],
    f0: Array,
    idx: NDArray[np.int64],
    passes: int,
    cov_dev: Array | None,
) -> tuple[Array, Array, Array, NDArray[np.int64]] | None:
    """:func:`joint_features` with every epoch's attitude an unknown (a bundle adjustment):
    ``p_i(j) = Phi[j] a + R_LG(j) exp([psi_j x]) f_i``, Gauss-Newton from ``psi = 0`` and
    ``f0`` (nf,3) over ``passes + 1`` linearisations, each epoch's ``psi_j`` eliminated by
    its Schur complement (epochs with fewer than three points left out). Weights: the
    points' covariances ``cov`` alone.

    A common rotation of the features against every ``psi_j`` changes no prediction. It is
    fixed by a prior on each ``psi_j`` of ``m`` times the measured attitude's covariance
    ``cov_G`` (``m`` the epochs used): the features' common rotation then follows the
    measured G attitudes (the G the least squares' inertia is in) to about one epoch's
    attitude error, as correlated errors allow, and the epochs that see disjoint sets of
    features (self-occlusion) stay tied. The covariance is the solution's, with the
    translation model's error ``cov_dev`` and the reduced chi-square as in
    :func:`joint_features`."""
    m = len(col)
    K = Phi.shape[2]
    nf = len(f0)
    dim = K + 3 * nf
    have = (col >= 0).sum(axis=1) >= 3
    col = np.where(have[:, None], col, -1)
    jj, ii = np.nonzero(col >= 0)
    c = col[jj, ii]
    if len(jj) < 12 or len(np.unique(c)) < nf:
        return None
    C = np.nan_to_num(cov)[jj, ii]
    if not np.all(np.linalg.det(C) > 0):
        return None
    W = np.linalg.inv(C)
    y = np.nan_to_num(p)[jj, ii]
    n_have = int(have.sum())
    Pinv = np.zeros((m, 3, 3))  # the prior's information on each psi_j
    CG = np.nan_to_num(cov_G[have]) * n_have
    if not np.all(np.linalg.det(CG) > 0):
        return None
    Pinv[have] = np.linalg.inv(CG)
    f = np.nan_to_num(f0).copy()
    R = R_LG.copy()
    a = np.zeros(K)
    psi = np.zeros((m, 3))  # the attitudes' corrections so far
    M = len(jj)
    rows = np.arange(M)
    for it in range(passes + 1):
        fc = f[c]
        Rj = R[jj]
        Ax = np.zeros((M, 3, dim))
        Ax[:, :, :K] = Phi[jj]
        for q in range(3):  # the feature's block: R_LG(j)
            Ax[rows, :, K + 3 * c + q] = Rj[:, :, q]
        Ap = -Rj @ _skew(fc)  # d p / d psi_j
        r = y - (Phi[jj] @ a) - (Rj @ fc[..., None])[..., 0]
        AxW = np.swapaxes(Ax, -1, -2) @ W  # (M, dim, 3)
        ApW = np.swapaxes(Ap, -1, -2) @ W  # (M, 3, 3)
        Nxx = np.einsum("mia,mak->ik", AxW, Ax)
        bx = np.einsum("mia,ma->i", AxW, r)
        Nxp = np.zeros((m, dim, 3))
        np.add.at(Nxp, jj, AxW @ Ap)
        Npp = Pinv.copy()
        np.add.at(Npp, jj, ApW @ Ap)
        bp = -(Pinv @ psi[..., None])[..., 0]
        np.add.at(bp, jj, (ApW @ r[..., None])[..., 0])
        Npp[~have] = np.eye(3)
        Nppi = np.linalg.inv(Npp)
        Nppi[~have] = 0.0
        XN = Nxp @ Nppi  # (m, dim, 3)
        Nr = Nxx - np.einsum("jia,jka->ik", XN, Nxp)
        br = bx - np.einsum("jia,ja->i", XN, bp)
        try:
            H = np.linalg.inv(Nr)
        except np.linalg.LinAlgError:
            return None
        dx = H @ br
        dpsi = (Nppi @ (bp - np.einsum("jia,i->ja", Nxp, dx))[..., None])[..., 0]
        if not (np.all(np.isfinite(dx)) and np.all(np.isfinite(dpsi))):
            return None
        a = a + dx[:K]
        f = f + dx[K:].reshape(nf, 3)
        if it < passes:
            R = R @ _exp_so3(dpsi)
            psi = psi + dpsi
    # the residuals (linearised) and the fit's covariance at the last linearisation
    r = r - np.einsum("mak,k->ma", Ax, dx) - (Ap @ dpsi[jj][..., None])[..., 0]
    chi2 = float(np.einsum("ma,mab,mb->", r, W, r))
    expect = float(max(3 * M - dim - 3 * n_have, 1))
    cov_x = H
    if cov_dev is not None:
        Sx = np.zeros((m, dim, 3))
        np.add.at(Sx, jj, AxW)
        Sp = np.zeros((m, 3, 3))
        np.add.at(Sp, jj, ApW)
        Wsum = np.zeros((m, 3, 3))
        np.add.at(Wsum, jj, W)
        S = Sx - XN @ Sp  # what an epoch's common offset does to the reduced right side
        S2 = np.transpose(S, (1, 0, 2)).reshape(dim, 3 * m)
        SQS = S2 @ cov_dev.reshape(3 * m, 3 * m) @ S2.T
        cov_x = H + H @ SQS @ H
        Qd = np.einsum("jajb->jab", cov_dev)
        absorbed = np.einsum("jae,jac,jcd,jde->", Sp, Nppi, Sp, Qd) + np.trace(H @ SQS)
        expect += float(np.einsum("jab,jba->", Wsum, Qd) - absorbed)
    cov_f = cov_x[K:, K:] * max(1.0, chi2 / max(expect, 1.0))
    if not np.all(np.isfinite(cov_f)):
        return None
    return a, f, cov_f, idx


def _exp_so3(v: Array) -> Array:
    """Rotation matrices (…,3,3) ``exp([v x])`` (Rodrigues)."""
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K_ = _skew(v)
    small = th < 1e-12
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0, np.sin(ths) / ths)
    B = np.where(small, 0.5, (1 - np.cos(ths)) / ths**2)
    return np.eye(3) + A * K_ + B * (K_ @ K_)
