"""ekf-pose's start as a batch: the start window's poses and map by Gauss-Newton (tumblenav's,
issue 18; beyond Chang 2021, which starts from the truth, Sec. 4.2).

Why: the replay (:meth:`.slam.StateSteps._replay`) runs the filter over the window with the
map's Jacobians at the previous pass's map; where one epoch fixes the attitude badly (Chang's
printed 59 m: ~15 deg per epoch across the line of sight) the passes do not converge and the
replay can end degrees (or radians) off with a 1-sigma of 0.1 deg. A batch least-squares fit of
the whole window (a bundle adjustment with the target's torque-free motion as the pose model)
uses every sighting at the solution, not at the estimate a filter had when it saw it.

Unknowns ``p = [omega_0 (3) | j (5, with the inertia estimated) | r_0, v_0 (6)]`` and the map
``s_i`` (3 each) of every track seen in the window; That is defined at k0 (``R_ThatL(k0) = I``,
exact). The attitude and rate at each window epoch follow from ``(I, omega_0)`` by the
filter's own propagation (:func:`.model.propagate_mean`: Chang 2021 eq. 2-3 with the inertia
``J(j)``), the mass centre from ``(r_0, v_0)`` by CW (eq. 4). Every sighting is a measurement
``rho_i(k) = r(k) + R_LThat(k) s_i`` with its triangulation covariance (the filter's
:func:`.slam.predicted_features`). Priors: the mass centre within ``prior_mass_centre_sigma_m``
of the first frame's feature centroid on each axis (as the replay's), the inertia parameters
``N(0, inertia_sigma^2)``. Each sighting is weighted as the filter weights it (a track's
first at its triangulation covariance, the later ones scaled by the tracks' stated tracked
noise). Gauss-Newton (Levenberg-Marquardt damped) with the map eliminated by
its Schur complement (each map point sees only its own sightings: Triggs et al. 2000,
"Bundle adjustment - a modern synthesis", Sec. 6.1); the pose parameters' derivatives by
central differences of the propagation. Sightings whose whitened residual exceeds the
feature gate (3 dof) are dropped and the fit repeated (slipped image tracks).

The result is the state at the window's last epoch, its map, and their joint covariance (the
inverse of the Gauss-Newton information, carried to the end epoch by the propagation's
derivatives).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.stats import chi2

from tumblenav import rotations as rot
from tumblenav.dynamics.relative_orbit import cw_stm
from tumblenav.estimators.chang2021.measurements import FeatureTracks
from tumblenav.estimators.chang2021.model import INERTIA_BASIS, omega_LI_L

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_NI = len(INERTIA_BASIS)  # the inertia parameters j: J = I + D(j)


@dataclass(frozen=True)
class BatchStart:
    """The fitted window: at its last epoch ``k1`` the pose ``x`` (13: q_ThatL, omega, r_L,
    v_L), the inertia parameters ``j`` (5), the map ``ids`` (m,) / ``s`` (m, 3) of the tracks
    seen at k1, and the joint covariance ``P`` (12 + 5 + 3m) in ekf-pose's error layout
    (attitude as the left error in That); ``cost`` the whitened residuals' sum of squares over
    ``dof`` residuals, ``iterations`` Gauss-Newton steps, ``dropped`` sightings gated out."""

    k1: int
    x: Array
    j: Array
    ids: IntArray
    s: Array
    P: Array
    cost: float
    dof: int
    iterations: int
    dropped: int
    omega0: Array  # the fitted rate at k0 (That)
    rv0: Array  # the fitted mass centre and velocity at k0 (L)
    window_ids: IntArray  # every track seen in the window, and its fitted position in That
    window_s: Array


@njit(cache=True, error_model="numpy")
def _rhs(q, w, Ji, J, a_L, dq, dw):  # pragma: no cover - compiled (tested through the caller)
    """Chang 2021 eq. 2-3 (:func:`.model.rate_derivative`, :func:`tumblenav.rotations.
    quat_derivative`) at ``q`` (4), ``w`` (3) with ``J`` and its inverse ``Ji``; ``a_L`` the
    orbit's rate in L. Into ``dq``, ``dw``."""
    x, y, z, s = q[0], q[1], q[2], q[3]
    # R_ThatL a_L (quat_to_matrix of the unit q)
    nq = np.sqrt(x * x + y * y + z * z + s * s)
    x, y, z, s = x / nq, y / nq, z / nq, s / nq
    R00, R01, R02 = 1 - 2 * (y * y + z * z), 2 * (x * y - s * z), 2 * (x * z + s * y)
    R10, R11, R12 = 2 * (x * y + s * z), 1 - 2 * (x * x + z * z), 2 * (y * z - s * x)
    R20, R21, R22 = 2 * (x * z - s * y), 2 * (y * z + s * x), 1 - 2 * (x * x + y * y)
    a0 = R00 * a_L[0] + R01 * a_L[1] + R02 * a_L[2]
    a1 = R10 * a_L[0] + R11 * a_L[1] + R12 * a_L[2]
    a2 = R20 * a_L[0] + R21 * a_L[1] + R22 * a_L[2]
    t0, t1, t2 = w[0] + a0, w[1] + a1, w[2] + a2  # w_ti
    I0 = J[0, 0] * t0 + J[0, 1] * t1 + J[0, 2] * t2
    I1 = J[1, 0] * t0 + J[1, 1] * t1 + J[1, 2] * t2
    I2 = J[2, 0] * t0 + J[2, 1] * t1 + J[2, 2] * t2
    c0 = -(t1 * I2 - t2 * I1)
    c1 = -(t2 * I0 - t0 * I2)
    c2 = -(t0 * I1 - t1 * I0)
    dw[0] = Ji[0, 0] * c0 + Ji[0, 1] * c1 + Ji[0, 2] * c2 + (w[1] * a2 - w[2] * a1)
    dw[1] = Ji[1, 0] * c0 + Ji[1, 1] * c1 + Ji[1, 2] * c2 + (w[2] * a0 - w[0] * a2)
    dw[2] = Ji[2, 0] * c0 + Ji[2, 1] * c1 + Ji[2, 2] * c2 + (w[0] * a1 - w[1] * a0)
    # dq = -1/2 [w; 0] (x) q (Hamilton, [x, y, z, w])
    qx, qy, qz, qw = q[0], q[1], q[2], q[3]
    dq[0] = -0.5 * (qw * w[0] + (w[1] * qz - w[2] * qy))
    dq[1] = -0.5 * (qw * w[1] + (w[2] * qx - w[0] * qz))
    dq[2] = -0.5 * (qw * w[2] + (w[0] * qy - w[1] * qx))
    dq[3] = -0.5 * (-(w[0] * qx + w[1] * qy + w[2] * qz))


@njit(cache=True, error_model="numpy")
def _propagate(omega0, J, Ji, dts, a_L):  # pragma: no cover - compiled (tested through the caller)
    """RK4 per interval (:func:`tumblenav.dynamics.integrators.rk4_step`), the quaternion
    normalised after each (:func:`.model.propagate_mean`), from ``(I, omega0[b])``: quaternions
    (B, K, 4) and rates (B, K, 3)."""
    B, K = omega0.shape[0], dts.shape[0] + 1
    Q = np.zeros((B, K, 4))
    W = np.zeros((B, K, 3))
    kq = np.zeros((4, 4))
    kw = np.zeros((4, 3))
    qs = np.zeros(4)
    ws = np.zeros(3)
    for b in range(B):
        Q[b, 0, 3] = 1.0
        W[b, 0] = omega0[b]
        for k in range(1, K):
            dt = dts[k - 1]
            q0 = Q[b, k - 1]
            w0 = W[b, k - 1]
            for st in range(4):
                h = 0.0 if st == 0 else (0.5 * dt if st < 3 else dt)
                for i in range(4):
                    qs[i] = q0[i] + h * kq[st - 1, i] if st else q0[i]
                for i in range(3):
                    ws[i] = w0[i] + h * kw[st - 1, i] if st else w0[i]
                _rhs(qs, ws, Ji[b], J[b], a_L, kq[st], kw[st])
            nq = 0.0
            for i in range(4):
                v = q0[i] + dt / 6.0 * (kq[0, i] + 2.0 * kq[1, i] + 2.0 * kq[2, i] + kq[3, i])
                Q[b, k, i] = v
                nq += v * v
            nq = np.sqrt(nq)
            for i in range(4):
                Q[b, k, i] /= nq
            for i in range(3):
                W[b, k, i] = w0[i] + dt / 6.0 * (
                    kw[0, i] + 2.0 * kw[1, i] + 2.0 * kw[2, i] + kw[3, i]
                )
    return Q, W


def _trajectories(omega0: Array, j: Array, t: Array, n: float) -> tuple[Array, Array]:
    """Attitude matrices R_ThatL (B, K, 3, 3) and rates (B, K, 3) at the times ``t`` of the
    motions from ``(I, omega0[b])`` with inertia ``J(j[b])``: the filter's propagation
    (:func:`.model.propagate_mean`: RK4 per interval, the quaternion normalised; compiled,
    for a stack of initial values at once: the fit's central differences)."""
    J = np.eye(3) + np.einsum("bp,pij->bij", np.asarray(j, float), INERTIA_BASIS)
    Q, W = _propagate(
        np.ascontiguousarray(omega0, dtype=float),
        J,
        np.linalg.inv(J),
        np.diff(np.asarray(t, float)),
        omega_LI_L(n),
    )
    return rot.quat_to_matrix(Q), W


def _start_rates(omega0: Array) -> list[Array]:
    """The fit's starting rates: the window's estimate and that estimate turned by +-90 deg
    about two axes across it. Where one epoch fixes the attitude to ~15 deg (Chang's printed
    59 m) the window's rate line can point 45-90 deg off, and Gauss-Newton from there can
    settle in another minimum (a wrong tumble that fits the sightings worse: on the 59 m point
    tracks, run 2, cost/dof 1.054 from the rate line against 0.976 from two turned starts;
    docs/results/consistency/prototype/chang_batch_start.py)."""
    w = np.asarray(omega0, float)
    nw = float(np.linalg.norm(w))
    if not nw > 0.0:
        return [w]
    e = np.eye(3)[int(np.argmin(np.abs(w)))]
    u = np.cross(w, e)
    u /= np.linalg.norm(u)
    v = np.cross(w / nw, u)
    return [w] + [rot.exp_map(a * s * np.pi / 2) @ w for a in (u, v) for s in (1.0, -1.0)]


def fit_window(
    tracks: FeatureTracks,
    t: Array,
    k0: int,
    k1: int,
    omega0: Array,
    rv0: Array,
    n: float,
    *,
    estimate_inertia: bool,
    inertia_sigma: float,
    centre_sigma: float,
    noise_scale: float,
    first_noise_scale: float,
    gate_probability: float,
    max_features: int,
    j_fixed: Array | None = None,
    iterations: int = 40,
    covariance_at: Callable[[Array, IntArray], Array] | None = None,
) -> BatchStart | None:
    """Fit the window ``k0..k1`` (module docstring) from the initial rate ``omega0`` (That, at
    k0; the fit starts from it and from :func:`_start_rates`' turned copies and keeps the
    lowest cost) and mass centre ``rv0`` (L, at k0); the inertia parameters are estimated
    (``estimate_inertia``) or fixed at ``j_fixed`` (default the sphere). None when the window
    has too few sightings, or no start reaches a finite cost with a positive-definite
    covariance.

    ``covariance_at(p_L (M, 3), epochs (M,))``: the triangulation covariance (at the first
    sightings' noise) of points at ``p_L`` seen at those epochs (NaN where none); given, the
    best start's solution is re-weighted at its own predicted points and refined, twice, as
    the filter weights its updates (``noise_at: predicted``; ekf-pose passes it for point
    tracks, :attr:`.slam.StateSteps._fit_at_predicted`). Why: weights at the measured
    points (``Sigma ~ depth^4``) lean to the points measured too near and pull the mass centre
    towards the camera by ~4 sigma_depth^2 / depth (:func:`.measurements.point_covariance`):
    on Chang's rig with 0.5 px at 40 m, 8 runs, the start's position NEES/dof was 8.4 and its
    velocity then took up the correction (nineteenth session, issue 18)."""
    tw = np.asarray(t[k0 : k1 + 1], float)
    ok = tracks.ok_p[k0 : k1 + 1]
    ids = np.flatnonzero(ok.any(axis=0))
    if len(ids) < 3:
        return None
    kk, ii = np.nonzero(ok[:, ids])  # sightings: window epoch, map index
    rho = tracks.p[k0 + kk, ids[ii]]
    _, first = np.unique(ii, return_index=True)  # each track's first sighting (kk sorted)
    scale = np.full(len(kk), noise_scale)
    scale[first] = first_noise_scale  # a track's later sightings may be stated finer
    Sig_meas = tracks.P[k0 + kk, ids[ii]]
    Wh = np.linalg.inv(np.linalg.cholesky(scale[:, None, None] * Sig_meas))  # Wh (rho - pred)
    nj = _NI if estimate_inertia else 0
    j0 = np.zeros(_NI) if j_fixed is None else np.asarray(j_fixed, float)  # when not estimated
    npar = 3 + nj + 6
    c0 = np.average(tracks.p[k0, ids[ok[0, ids]]], axis=0)  # the first frame's centroid
    prior_p = np.zeros(npar)
    prior_p[3 + nj : 6 + nj] = c0
    prior_w = np.zeros(npar)
    prior_w[3 : 3 + nj] = 1.0 / inertia_sigma**2
    prior_w[3 + nj : 6 + nj] = 1.0 / centre_sigma**2
    Phi = np.stack([cw_stm(n, float(tk - tw[0])) for tk in tw])  # (K, 6, 6)

    def poses(p: Array) -> tuple[Array, Array, Array]:
        jj = p[3 : 3 + nj] if nj else j0
        R, W = _trajectories(p[None, :3], jj[None], tw, n)
        return R[0], W[0], Phi[:, :3] @ p[3 + nj :]

    def perturbed(p: Array, h: float) -> tuple[Array, Array]:
        """The trajectories at ``p +- h e_c`` for the rate and inertia parameters:
        R (2, 3 + nj, K, 3, 3), W (2, 3 + nj, K, 3)."""
        E = h * np.eye(npar)[: 3 + nj]
        P2 = np.concatenate([p + E, p - E])
        jj = P2[:, 3 : 3 + nj] if nj else np.tile(j0, (len(P2), 1))
        R, W = _trajectories(P2[:, :3], jj, tw, n)
        return R.reshape(2, 3 + nj, *R.shape[1:]), W.reshape(2, 3 + nj, *W.shape[1:])

    def residuals(p: Array, s: Array) -> tuple[Array, Array]:
        R, _, r = poses(p)
        pred = r[kk] + np.einsum("mji,mj->mi", R[kk], s[ii])  # r + R_LThat s
        return np.einsum("mij,mj->mi", Wh, rho - pred), R

    def cost_of(e: Array, p: Array, use: NDArray[np.bool_]) -> float:
        c = float(np.sum(e[use] ** 2) + np.sum(prior_w * (p - prior_p) ** 2))
        return c if np.isfinite(c) else np.inf  # a step into NaN is refused

    def normal(p: Array, s: Array, R: Array, e: Array, use: NDArray[np.bool_]):
        """Gauss-Newton's blocks: Hpp, bp (npar), Hss (m, 3, 3), Hsp (m, 3, npar), bs (m, 3)."""
        h = 1e-6
        Rpm, _ = perturbed(p, h)
        dR = np.swapaxes(np.swapaxes(Rpm[0] - Rpm[1], 2, 3), 0, 1) / (2 * h)  # dR_LThat/dp_c
        # e = Wh (rho - r - R_LThat s): de/dp = -Wh (dr/dp + dR_LThat/dp s), de/ds = -Wh R_LThat
        Jp = np.zeros((len(kk), 3, npar))
        Jp[:, :, : 3 + nj] = np.einsum("mcij,mj->mic", dR[kk], s[ii])
        Jp[:, :, 3 + nj :] = Phi[kk, :3]
        Jp = -np.einsum("mij,mjc->mic", Wh, Jp)
        Js = -np.einsum("mij,mkj->mik", Wh, R[kk])
        Jp[~use] = 0.0
        Js[~use] = 0.0
        ew = np.where(use[:, None], e, 0.0)
        Hpp = np.einsum("mic,mid->cd", Jp, Jp) + np.diag(prior_w)
        bp = -np.einsum("mic,mi->c", Jp, ew) - prior_w * (p - prior_p)
        Hss = np.zeros((len(ids), 3, 3))
        np.add.at(Hss, ii, np.einsum("mia,mib->mab", Js, Js))
        Hsp = np.zeros((len(ids), 3, npar))
        np.add.at(Hsp, ii, np.einsum("mia,mic->mac", Js, Jp))
        bs = np.zeros((len(ids), 3))
        np.add.at(bs, ii, -np.einsum("mia,mi->ma", Js, ew))
        return Hpp, bp, Hss + 1e-12 * np.eye(3), Hsp, bs

    def solve(p: Array, s: Array | None = None):
        """Levenberg-Marquardt from the rate and mass centre ``p`` and the map ``s`` (default
        each track's first sighting); sightings beyond the gate dropped and the fit repeated
        (twice at most)."""
        R, _, r = poses(p)
        if s is None:  # R_ThatL (rho - r)
            s = np.einsum("mij,mj->mi", R[kk[first]], rho[first] - r[kk[first]])
        use = np.ones(len(kk), bool)
        e, R = residuals(p, s)
        cost, lam, it = cost_of(e, p, use), 1e-3, 0
        if not np.isfinite(cost):  # a start that cannot even be evaluated
            return p, s, e, R, use, np.inf, it
        for rnd in range(3):
            converged = False
            for _ in range(iterations):
                it += 1
                Hpp, bp, Hss, Hsp, bs = normal(p, s, R, e, use)
                while True:  # the map eliminated (Schur complement), damped
                    try:
                        Hss_inv = np.linalg.inv(
                            Hss + lam * np.einsum("mii->mi", Hss)[..., None] * np.eye(3)
                        )
                        HpsHi = np.einsum("mac,mab->mcb", Hsp, Hss_inv)
                        A = Hpp + lam * np.diag(np.diag(Hpp))
                        A -= np.einsum("mcb,mbd->cd", HpsHi, Hsp)
                        dp = np.linalg.solve(A, bp - np.einsum("mcb,mb->c", HpsHi, bs))
                        ds = np.einsum("mab,mb->ma", Hss_inv, bs - np.einsum("mac,c->ma", Hsp, dp))
                        e_new, R_new = residuals(p + dp, s + ds)
                        cost_new = cost_of(e_new, p + dp, use)
                    except np.linalg.LinAlgError:  # a start that ran off: no step
                        cost_new = np.inf
                    if cost_new <= cost or lam > 1e8:
                        break
                    lam *= 10.0
                if not cost_new <= cost:  # no step lowers the cost: a minimum
                    converged = True
                    break
                done = cost - cost_new < 1e-13 * cost  # to rounding: Gauss-Newton ends fast
                p, s, e, R, cost = p + dp, s + ds, e_new, R_new, cost_new
                lam = max(lam / 10.0, 1e-9)
                if done:
                    converged = True
                    break
            # gate only at a minimum: away from one the residuals are the start's, not outliers
            bad = use & (np.sum(e**2, axis=1) > chi2.ppf(gate_probability, 3))
            if not converged or not bad.any() or rnd == 2:
                break
            use &= ~bad
            cost = cost_of(e, p, use)
        # the candidates are compared by the truncated cost (a sighting beyond the gate counts
        # as the gate): a wrong tumble must not win by calling the sightings it misses outliers
        gate = chi2.ppf(gate_probability, 3)
        robust = float(np.sum(np.minimum(np.sum(e**2, axis=1), gate)))
        robust += float(np.sum(prior_w * (p - prior_p) ** 2))
        return p, s, e, R, use, robust if np.isfinite(robust) else np.inf, it

    best = None
    for w0 in _start_rates(omega0):
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            out = solve(np.concatenate([w0, np.zeros(nj), rv0]))  # a start may run off: NaN,
            # refused by its cost
        # a turned start wins only by fitting better than rounding can tell (the same minimum
        # reached from two starts must not flip the choice)
        if best is None or out[5] < best[5] - 1e-6 * abs(best[5]):
            best = out
    if best is None or not np.isfinite(best[5]):
        return None
    for _ in range(2 if covariance_at is not None else 0):  # weights at the predicted points
        assert covariance_at is not None
        R, _, r = poses(best[0])
        pred = r[kk] + np.einsum("mji,mj->mi", R[kk], best[1][ii])
        Sig = covariance_at(pred, k0 + kk)
        Sig = np.where(np.all(np.isfinite(Sig), axis=(1, 2))[:, None, None], Sig, Sig_meas)
        Wh = np.linalg.inv(np.linalg.cholesky(scale[:, None, None] * Sig))  # the closures' too
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            out = solve(best[0], best[1])
        if not np.isfinite(out[5]):
            return None
        best = out[:6] + (best[6] + out[6],)
    p, s, e, R, use, _, it = best

    # covariance of (p, s) at the solution (undamped): the Schur complement's inverse
    Hpp, _, Hss, Hsp, _ = normal(p, s, R, e, use)
    try:
        Hss_inv = np.linalg.inv(Hss)
        HpsHi = np.einsum("mac,mab->mcb", Hsp, Hss_inv)
        Spp = np.linalg.inv(Hpp - np.einsum("mcb,mbd->cd", HpsHi, Hsp))
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(Spp)) and np.all(np.linalg.eigvalsh(0.5 * (Spp + Spp.T)) > 0)):
        return None
    # keep the tracks seen at k1 (the longest seen first), at most max_features
    # (a track with every sighting gated out, a slip, is left to the filter to augment again)
    used = np.bincount(ii[use], minlength=len(ids)) > 0
    at_end = np.flatnonzero(ok[-1, ids] & used)
    age = ok[:, ids[at_end]].sum(axis=0)
    keep = at_end[np.argsort(-age, kind="stable")[:max_features]]
    m = len(keep)
    A = -np.einsum("mab,mbc->mac", Hss_inv[keep], Hsp[keep])  # s_i's dependence on p
    Ssp = np.einsum("mac,cd->mad", A, Spp)  # (m, 3, npar)
    Sss = np.einsum("mac,nbc->manb", Ssp, A).reshape(3 * m, 3 * m)
    idx = np.arange(3 * m).reshape(m, 3)
    Sss[idx[:, :, None], idx[:, None, :]] += Hss_inv[keep]
    # the end state's derivatives over p: attitude (left error in That), rate, r, v; j itself
    R1 = R[-1]
    G = np.zeros((17, npar))
    Rpm, Wpm = perturbed(p, 1e-6)
    for c in range(3 + nj):
        G[0:3, c] = (rot.log_map(Rpm[0, c, -1] @ R1.T) - rot.log_map(Rpm[1, c, -1] @ R1.T)) / 2e-6
        G[3:6, c] = (Wpm[0, c, -1] - Wpm[1, c, -1]) / 2e-6
    G[6:12, 3 + nj :] = Phi[-1]
    if nj:
        G[12:17, 3 : 3 + nj] = np.eye(nj)
    D = 17 + 3 * m
    P = np.zeros((D, D))
    P[:17, :17] = G @ Spp @ G.T
    P[17:, :17] = Ssp.reshape(3 * m, npar) @ G.T
    P[:17, 17:] = P[17:, :17].T
    P[17:, 17:] = Sss
    _, W, _ = poses(p)
    x = np.zeros(13)
    x[0:4] = rot.matrix_to_quat(R1)
    x[4:7] = W[-1]
    x[7:13] = Phi[-1] @ p[3 + nj :]
    return BatchStart(
        k1,
        x,
        p[3 : 3 + nj].copy() if nj else j0.copy(),
        ids[keep],
        s[keep],
        0.5 * (P + P.T),
        float(np.sum(e[use] ** 2)),
        int(3 * use.sum()),
        it,
        int((~use).sum()),
        p[:3].copy(),
        p[3 + nj :].copy(),
        ids,
        s,
    )
