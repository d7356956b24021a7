"""Stereo feature points -> measurements for the Hu 2024 filter, batched over Monte Carlo runs.

From raw pixel tracks (:class:`tumblenav.measurements.StereoMeasurements`) of B runs that share a
rig and a time grid, this front end computes, for every run and epoch:

1. triangulated feature points in the rig frame C and in L, with their first-order
   covariances (Hu 2024 eq. 1 corrected; two-ray triangulation for a convergent rig);
2. the photogrammetric frame G (Hu 2024 eq. 6-7) from the best-conditioned triplet at the first
   epoch with three features, kept through occlusions by rigid alignment of any >= 3 visible
   features whose G coordinates are known (weighted Kabsch), with the covariance of its
   attitude;
3. the angular rate of G relative to I (Hu 2024 eq. 15-16) from a local linear fit of the G
   attitude over +-h epochs (the chaser's rotation removed through the known R_CI);
4. the least-squares identification of the normalised inertia and angular momentum
   (Hu 2024 eq. 9-14), accumulated over time (growing batch). Beyond the paper, each epoch is
   weighted by the inverse variance of its rate, so far-away (noisy) epochs do not spoil it;
   the template is refined on a schedule (``template_refine_s``) and each refinement
   reprocesses the batch's past rows (``_refine_template``);
5. the unique principal-axis frame (DPACF, Hu 2024 eq. 17) and the attitude measurement
   ``q_TI = q_TG (x) q_GI`` (Hu 2024 eq. 31) with a first-order covariance: eigenvector
   perturbation of the identified inertia plus the G attitude noise.

All arrays have leading shape (B, n) (runs, epochs); unavailable values are NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from tumblenav import rotations as rot
from tumblenav.frontends import _points_kernel
from tumblenav.frontends.inertia import inertia_design, principal_frame
from tumblenav.frontends.photogrammetric import g_frame_from_points, triplet_score
from tumblenav.frontends.triangulation import (
    triangulate_parallel,
    triangulate_two_ray,
    triangulation_jacobian,
)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FrontEndSettings:
    rate_half_window: int = 10  # epochs on each side of the local rate fit
    min_ls_epochs: int = 20  # epochs of rate data before the inertia is trusted
    max_condition: float = 1e8  # of the column-scaled normal equations
    min_eigengap: float = 0.02  # relative gap between principal moments for a defined DPACF
    max_dpacf_sigma_rad: float = 0.05  # the DPACF frame is used once its 1-sigma error is below
    ls_every: int = 10  # epochs between least-squares solutions
    g_fit: str = "full"  # G attitude: "full" (points' covariances) or "kabsch" (isotropic)
    # refit the template over this much data after G's definition (seconds; one value or
    # several, each a refinement; 0 or empty: never)
    template_refine_s: float | tuple[float, ...] = 0.0
    # after the last refinement, the least squares' rows from the unbiased (cubic) rate fit
    unbiased_last: bool = True


class StereoPointsTuning(BaseModel):
    """Settings of the stereo-points front end (Hu 2024 Sec. 2-3: triangulation, the
    photogrammetric frame G, the inertia least squares and the DPACF frame), under
    ``estimator.tuning.frontend`` of ekf-dpacf and ekf-baseline (the same keys at the top of
    ``estimator.tuning`` are still read, as before)."""

    model_config = ConfigDict(extra="forbid")
    rate_half_window: int = Field(
        10, ge=1, description="half-width (epochs) of the local fit that gives the rate of G"
    )
    min_ls_epochs: int = Field(
        50, ge=3, description="epochs of rate data needed before the inertia is trusted"
    )
    g_attitude_fit: Literal["full", "kabsch"] = Field(
        "full",
        description="G attitude per epoch: 'full' refines the Kabsch fit in the metric of the "
        "triangulated points' covariances (beyond the paper); 'kabsch' is the isotropic fit",
    )
    dpacf_emit_sigma_rad: float = Field(
        0.2,
        gt=0,
        description="the front end gives a DPACF frame (Hu 2024 Fig. 5, the filter's attitude "
        "measurement) once its 1-sigma is below this; the filter itself starts at "
        "max_dpacf_sigma_rad",
    )
    template_refine_s: float | list[float] = Field(
        [8.0, 10.0, 30.0],
        description="the front end refits its template (the features' G coordinates, from "
        "their first sighting) to all their views over this many seconds after G's "
        "definition, and computes G with it from then on (beyond the paper, "
        "stereo_points._refine_template); a list: a refinement at each (the early one "
        "brings the DPACF in within 10 s, the later one makes it precise); 0 or []: never "
        "(the first sighting's template throughout). Both estimators share the front end, so "
        "that they start on the same data",
    )
    ls_unbiased_rates: bool = Field(
        True,
        description="the inertia least squares takes, from the template's last refinement "
        "on, the rates of the cubic (unbiased) fit at every epoch, past ones reprocessed "
        "(beyond the paper): the line fit, chosen where its error is smaller epoch by "
        "epoch, has a third-order bias that does not average out over the growing batch "
        "(inertia ratios 1.2e-3 -> 4e-5 off at 200 s, 2e-5 rad, "
        "benchmarks/hu2024_refinement_checks.py schedule); false: the per-epoch choice "
        "throughout. No effect without a refinement",
    )

    @field_validator("template_refine_s")
    @classmethod
    def _refine_times(cls, v: float | list[float]) -> float | list[float]:
        if any(x < 0 or not np.isfinite(x) for x in np.atleast_1d(np.asarray(v, dtype=float))):
            raise ValueError("template_refine_s: times must be finite and >= 0 s")
        return v


@dataclass
class PointsFrontEnd:
    t: Array
    p_L: Array  # (B,n,N,3) m
    cov_L: Array  # (B,n,N,3,3) m^2
    usable: NDArray[np.bool_]  # (B,n,N)
    R_GI: Array  # (B,n,3,3)
    cov_G: Array  # (B,n,3,3) rad^2, G attitude error in G
    omega_G: Array  # (B,n,3) rad/s, rate of G wrt I in G
    var_omega: Array  # (B,n) rad^2/s^2, its variance per axis
    template_G: Array  # (B,N,3) m, feature coordinates in G
    known: NDArray[np.bool_]  # (B,N)
    known_at: NDArray[np.bool_]  # (B,n,N) catalogued in the template by epoch k
    R_GT: Array  # (B,n,3,3) DPACF principal frame (NaN until identified)
    moments: Array  # (B,n,3) principal moments / lambda_1
    q_TI: Array  # (B,n,4) DPACF attitude measurement
    cov_TI: Array  # (B,n,3,3) its covariance (frame part + G attitude noise)
    cov_frame: Array  # (B,n,3,3) the slowly varying part: error of the DPACF frame T in G
    cov_ratios: Array  # (B,n,3,3) covariance of the inertia ratios p (Hu 2024 eq. 19)
    skipped: dict[str, Array] = field(default_factory=dict)  # name -> (B,) counts
    cov_omega: Array | None = None  # (B,n,3,3) rad^2/s^2, full covariance of omega_G
    # the template's refinements (template_refine_s): (from epoch (B,), template (B,N,3))
    # for each version in order, the first from epoch 0, the last being template_G (a
    # refinement's epoch is n in runs where it did not happen); None: never refined
    template_history: list[tuple[NDArray[np.int64], Array]] | None = None
    # (B,n,3,3) attitude of L in I per run and epoch; set by the caller that holds the
    # measurements (tumblenav.estimators.hu2024.filter.frontend), None until then
    R_LI: Array | None = None

    def template_at(self, k: int | NDArray[np.int64]) -> Array:
        """The template (B,N,3) as known at epoch ``k`` (scalar or per run): the latest
        version refined at or before ``k`` (causal use of the template)."""
        if self.template_history is None:
            return self.template_G
        out = self.template_history[0][1]
        for k_v, tmpl in self.template_history[1:]:
            now = np.broadcast_to(np.asarray(k) >= k_v, k_v.shape)
            out = np.where(now[:, None, None], tmpl, out)
        return out


def triangulate(meas_list) -> tuple[Array, Array, NDArray[np.bool_], dict[str, Array]]:
    """Points (B,n,N,3) in C, covariances, usable mask, skip counts, for B runs of one rig."""
    uv = np.stack([m.uv for m in meas_list])  # (B,n,2,N,2)
    obs = np.stack([m.observed for m in meas_list])  # (B,n,2,N)
    rig = meas_list[0].rig
    sigma = meas_list[0].noise_px

    def tri(uvl: Array, uvr: Array) -> Array:
        if rig.kind == "parallel":
            L = rig.left
            return triangulate_parallel(uvl, uvr, L.focal_px, rig.baseline_m, L.principal_point_px)
        L, R = rig.left, rig.right
        return triangulate_two_ray(
            uvl,
            uvr,
            (L.focal_px, R.focal_px),
            (L.principal_point_px, R.principal_point_px),
            L.R_CkC,
            L.p_CkinC,
            R.R_CkC,
            R.p_CkinC,
        )

    uvl, uvr = uv[:, :, 0], uv[:, :, 1]
    p = tri(uvl, uvr)
    # First-order covariance by central differences over the four pixel coordinates: works
    # for any rig (the closed form of triangulation_covariance covers the parallel one only).
    if rig.kind == "parallel":  # closed form (Hu 2024 eq. 1 differentiated)
        J = triangulation_jacobian(np.nan_to_num(p), rig.left.focal_px, rig.baseline_m)
        J = np.where(np.isfinite(p)[..., None], J, np.nan)
        cov = sigma**2 * (J @ np.swapaxes(J, -1, -2))
        return _finish_triangulation(p, cov, obs)
    h = 1e-3
    J = np.empty(p.shape + (4,))
    for k in range(4):
        d = np.zeros(4)
        d[k] = h
        dl, dr = d[:2], d[2:]
        J[..., k] = (tri(uvl + dl, uvr + dr) - tri(uvl - dl, uvr - dr)) / (2 * h)
    cov = sigma**2 * (J @ np.swapaxes(J, -1, -2))
    return _finish_triangulation(p, cov, obs)


def _finish_triangulation(p: Array, cov: Array, obs: NDArray[np.bool_]):
    both = obs[:, :, 0] & obs[:, :, 1]
    usable = both & np.all(np.isfinite(p), axis=-1) & np.all(np.isfinite(cov), axis=(-1, -2))
    p = np.where(usable[..., None], p, np.nan)
    skipped = {
        "one_camera_only": np.sum(obs[:, :, 0] ^ obs[:, :, 1], axis=(1, 2)),
        "bad_triangulation": np.sum(both & ~usable, axis=(1, 2)),
    }
    return p, cov, usable, skipped


def weighted_kabsch(
    p_C: Array,
    g_G: Array,
    w: Array,
    cov_C: Array | None = None,
    cov_g: Array | None = None,
    run_len: int = 1,
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
    chi-square gate keep the Kabsch fit and covariance.
    """
    p_C = np.ascontiguousarray(p_C, dtype=float)
    g_G = np.ascontiguousarray(g_G, dtype=float)
    w = np.ascontiguousarray(w, dtype=float)
    if cov_C is not None:
        cov_g = np.zeros((len(w) // run_len,) + w.shape[1:] + (3, 3)) if cov_g is None else cov_g
        R_CG, o, cov_t, ok, _ = _points_kernel.align_rigid(
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
    covariance in G, and with ``stop_after``: ``first`` (B,), G's first epoch (n where
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
    )
    ok = ok.reshape(B, n)
    R_GC = np.where(ok[..., None, None], Rgc.reshape(B, n, 3, 3), np.nan)
    cov_G = np.where(ok[..., None, None], cg.reshape(B, n, 3, 3), np.nan)
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
    cov_f = Ninv[K:, K:] * max(1.0, chi2 / dof)
    if not np.all(np.isfinite(cov_f)):
        return None
    return x[:K], f, cov_f, idx


def _fit_factors(h: int) -> tuple[float, float, float]:
    """For the slope fits over ``j = -h..h``: the variance factors ``sum_j c_j^2`` of the
    linear and the linear-plus-cubic fit (the slope's variance is that times
    ``sigma_psi^2 / dt^2``) and the (-dimensionless) bias of the linear fit per unit cubic
    coefficient, ``sum_j c_j j^3``."""
    j = np.arange(-h, h + 1, dtype=float)
    cl = j / np.sum(j * j)
    cc = np.linalg.pinv(np.stack([j, j**3], 1))[0]
    return float(np.sum(cl**2)), float(np.sum(cc**2)), float(np.sum(cl * j**3))


def rates_and_covariance(
    R_GI: Array,
    cov_G: Array,
    dt: float,
    h: int,
    bias_epochs: int = 100,
    unbiased: bool | NDArray[np.bool_] = False,
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
    bias's mean square added to its covariance. ``cov_G`` is taken as constant over the
    window.

    ``unbiased`` (bool or (B,)): the cubic fit wherever it exists, in those runs (the rows of
    a growing least-squares batch: there the noise averages out but the line's bias does
    not; ``process`` uses it after the template's last refinement).

    Returns the rate, the covariance of the fit's noise (the ``2h`` attitudes other than
    the centre's) and the full covariance, which adds the centre attitude's part: every
    ``phi_j`` is taken relative to ``R_GI(k)``, whose error ``psi`` enters turned by
    ``j dt omega``, which leaves ``-[omega x] psi`` in the slope (``[omega x] cov_G [omega
    x]^T``; a fifth of the line's variance for this tumble). NaN unless all ``2h + 1``
    epochs have a G attitude."""
    q = _quats(_finite_or_identity(R_GI))
    valid = np.all(np.isfinite(R_GI), axis=(-1, -2))
    # phi_j = log(q(k+j) (x) conj(q(k))), j = -h..h (compiled loop)
    om_l, om_c = _points_kernel.rate_fit(q, valid, h, dt)
    good = np.all(np.isfinite(om_l), axis=-1) & np.all(np.isfinite(cov_G), axis=(-1, -2))
    fl, fc, _ = _fit_factors(h) if h >= 2 else (0.5, np.inf, 0.0)
    C = np.where(good[..., None, None], cov_G, 0.0) / dt**2
    var_diff = (fc - fl) * np.diagonal(C, axis1=-2, axis2=-1)  # (B,n,3)
    d2 = np.where(good[..., None], np.nan_to_num((om_l - om_c) ** 2 - var_diff), 0.0)
    # trailing mean over the last `bias_epochs` epochs with a rate (causal)
    cs = np.cumsum(np.concatenate([np.zeros_like(d2[:, :1]), d2], 1), axis=1)
    cn = np.cumsum(np.concatenate([np.zeros_like(good[:, :1], int), good], 1), axis=1)
    n = d2.shape[1]
    lo = np.maximum(np.arange(n) + 1 - bias_epochs, 0)
    hi = np.arange(n) + 1
    cnt = np.maximum(cn[:, hi] - cn[:, lo], 1)
    b2 = np.maximum((cs[:, hi] - cs[:, lo]) / cnt[..., None], 0.0)
    cubic = (np.sum(b2, -1) > (fc - fl) * np.trace(C, axis1=-2, axis2=-1)) & np.all(
        np.isfinite(om_c), -1
    )
    # per run (B,): the cubic fit wherever it exists
    unb = np.broadcast_to(np.asarray(unbiased, dtype=bool), good.shape[:1])[:, None]
    cubic = np.where(unb, np.all(np.isfinite(om_c), -1), cubic)
    omega = np.where(cubic[..., None], om_c, om_l)
    eye = np.eye(3)
    with np.errstate(invalid="ignore"):  # fc = inf for h = 1, where the cubic fit is not used
        cov = np.where(cubic[..., None, None], fc * C, fl * C + b2[..., None] * eye)
    omega = np.where(good[..., None], omega, np.nan)
    cov = np.where(good[..., None, None], cov, np.nan)
    wx = _skew(np.nan_to_num(omega))
    return omega, cov, cov + wx @ np.nan_to_num(cov_G) @ np.swapaxes(wx, -1, -2)


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
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Growing-batch weighted least squares (Hu 2024 eq. 13-14), DPACF (eq. 17) and the
    attitude measurement q_TI = q_TG (x) q_GI (eq. 31) with its covariance; last, the
    covariance of the inertia ratios (eq. 19). With the covariances of the rates' fit noise
    ``cov_w`` (B,n,3,3) the least squares is generalised (rows whitened), else weighted by
    ``1 / var_w``. ``R_GI_report``: the G attitudes of the attitude measurement, if not
    ``R_GI``. ``before``: a list of ``(omega, var_w, R_GI, cov_w, k_from, k_to)``, the rows of
    the first epochs (as many as given) as they were between two of the template's
    refinements: the solutions at epochs ``k_from <= k < k_to`` ((B,) each) use these rows
    instead of the main ones."""
    B, n = omega_G.shape[:2]
    a, b, w, ok = _ls_rows(omega_G, var_w, R_GI, cov_w)
    # The identification is re-solved every `ls_every` epochs and held in between (the
    # attitude measurement still uses the G attitude of every epoch).
    held = (np.arange(n) // s.ls_every) * s.ls_every
    sel = np.unique(held)
    # Sums of w a^T a, w a^T b, w |b|^2 and the count of epochs, up to epoch k - delay at
    # each solved epoch k. Causality: the rate at epoch j uses attitudes up to j + h, so epoch
    # k may only use the least-squares sums up to k - h (compiled loop).
    N, r, bb, cnt = _points_kernel.normal_equations_at(a, b, w, ok, delay, sel)
    for om_o, var_o, R_o, cw_o, k_from, k_to in before or []:
        # the solutions between two refinements: the sums of the rows as they were then
        m = min(int(k_to.max()), n)
        early = sel < m
        if not early.any():
            continue
        ao, bo, wo, oko = _ls_rows(om_o[:, :m], var_o[:, :m], R_o[:, :m],
                                   None if cw_o is None else cw_o[:, :m])  # fmt: skip
        se = sel[early]
        # the sums of a solution before k_to cover epochs up to k_to - h - 1 < m only
        No, ro, bbo, co = _points_kernel.normal_equations_at(ao, bo, wo, oko, delay, se)
        use = (se[None, :] >= k_from[:, None]) & (se[None, :] < k_to[:, None])  # (B, S_early)
        N[:, early] = np.where(use[..., None, None], No, N[:, early])
        r[:, early] = np.where(use[..., None], ro, r[:, early])
        bb[:, early] = np.where(use, bbo, bb[:, early])
        cnt[:, early] = np.where(use, co, cnt[:, early])
    return _solve_and_dpacf(N, r, bb, cnt, sel, held, s,
                            R_GI if R_GI_report is None else R_GI_report, cov_G)  # fmt: skip


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


def _solve_and_dpacf(N, r, bb, cnt, sel, held, s, R_GI, cov_G):
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
    rss = bb - 2 * np.einsum("...i,...i->...", X, r) + np.einsum("...i,...ij,...j->...", X, N, X)
    dof = np.maximum(3 * cnt - 8, 1)
    s2 = np.maximum(rss / dof, 1e-30)
    # The rates come from overlapping windows of 2h+1 attitudes, so neighbouring epochs share
    # their noise: the least-squares covariance, which assumes independent epochs, is too
    # small by about that factor.
    cov_l = (2 * s.rate_half_window + 1) * s2[..., None, None] * Ninv[..., :5, :5]
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
    valid &= sig_phi < s.max_dpacf_sigma_rad
    # back to every epoch (hold the latest solution)
    pos = np.searchsorted(sel, held)
    R_GT, lam, cov_phi, valid = R_GT[:, pos], lam[:, pos], cov_phi[:, pos], valid[:, pos]
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
    return R_GT, moments, q_TI, cov_TI, cov_phi, cov_p


def _refine_template(
    t, first, k_ref, upto, p_C, cov_C, p_L, cov_L, usable, known_at, template, cov_tmpl,
    R_GI, cov_G, R_CL, R_LI, refined=None,
):  # fmt: skip
    """One refinement of the template: refitted over the epochs ``first .. k_ref - 1`` of G
    (``first`` (B,), G's first epoch; ``k_ref`` (B,), the refinement's epoch, n where
    none), and G with it at the epochs ``0 .. upto - 1`` (beyond Hu 2024, whose G comes
    from three points of one sighting).

    The template (each feature's G coordinates at its first sighting: one stereo point,
    8 mm deep at 17 m and 2e-5 rad) has errors fixed in G that the G attitude fit turns
    into view-dependent attitude errors, which do not average out in the rates. At epoch
    ``k_ref`` the features are refitted jointly to all their views so far
    (``joint_features``, with a quadratic translation in L, which is the Hill motion to
    0.1 mm over 30 s), in the axes of the G attitudes ``R_GI`` measured so far (with the
    template ``template``, the previous version), so that G keeps its orientation; the
    other features' coordinates shift with the fitted ones' mean. How ``process`` uses it
    causally: G attitudes are reported with a version from its ``k_ref`` on; the rates of
    epochs from ``k_ref - h`` on (each available at its epoch + h >= k_ref) come from its
    attitudes; and the least squares, a batch re-solved at each solution, uses from
    ``k_ref`` on the rows of every epoch recomputed with it (past data reprocessed at
    ``k_ref``), before it the rows as they were.

    Tried and not kept: keeping the first G's orientation across the switch (the refined
    template rotated by the mean rotation between the two G over ``k_ref - 2h .. k_ref``):
    median attitude 0.094 -> 0.102 deg over 500 runs at 2e-5 rad, no change at 1e-6 rad.

    ``refined`` (B,): the runs whose ``template`` is a fit's already (about its fitted mass
    centre: one pass of the fit from it).

    Returns the refined template (B,N,3) (the previous one where the fit failed) and its
    covariance, G's attitude and covariance (B,upto,...) with it, and ``refined`` updated."""
    B, n, N = usable.shape
    valid = np.all(np.isfinite(R_GI), axis=(-1, -2))
    new_t = template.copy()
    new_c = cov_tmpl.copy()
    ref = np.zeros(B, dtype=bool) if refined is None else refined.copy()
    for b in np.flatnonzero(k_ref < n):
        j = np.flatnonzero(valid[b, first[b] : k_ref[b]]) + first[b]
        if len(j) < 10:
            continue
        R_LG = R_LI[b, j] @ np.swapaxes(R_GI[b, j], -1, -2)
        tau = (t[j] - t[j[0]])[:, None, None]
        eye = np.eye(3)[None]
        Phi = np.concatenate([np.broadcast_to(eye, tau.shape[:1] + (3, 3)), tau * eye,
                              0.5 * tau**2 * eye], axis=2)  # fmt: skip
        kn = known_at[b, k_ref[b] - 1]
        use = usable[b, j] & kn[None, :]
        g = template[b]
        # the lever arms: a refined template is about its fitted mass centre already (one
        # pass); the first sightings' about one feature (centred, then re-linearised)
        out = joint_features(Phi, R_LG, p_L[b, j], cov_L[b, j], cov_G[b, j], use,
                             g if ref[b] else g - np.nanmean(g[kn], axis=0),
                             passes=1 if ref[b] else 2)  # fmt: skip
        if out is None:
            continue
        _, f, cov_f, idx = out
        c = np.mean(g[idx] - f, axis=0)
        new_t[b] = g - c
        new_t[b, idx] = f
        # the template's covariance is its shape's: the features' common shift (their mass
        # centre, poorly known in a slow tumble) is a translation, which each epoch's fit
        # of G estimates anyway (with it, G got worse than unrefined at 0.024 rad/s)
        nf = len(idx)
        Pm = np.kron(np.eye(nf) - 1.0 / nf, np.eye(3))
        cov_s = Pm @ cov_f @ Pm.T
        for m, i in enumerate(idx):
            new_c[b, i] = cov_s[3 * m : 3 * m + 3, 3 * m : 3 * m + 3]
        ref[b] = True
    m = upto
    use = usable[:, :m] & known_at[:, :m] & (k_ref < n)[:, None, None]
    w = np.where(use, 1.0 / np.maximum(np.trace(cov_C[:, :m], axis1=-2, axis2=-1), 1e-30), 0.0)
    R2, _, c2, ok2 = weighted_kabsch(
        p_C[:, :m].reshape(B * m, N, 3),
        np.broadcast_to(new_t[:, None], (B, m, N, 3)).reshape(B * m, N, 3),
        w.reshape(B * m, N),
        cov_C[:, :m].reshape(B * m, N, 3, 3),
        np.trace(new_c, axis1=-2, axis2=-1)[..., None, None] * np.eye(3),  # as in pass 2
        run_len=m,
    )
    ok2 = ok2.reshape(B, m)
    R_GI2 = np.where(ok2[..., None, None], R2.reshape(B, m, 3, 3), np.nan) @ (
        R_CL[:, :m] @ R_LI[:, :m]
    )
    cov_G2 = np.where(ok2[..., None, None], c2.reshape(B, m, 3, 3), np.nan)
    return new_t, new_c, R_GI2, cov_G2, ref


def _refine_epochs(first: NDArray[np.int64], s: FrontEndSettings, dt: float, n: int):
    """The epochs (V, B) of the template's refinements (``template_refine_s`` after G's
    first epoch ``first`` (B,), each rounded up to a least-squares solution; n where it
    would be at or after the end, or G is never defined)."""
    secs = np.atleast_1d(np.asarray(s.template_refine_s, dtype=float))
    steps = sorted({int(round(x / dt)) for x in secs if x > 0})
    ks = [np.minimum(-(-(first + m) // s.ls_every) * s.ls_every, n) for m in steps]
    return [np.where(first < n, k, n) for k in ks]


def process(meas_list, settings: FrontEndSettings | None = None) -> PointsFrontEnd:
    """Run the whole front end on B runs (same rig, same time grid)."""
    s = settings or FrontEndSettings()
    t = meas_list[0].t
    dt = float(np.median(np.diff(t)))
    R_CL = rot.quat_to_matrix(np.stack([m.q_CL for m in meas_list]))  # (B,n,3,3)
    R_LI = rot.quat_to_matrix(np.stack([m.q_LI for m in meas_list]))
    R_LC = np.ascontiguousarray(np.swapaxes(R_CL, -1, -2))
    rig = meas_list[0].rig
    if rig.kind == "parallel":  # compiled: the same as triangulate() and the rotation below
        L = rig.left
        p_C, cov_C, p_L, cov_L, usable, one_cam, bad = _points_kernel.triangulate_parallel_rotated(
            np.stack([m.uv for m in meas_list]).astype(float),
            np.stack([m.observed for m in meas_list]).astype(np.bool_),
            float(L.focal_px),
            float(rig.baseline_m),
            float(L.principal_point_px[0]),
            float(L.principal_point_px[1]),
            float(meas_list[0].noise_px),
            R_LC,
        )
        skipped = {"one_camera_only": one_cam, "bad_triangulation": bad}
    else:
        p_C, cov_C, usable, skipped = triangulate(meas_list)
        p_L = (R_LC[:, :, None] @ p_C[..., None])[..., 0]
        cov_L = R_LC[:, :, None] @ cov_C @ np.swapaxes(R_LC, -1, -2)[:, :, None]
    h = s.rate_half_window
    n = len(t)
    full = s.g_fit == "full"
    steps: Array | list[float] = (
        np.atleast_1d(np.asarray(s.template_refine_s, dtype=float)) if full else []
    )
    n_first = int(round(min([x for x in steps if x > 0], default=0.0) / dt))
    info: dict = {}
    R_GC, cov_G, template, known, known_at = photogrammetric_frames(
        p_C, cov_C, usable, full_cov=full, stop_after=n_first, info=info,
        stop_every=s.ls_every,
    )  # fmt: skip
    # Versions of the template (the first sightings', then each refinement's) and of what
    # follows from it: G at the epochs it is needed for (up to the next refinement), the
    # rates and the least squares' rows; each version is reported from its refinement on
    ks = _refine_epochs(info["first"], s, dt, n) if n_first > 0 else []
    ks = [k for k in ks if np.any(k < n)]
    bounds = [np.zeros(len(meas_list), dtype=np.int64)] + ks + [np.full(len(meas_list), n)]
    R_GI = R_GC @ R_CL @ R_LI
    history = [(bounds[0], template)]
    vers = []  # (R_GI, cov_G, omega, cov_fit, cov_w) over the version's first epochs
    tmpl, cov_t = template, info.get("cov_template")
    fitted = np.zeros(len(meas_list), dtype=bool)  # runs whose template is a fit's
    for v in range(len(bounds) - 1):
        m = min(int(bounds[v + 1].max()), n)  # a rate before bounds[v+1] - h needs no more
        if v > 0:  # refine at bounds[v], with the previous version's G
            tmpl, cov_t, R_GI, cov_G, fitted = _refine_template(
                t, info["first"], bounds[v], m, p_C, cov_C, p_L, cov_L, usable, known_at,
                tmpl, cov_t, R_GI, cov_G, R_CL, R_LI, refined=fitted,
            )  # fmt: skip
            history.append((bounds[v], tmpl))
        Rv, cGv = R_GI[:, :m], cov_G[:, :m]
        # the runs' last version (the rows the least squares accumulates to the end): the
        # unbiased rate fit (see rates_and_covariance)
        last = (bounds[v + 1] >= n) & (v > 0) & s.unbiased_last
        vers.append((Rv, cGv) + rates_and_covariance(Rv, cGv, dt, h, unbiased=last))
    # as reported at each epoch: G from a version's refinement on, the rate of epoch j (known
    # at j + h) from the version in force at j + h
    R_GI = np.full((len(meas_list), n, 3, 3), np.nan)
    cov_G, omega_G, cov_w = R_GI.copy(), R_GI[..., 0].copy(), R_GI.copy()
    ep = np.arange(n)[None, :]
    for v, (Rv, cGv, omv, _, cwv) in enumerate(vers):
        m = Rv.shape[1]
        sel = (ep >= bounds[v][:, None]) & (ep < bounds[v + 1][:, None])
        R_GI[:, :m] = np.where(sel[:, :m, None, None], Rv, R_GI[:, :m])
        cov_G[:, :m] = np.where(sel[:, :m, None, None], cGv, cov_G[:, :m])
        sel = (ep + h >= bounds[v][:, None]) & (ep + h < bounds[v + 1][:, None])
        omega_G[:, :m] = np.where(sel[:, :m, None], omv, omega_G[:, :m])
        cov_w[:, :m] = np.where(sel[:, :m, None, None], cwv, cov_w[:, :m])
    skipped["too_few_features"] = np.sum(~np.all(np.isfinite(R_GI), axis=(-1, -2)), axis=1)
    var_w = np.trace(cov_w, axis1=-2, axis2=-1) / 3.0
    # the least squares: the last version's rows, those of the earlier versions for the
    # solutions before the next refinement
    R_ls, _, om_ls, cf_ls, cw_ls = vers[-1]
    before = [
        (om, np.trace(cw, axis1=-2, axis2=-1) / 3.0, Rv, cf if full else None, bounds[v],
         bounds[v + 1])
        for v, (Rv, _, om, cf, cw) in enumerate(vers[:-1])
    ]  # fmt: skip
    R_GT, moments, q_TI, cov_TI, cov_frame, cov_ratios = identify_and_dpacf(
        om_ls,
        np.trace(cw_ls, axis1=-2, axis2=-1) / 3.0,
        R_ls,
        cov_G,
        s,
        delay=s.rate_half_window,
        cov_w=cf_ls if full else None,
        R_GI_report=R_GI,
        before=before,
    )
    return PointsFrontEnd(
        t=t,
        p_L=p_L,
        cov_L=cov_L,
        usable=usable,
        R_GI=R_GI,
        cov_G=cov_G,
        omega_G=omega_G,
        var_omega=var_w,
        template_G=tmpl,
        known=known,
        known_at=known_at,
        R_GT=R_GT,
        moments=moments,
        q_TI=q_TI,
        cov_TI=cov_TI,
        cov_frame=cov_frame,
        cov_ratios=cov_ratios,
        skipped=skipped,
        cov_omega=cov_w,
        template_history=history if len(history) > 1 else None,
    )
