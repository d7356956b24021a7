"""The start of ekf-pose from the first frames alone (Chang 2021 Sec. 4.1: 100 frames), and the
feature map (each feature's position in the estimator's frame That, eq. 30's ``r_i^t``).

Chang starts from the simulation's truth (Sec. 4.2); tumblenav starts from the measurements:

1. That is defined at the first usable epoch k0 (enough features that fix a rotation):
   ``R_ThatL(k0) = I``. The map origin is the weighted centroid of k0's features, which are
   registered at ``s_i = rho_i - c(k0)``.
2. Every later window epoch: the q-method (eq. 27-28) of the registered features gives
   ``R_ThatL(t)``, the weighted centroids give the map origin ``c(t) = rho_bar - R_LThat
   s_bar``; features seen for the first time are registered, young ones refined.
3. The mass centre ``r(t) = c(t) + R_LThat(t) b`` follows CW from six unknown initial values:
   linear least squares for ``[r(k0), v(k0), b]`` with a prior ``b ~ N(0,
   prior_mass_centre_sigma_m^2 I)`` for the directions the window's rotation leaves weak;
   the LS covariance, propagated to the window's end, is the start covariance.
4. The rate: eq. 29 at every window epoch, rotated into That, and a straight line fitted to
   it (the rate drifts in the body under the unknown Euler torque); its value and covariance at
   the window's end start the filter.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.dynamics.relative_orbit import cw_stm
from tumblenav.estimators.chang2021.measurements import FeatureTracks, pose_fix, rate_eq29
from tumblenav.estimators.chang2021.model import DIM, E_ATT, E_OFF, E_POS, E_RATE, E_VEL, LAYOUT
from tumblenav.estimators.chang2021.tuning import PoseTuning

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FeatureMap:
    """Registered features: ``s`` (N, 3) m in That about the map origin, ``S_sum`` (N, 3, 3)
    the sum of the registering observations' covariances, ``count`` (N,) how many (0: not
    registered). Immutable: :meth:`register` returns a new map."""

    s: Array
    S_sum: Array
    count: NDArray[np.int64]

    @classmethod
    def empty(cls, N: int) -> FeatureMap:
        return cls(np.zeros((N, 3)), np.zeros((N, 3, 3)), np.zeros(N, np.int64))

    def cov(self, idx: NDArray[np.int64]) -> Array:
        c = np.maximum(self.count[idx], 1)[:, None, None]
        return self.S_sum[idx] / c**2  # covariance of the running mean

    def register(
        self, idx: NDArray[np.int64], s_obs: Array, S_obs: Array, max_count: int
    ) -> FeatureMap:
        """Add observations ``s_obs`` (M, 3) of features ``idx`` to features seen fewer than
        ``max_count`` times (running mean)."""
        young = self.count[idx] < max_count
        if not young.any():
            return self
        i = idx[young]
        s, S, c = self.s.copy(), self.S_sum.copy(), self.count.copy()
        ci = c[i][:, None]
        s[i] = (ci * s[i] + s_obs[young]) / (ci + 1)
        S[i] = S[i] + S_obs[young]
        c[i] += 1
        return replace(self, s=s, S_sum=S, count=c)


def _usable(tracks: FeatureTracks, k: int, tun: PoseTuning) -> bool:
    idx = np.flatnonzero(tracks.ok_p[k])
    if len(idx) < tun.min_features:
        return False
    p = tracks.p[k, idx]
    return (
        pose_fix(p, tracks.P[k, idx], p, np.zeros_like(tracks.P[k, idx]), "centroid", 0.9999)
        is not None
    )


def first_usable_epoch(tracks: FeatureTracks, tun: PoseTuning, upto: int) -> int | None:
    """The first epoch <= ``upto`` whose features fix a rotation (That's defining epoch k0)."""
    for k in range(upto + 1):
        if _usable(tracks, k, tun):
            return k
    return None


@dataclass(frozen=True)
class Start:
    """The start: epoch ``k`` (end of the window), the state ``x`` (16) and covariance ``P``
    (15, 15), the map, the defining epoch ``k0`` and the map origin at k0 in L."""

    k: int
    x: Array
    P: Array
    fmap: FeatureMap
    k0: int
    origin_L_k0: Array
    omega_k0: Array | None = None  # the rate line's value at k0 (in That) and its covariance
    P_omega_k0: Array | None = None
    fit: str = "window"  # how ekf-pose's map state took the start: replay, batch, batch+replay
    fit_cost: float | None = None  # the batch fit's whitened cost per residual
    fit_noise_ratio: float | None = None  # slam.StateSteps._window_noise


def start(
    tracks: FeatureTracks, t: Array, k0: int, k_end: int, tun: PoseTuning, n: float
) -> Start | None:
    """Steps 1-4 of the module docstring on epochs ``k0..k_end``; None if the window holds
    fewer than three pose fixes or no rate."""
    N = tracks.p.shape[1]
    fmap = FeatureMap.empty(N)
    rows: list[tuple[float, Array, Array, Array]] = []  # (t, R_LThat, c, Cc)
    rates: list[tuple[float, Array, Array]] = []
    q_last, P_att_last = rot.IDENTITY.copy(), np.zeros((3, 3))
    for k in range(k0, k_end + 1):
        idx = np.flatnonzero(tracks.ok_p[k])
        if len(idx) == 0:
            continue
        rho, S_rho = tracks.p[k, idx], tracks.P[k, idx]
        if not rows:
            w = 3.0 / np.trace(S_rho, axis1=-2, axis2=-1)
            W = w / w.sum()
            c = W @ rho
            R_ThatL = np.eye(3)
            Cc = np.einsum("m,mij->ij", W**2, S_rho)
            P_att = np.zeros((3, 3))
            q = rot.IDENTITY.copy()
        else:
            reg = fmap.count[idx] > 0
            if reg.sum() < tun.min_features:
                continue
            fix = pose_fix(
                rho[reg],
                S_rho[reg],
                fmap.s[idx[reg]],
                fmap.cov(idx[reg]),
                tun.reference,
                tun.feature_gate_probability,
                tun.min_features,
            )
            if fix is None:
                continue
            q, P_att = fix.q_ThatL, fix.P_att
            R_ThatL = rot.quat_to_matrix(q)
            c = fix.rho_bar - R_ThatL.T @ fix.s_bar
            J = -R_ThatL.T @ rot.skew(fix.s_bar)
            Cc = fix.C_rho_bar + R_ThatL.T @ fix.C_s_bar @ R_ThatL + J @ P_att @ J.T
        rows.append((float(t[k]), R_ThatL.T, c, Cc))
        q_last, P_att_last = q, P_att
        s_obs = (rho - c) @ R_ThatL.T
        S_obs = R_ThatL @ S_rho @ R_ThatL.T + _lever_cov(s_obs, P_att)
        fmap = fmap.register(idx, s_obs, S_obs, tun.register_frames)
        # eq. 29 at this epoch (features with a velocity), rotated into That
        iv = np.flatnonzero(tracks.ok_v[k])
        if len(iv) >= tun.min_features:
            r = _rate(tracks, k, iv)
            if r is not None:
                rates.append((float(t[k]), R_ThatL @ r[0], R_ThatL @ r[1] @ R_ThatL.T))
    if len(rows) < 3 or len(rates) < 2:
        return None

    # step 3: r(t) = Phi_r(t - t0) [r0; v0] = c(t) + R_LThat(t) b
    t0, t_end = float(t[k0]), float(t[k_end])
    A = np.zeros((9, 9))
    y = np.zeros(9)
    for tk, R_LThat, c, Cc in rows:
        Ak = np.hstack([cw_stm(n, tk - t0)[:3], -R_LThat])
        Wk = np.linalg.inv(Cc + 1e-12 * np.eye(3))
        A += Ak.T @ Wk @ Ak
        y += Ak.T @ Wk @ c
    A[6:, 6:] += np.eye(3) / tun.prior_mass_centre_sigma_m**2  # prior b ~ N(0, sigma^2)
    Pu = np.linalg.inv(A)
    u = Pu @ y
    T = np.zeros((9, 9))  # [r0, v0, b] -> [r, v, b] at t_end
    T[:6, :6] = cw_stm(n, t_end - t0)
    T[6:, 6:] = np.eye(3)
    rvb = T @ u
    P_rvb = T @ Pu @ T.T

    # step 4: a straight line through the rates (in That): value and covariance at t_end
    G = np.zeros((6, 6))
    g = np.zeros(6)
    for tk, w_T, C in rates:
        Bk = np.hstack([np.eye(3), (tk - t_end) * np.eye(3)])
        Wk = np.linalg.inv(C)
        G += Bk.T @ Wk @ Bk
        g += Bk.T @ Wk @ w_T
    Gi = np.linalg.inv(G)
    line = Gi @ g
    omega = line[:3]
    P_omega = Gi[:3, :3]
    B0 = np.hstack([np.eye(3), (t0 - t_end) * np.eye(3)])  # the line at k0 (the replay's start)
    omega_k0, P_omega_k0 = B0 @ line, B0 @ Gi @ B0.T

    # The window's map origin c(t) has errors correlated from epoch to epoch (the map is built
    # from its own poses), which the LS treats as independent: along the weakly observed
    # directions its covariance of b is too small. The start therefore keeps the prior's
    # uncertainty on b in full, with the position and velocity it moves along:
    # r = c + R_LThat b, v = c_dot + omega_L x R_LThat b.
    R_LThat_end = rows[-1][1]
    w_L = R_LThat_end @ omega
    Gb = np.vstack([R_LThat_end, rot.skew(w_L) @ R_LThat_end, np.eye(3)])
    P_rvb = P_rvb + tun.prior_mass_centre_sigma_m**2 * Gb @ Gb.T

    x = np.zeros(LAYOUT.nominal_dim)
    x[LAYOUT.nom("attitude")] = q_last
    x[LAYOUT.nom("rate")] = omega
    x[LAYOUT.nom("position")] = rvb[:3]
    x[LAYOUT.nom("velocity")] = rvb[3:6]
    x[LAYOUT.nom("offset")] = rvb[6:]
    P = np.zeros((DIM, DIM))
    P[E_ATT, E_ATT] = P_att_last
    P[E_RATE, E_RATE] = P_omega
    sl = np.r_[np.arange(E_POS.start, E_VEL.stop), np.arange(E_OFF.start, E_OFF.stop)]
    P[np.ix_(sl, sl)] = P_rvb
    return Start(
        k_end, x, 0.5 * (P + P.T), fmap, k0, rows[0][2], omega_k0, 0.5 * (P_omega_k0 + P_omega_k0.T)
    )


def _lever_cov(s: Array, P_att: Array) -> Array:
    """Covariance (M, 3, 3) a registration ``s_i = R_ThatL (rho_i - c)`` inherits from the
    attitude error ``P_att`` (left error in That: ``ds_i = -[s_i x] dtheta`` to first
    order ``[s_i x] P_att [s_i x]^T``), about the weighted centroid of the registered set."""
    S = rot.skew(s - s.mean(axis=0))
    return np.einsum("mij,jk,mlk->mil", S, P_att, S)


def _rate(tracks: FeatureTracks, k: int, iv: NDArray[np.int64]) -> tuple[Array, Array] | None:
    """Chang 2021 eq. 29 at epoch ``k`` on the features ``iv`` with a velocity: difference
    vectors from their weighted centroid (positions at the middle of the differenced
    interval)."""
    V = tracks.V[k, iv]
    w = 3.0 / np.trace(V, axis1=-2, axis2=-1)
    W = w / w.sum()
    p = 0.5 * (tracks.p[k, iv] + tracks.p[k - 1, iv])
    v = tracks.v[k, iv]
    return rate_eq29(p - W @ p, v - W @ v, V)
