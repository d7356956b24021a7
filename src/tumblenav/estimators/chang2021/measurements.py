"""Chang 2021 Sec. 2.2-2.3: feature positions and velocities from stereo tracks, the rate
(eq. 29) and the centroid (eq. 30), with first-order covariances.

Per epoch and feature observed by both cameras:

* position in C by general two-ray triangulation
  (:func:`tumblenav.frontends.triangulation.triangulate_two_ray`, any calibrated rig; Chang's
  eq. 31 is its special case for the convergent rig), covariance from the Fisher information
  of the four pixel coordinates, ``Sigma_C = sigma_px^2 (J^T J)^-1`` with ``J = d(u_l, v_l,
  u_r, v_r)/dp`` of the exact projection (each camera in its own frame); rotated into L with
  the rig attitude ``q_CL`` the chaser knows (``rho_L = R_LC rho_C``: the rig origin is the
  chaser's reference point, as in :mod:`tumblenav.simulation`).
* velocity by Chang 2021 eq. 26 from the pixel velocities of both cameras. The pixel
  velocities are **differences of the track's pixels between consecutive epochs** (``(uv_k -
  uv_{k-1}) / dt``, i.e. the optical-flow displacement a KLT front end measures) rather than
  differences of triangulated positions: eq. 26 then weighs the four pixel rates by their own
  (equal) noise and the solve stays linear. Each camera's two rows are written in that
  camera's own frame (notes Sec. 1.6: the printed rows assume a parallel rig)::

      [f, c_u - u_k, 0] R_CkC rho_dot_C = y_k u_dot_k,  [0, c_v - v_k, f] R_CkC rho_dot_C
      = y_k v_dot_k      (from u y = f x + c_u y; y_k: depth in camera k; the printed
                          left-hand side multiplies rho-bar, read rho-dot)

  (the matrix is printed with the pixel column in the third place because Chang's depth is
  ``z``; here the depth axis is ``y``), solved by least squares (divided by ``y_k``, the rows
  have equal pixel-rate noise ``sqrt(2) sigma_px / dt``). The rig rotates w.r.t. L
  (target pointing), so the velocity seen from L is ``R_LC rho_dot_C + (dR_LC/dt) rho_C``
  with ``dR_LC/dt`` differenced from the known ``q_CL`` over the same interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.frontends.triangulation import triangulate_two_ray

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class FeatureTracks:
    """Triangulated features of a whole run, in L.

    p : (n, N, 3) m, NaN where not stereo-observed; P : (n, N, 3, 3) m^2 covariance of p;
    v : (n, N, 3) m/s (eq. 26, from epochs k-1 and k), NaN where unavailable; V : (n, N, 3, 3)
    (m/s)^2; ok_p, ok_v : (n, N) masks.
    """

    p: Array
    P: Array
    v: Array
    V: Array
    ok_p: BoolArray
    ok_v: BoolArray


def _rig_arrays(rig) -> tuple[Array, Array, Array, Array]:
    cams = rig.cameras
    f = np.array([c.focal_px for c in cams])
    pp = np.array([c.principal_point_px for c in cams], dtype=float)
    R = np.stack([c.R_CkC for c in cams])
    o = np.stack([c.p_CkinC for c in cams])
    return f, pp, R, o


def projection_rows(p_C: Array, rig) -> tuple[Array, Array]:
    """Rows ``d(u_k, v_k)/d p_C`` of both cameras (..., 4, 3) (px/m) and the depths ``y_k``
    (..., 2) of ``p_C`` (..., 3) in each camera."""
    f, _, R, o = _rig_arrays(rig)
    rows, depth = [], []
    for k in range(2):
        pk = (p_C - o[k]) @ R[k].T
        x, y, z = pk[..., 0], pk[..., 1], pk[..., 2]
        du = np.stack([1.0 / y, -x / y**2, np.zeros_like(y)], -1) * f[k]
        dv = np.stack([np.zeros_like(y), -z / y**2, 1.0 / y], -1) * f[k]
        rows += [du @ R[k], dv @ R[k]]
        depth.append(y)
    return np.stack(rows, -2), np.stack(depth, -1)


def eq26_rows(uv: Array, p_C: Array, rig) -> Array:
    """Chang 2021 eq. 26's rows divided by each camera's depth (..., 4, 3), so that
    ``A rho_dot_C = uv_dot`` (px/s): ``[f, c - u, 0] R_CkC / y_k`` etc. in camera k's frame."""
    f, pp, R, o = _rig_arrays(rig)
    rows = []
    for k in range(2):
        y = ((p_C - o[k]) @ R[k].T)[..., 1]
        u, v = uv[..., k, 0], uv[..., k, 1]
        zero = np.zeros_like(u)
        ru = np.stack([np.full_like(u, f[k]), pp[k, 0] - u, zero], -1) @ R[k]
        rv = np.stack([zero, pp[k, 1] - v, np.full_like(u, f[k])], -1) @ R[k]
        rows += [ru / y[..., None], rv / y[..., None]]
    return np.stack(rows, -2)


def pixel_variance(meas) -> float:
    """The tracks' pixel noise variance (px^2); noise-free tracks get a floor that keeps the
    covariances invertible."""
    s2 = float(meas.noise_px) ** 2
    return s2 if s2 > 0.0 else 1e-6


def track_noise_ratio(meas) -> float:
    """The tracked sightings' noise variance over the first sightings' (the tracks'
    ``track_noise_px`` over ``noise_px``, squared; 1 where they state no tracked noise): below 1
    for a template tracker such as the image front end with its affine refinement, which holds
    a track to its first-sighting patch more precisely than a new corner is localised and
    matched (tumblenav's, issue 18)."""
    tn = getattr(meas, "track_noise_px", None)
    return 1.0 if tn is None else float(tn) ** 2 / pixel_variance(meas)


def _covariance_C(p_C: Array, rig, s2: float) -> tuple[Array, BoolArray]:
    """``Sigma_C = s2 (J^T J)^-1`` at the points ``p_C`` (..., 3) in C, and where it exists."""
    J, _ = projection_rows(p_C, rig)  # (..., 4, 3)
    info = np.einsum("...ki,...kj->...ij", J, J)
    with np.errstate(all="ignore"):
        det = np.linalg.det(info)
    ok = np.isfinite(det) & (np.abs(det) > 0.0)
    info = np.where(ok[..., None, None], info, np.eye(3))
    return s2 * np.linalg.inv(info), ok


def point_covariance(p_L: Array, q_CL: Array, rig, s2: float) -> Array:
    """The triangulation covariance (m, 3, 3) in L of points at ``p_L`` (m, 3), seen with the
    rig attitude ``q_CL`` (4,) or each with its own (m, 4): the same Fisher information as
    :func:`feature_tracks`, evaluated at the given points instead of the triangulated ones.

    Why (tumblenav, issue 18): at the measured point the covariance grows with the measured
    depth (``Sigma ~ y^4``), so a filter that weighs each triangulated point by it leans to
    the points measured too near: with depth noise ``sigma_y`` the weighted mean is biased by
    ``~ -4 sigma_y^2 / y`` along the line of sight (chang_range20, 20 m, 0.5 px: sigma_y 0.19 m,
    -7 mm; measured -4 to -16 mm on 5 runs, with a position sigma of 2-5 mm). At the filter's
    predicted point the weight does not depend on the measurement's own noise."""
    p_L = np.asarray(p_L, float)
    R_CL = np.broadcast_to(rot.quat_to_matrix(q_CL), (len(p_L), 3, 3))
    P_C, ok = _covariance_C(np.einsum("mij,mj->mi", R_CL, p_L), rig, s2)
    P_L = np.einsum("mji,mjk,mkl->mil", R_CL, P_C, R_CL)
    return np.where(ok[:, None, None], P_L, np.nan)


def slide_covariance(p_L: Array, q_CL: Array, rig, s2: float) -> Array:
    """The covariance (m, 3, 3) in L of points at ``p_L`` (m, 3) moved across the left
    camera's line of sight by ``s2`` px^2 in each of its u and v at their depth ``y``:
    ``s2 (y / f)^2`` along the left camera's x and z axes, nothing along its optical axis.

    Why (tumblenav, issue 18): a track that slides over the surface moves its point in both
    images alike (the right match follows the left patch), so the triangulated point slides
    across the line of sight; :func:`point_covariance` with the same pixel variance would put
    it in depth, where independent noise in the two images goes."""
    cam = rig.left
    R_CL = rot.quat_to_matrix(q_CL)
    y = (np.asarray(p_L, float) @ R_CL.T - cam.p_CkinC) @ cam.R_CkC[1]  # left depth
    R_LCl = R_CL.T @ cam.R_CkC.T  # left camera -> L
    M_L = R_LCl @ np.diag([1.0, 0.0, 1.0]) @ R_LCl.T  # its x and z (y: optical axis)
    scale = np.where(y > 0.0, s2 * (y / cam.focal_px) ** 2, 0.0)
    return scale[:, None, None] * M_L[None]


def feature_tracks(meas) -> FeatureTracks:
    """Positions, velocities and covariances of every stereo-observed feature of a run, in L
    (module docstring). Computed at the observed (epoch, feature) entries only and scattered
    into the (epochs, features) arrays: an image front end creates thousands of track IDs of
    which ~100 are seen at a time (chang2021_close: 3762 IDs over 601 epochs, 2.6 % of the
    entries observed), so the dense computation spent 12.6 of ekf-pose's 36.2 s under cProfile
    on entries nobody reads (1.6 s now; benchmarks/chang2021_estimator_speed.py --profile). Unobserved entries hold: position and velocity NaN, the position
    covariance that of a point 10 m down the rig's y axis turned into L, the velocity
    covariance the identity (as the dense version held them, the covariance to rounding). NaN never leaks into ``ok``."""
    rig = meas.rig
    uv = np.asarray(meas.uv, dtype=float)  # (n, 2, N, 2)
    n, _, N, _ = uv.shape
    obs = np.asarray(meas.observed, bool).all(axis=1) & np.all(np.isfinite(uv), axis=(1, 3))
    f, pp, R, o = _rig_arrays(rig)
    s2 = pixel_variance(meas)
    R_LC = np.swapaxes(rot.quat_to_matrix(meas.q_CL), -1, -2)  # (n, 3, 3)
    fill = np.array([0.0, 10.0, 0.0])  # a safe point for the covariance of unobserved entries
    P_fill, _ = _covariance_C(fill, rig, s2)
    P_L = np.repeat((R_LC @ P_fill @ np.swapaxes(R_LC, -1, -2))[:, None], N, axis=1)  # (n, N, 3, 3)
    p_L = np.full((n, N, 3), np.nan)
    ok_p = np.zeros((n, N), bool)
    p_Cs = np.tile(fill, (n, N, 1))
    ti, fi = np.nonzero(obs)
    if len(ti):
        p_C = triangulate_two_ray(
            uv[ti, 0, fi], uv[ti, 1, fi], f, pp, R[0], o[0], R[1], o[1]
        )  # (M, 3) m, NaN where it fails
        ok = np.all(np.isfinite(p_C), axis=-1)
        p_C = np.where(ok[:, None], p_C, fill)
        P_C, inv_ok = _covariance_C(p_C, rig, s2)
        ok &= inv_ok
        p_Cs[ti, fi] = p_C
        Rt = R_LC[ti]
        P_L[ti, fi] = np.einsum("mij,mjk,mlk->mil", Rt, P_C, Rt)
        p_L[ti[ok], fi[ok]] = np.einsum("mij,mj->mi", Rt[ok], p_C[ok])
        ok_p[ti, fi] = ok

    # eq. 26: pixel velocities by differencing consecutive epochs of the track
    v_L = np.full((n, N, 3), np.nan)
    V_L = np.tile(np.eye(3), (n, N, 1, 1))
    ok_v = np.zeros((n, N), bool)
    if n > 1:
        dt_all = np.diff(meas.t)  # (n-1,)
        ti, fi = np.nonzero(ok_p[1:] & ok_p[:-1])  # epoch ti + 1 and the one before
        dt = dt_all[ti][:, None]  # (M, 1)
        uv_dot = (uv[ti + 1, :, fi] - uv[ti, :, fi]) / dt[:, :, None]  # (M, 2, 2)
        uv_dot = uv_dot.reshape(-1, 4)  # (u_l, v_l, u_r, v_r)
        A = eq26_rows(uv[ti + 1, :, fi], p_Cs[ti + 1, fi], rig)
        AtAi = np.linalg.inv(np.einsum("...ki,...kj->...ij", A, A))
        rhs = np.einsum("...ki,...k->...i", A, uv_dot)
        v_C = np.einsum("...ij,...j->...i", AtAi, rhs)  # rho_dot_C, LS solution of eq. 26
        dR = (R_LC[ti + 1] - R_LC[ti]) / dt[:, :, None]  # (M, 3, 3): dR_LC/dt
        p_mid = 0.5 * (p_Cs[ti + 1, fi] + p_Cs[ti, fi])
        v = np.einsum("mij,mj->mi", R_LC[ti + 1], v_C) + np.einsum("mij,mj->mi", dR, p_mid)
        V_C = (2.0 * s2 / dt[..., None] ** 2) * AtAi  # pixel rates: 2 sigma^2 / dt^2
        V = np.einsum("mij,mjk,mlk->mil", R_LC[ti + 1], V_C, R_LC[ti + 1])
        good = np.all(np.isfinite(v), axis=-1)
        v_L[ti[good] + 1, fi[good]] = v[good]
        V_L[ti[good] + 1, fi[good]] = V[good]
        ok_v[ti + 1, fi] = good
    return FeatureTracks(p=p_L, P=P_L, v=v_L, V=V_L, ok_p=ok_p, ok_v=ok_v)


def rate_eq29(d_rho: Array, d_rho_dot: Array, V: Array) -> tuple[Array, Array] | None:
    """Chang 2021 eq. 29: least-squares ``omega`` (in L) from the rigid-body relation
    ``d_rho_dot_i = omega x d_rho_i`` on difference vectors (M, 3) with velocity-noise
    covariances ``V`` (M, 3, 3); returns ``(omega_L, covariance)`` (sandwich of the
    ``1/tr(V_i)``-weighted solve), or None when the difference vectors do not fix ``omega``
    (fewer than two, or all parallel)."""
    if len(d_rho) < 2:
        return None
    Mi = -rot.skew(d_rho)  # d_rho_dot = -[d_rho x] omega  (eq. 29: M = [d_rho x], rhs -d_rho_dot)
    w = 3.0 / np.trace(V, axis1=-2, axis2=-1)
    H = np.einsum("m,mki,mkj->ij", w, Mi, Mi)
    ev = np.linalg.eigvalsh(H)
    if not ev[0] > 1e-9 * ev[-1]:
        return None
    Hi = np.linalg.inv(H)
    omega = Hi @ np.einsum("m,mki,mk->i", w, Mi, d_rho_dot)
    S = np.einsum("m,mki,mkl,mlj->ij", w**2, Mi, V, Mi)
    C = Hi @ S @ Hi
    return omega, 0.5 * (C + C.T)


@dataclass(frozen=True)
class PoseFix:
    """A q-method pose measurement of one epoch (Chang 2021 eq. 27-28 and 30).

    q_ThatL : attitude (4,); P_att : its covariance (3, 3) rad^2 (left error in That);
    rho_bar : weighted centroid of the used features in L (m); s_bar : the same weighted
    centroid of their registered positions in That (m); C_rho_bar, C_s_bar : their covariances;
    used : (M,) mask over the input features (outliers dropped); outliers : how many.
    """

    q_ThatL: Array
    P_att: Array
    rho_bar: Array
    s_bar: Array
    C_rho_bar: Array
    C_s_bar: Array
    used: BoolArray
    outliers: int


def _fix(rho, Sr, s, Ss, reference):
    from tumblenav.estimators.chang2021.qmethod import q_method, q_method_covariance

    w = 3.0 / (np.trace(Sr, axis1=-2, axis2=-1) + np.trace(Ss, axis1=-2, axis2=-1))
    if reference == "feature":  # Chang 2021 eq. 27: difference vectors from one feature
        j = int(np.argmax(w))
        rho_ref, s_ref = rho[j], s[j]
    else:  # a virtual reference feature: the weighted centroid
        rho_ref, s_ref = w @ rho / w.sum(), w @ s / w.sum()
    a, b = s - s_ref, rho - rho_ref  # in That and in L
    q, _ = q_method(a, b, w)  # q_ThatL: a ~ R_ThatL b
    R = rot.quat_to_matrix(q)
    N = Ss + R @ Sr @ R.T  # covariance of each residual a_i - R b_i (in That)
    P, H = q_method_covariance(q, b, w, N)
    ev = np.linalg.eigvalsh(H)
    return q, R, P, ev, w, a - b @ R.T, N


def pose_fix(
    rho: Array,
    S_rho: Array,
    s: Array,
    S_s: Array,
    reference: str = "centroid",
    gate_probability: float = 0.9999,
    min_features: int = 3,
) -> PoseFix | None:
    """Attitude ``q_ThatL`` of the feature set ``rho`` (M, 3) in L (covariances ``S_rho``)
    against the registered positions ``s`` (M, 3) in That (``S_s``), by Davenport's q-method
    on difference vectors (Chang 2021 eq. 27-28) with scalar weights ``3 / tr(S_rho_i +
    S_s_i)``; features whose residual fails the chi-square gate (3 dof) are dropped and the fit
    redone once. None when fewer than ``min_features`` remain or the vectors do not fix the
    rotation (collinear: the information matrix has a near-zero eigenvalue)."""
    M = len(rho)
    if M < min_features:
        return None
    from scipy.stats import chi2

    used = np.ones(M, bool)
    gate = chi2.ppf(gate_probability, 3)
    # outliers one at a time, the worst first (one bad match skews the first fit, so that a
    # single pass would throw out good features with it), at most a quarter of the set
    while True:  # ends: each pass drops one feature, and at most M // 4 are dropped
        q, R, P, ev, w, res, N = _fix(rho[used], S_rho[used], s[used], S_s[used], reference)
        if not (np.isfinite(ev).all() and ev[0] > 1e-6 * ev[-1] and np.isfinite(P).all()):
            return None
        d2 = np.einsum("mi,mij,mj->m", res, np.linalg.inv(N), res)
        worst = int(np.argmax(d2))
        if d2[worst] <= gate:
            break
        if M - used.sum() >= M // 4 or used.sum() <= min_features:
            return None  # too many outliers to trust the rest
        used[np.flatnonzero(used)[worst]] = False
    W = w / w.sum()
    rho_bar = W @ rho[used]
    s_bar = W @ s[used]
    C_rho = np.einsum("m,mij->ij", W**2, S_rho[used])
    C_s = np.einsum("m,mij->ij", W**2, S_s[used])
    return PoseFix(q, P, rho_bar, s_bar, C_rho, C_s, used, int(M - used.sum()))
