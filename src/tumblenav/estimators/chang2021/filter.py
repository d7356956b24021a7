"""Chang 2021's EKF (Sec. 2.1-2.2) as stateless steps (:class:`PoseSteps`) folded per run.

Measurement (eq. 32): ``y = [q_ThatL, omega_ThatL_That, rho_0, rho_dot_0]`` from each epoch's
features (:mod:`.measurements`), error-state innovations ``[boxminus(q_meas, q_hat),
omega_meas - omega_hat, rho_0 - r_hat, rho_dot_0 - v_hat]`` with

* attitude: Davenport's q-method of the registered features (eq. 27-28), ``H = [I, 0, ...]``;
* rate: eq. 29 in L, rotated into That with the measured attitude, ``H = [0, I, 0, ...]``;
* position: eq. 30, ``rho_0 = rho_bar - R_LThat (s_bar - b_hat)`` (weighted means over the
  used features; ``s`` about the map origin, ``b`` the mass centre about it), so
  ``H = [0, 0, I, 0, -R_LThat]`` (eq. 32's ``H`` is not printed; with Chang's truth-registered
  ``r_i^t`` the ``b`` column vanishes and ``H`` is the identity);
* velocity: eq. 30, ``rho_dot_0 = mean(rho_dot_i) - omega_L x (mean(rho_i) - r_hat)``, so
  ``H = [0, 0, -[omega_L x], I, 0]``.

``R`` is first order from the pixel noise (the q-method sandwich, the triangulation and eq. 26
covariances, the eq. 29 sandwich) with the couplings through the measured attitude and rate,
times ``measurement_noise_scale``. Each of the four 3-dof blocks is gated by its own NIS
(chi-square, ``gate_probability``) against the prediction; rejected blocks are counted in
``StepInfo.rejected`` and ``skipped['gated_out']``; the accepted ones update jointly (Joseph
form; ``b`` gets no gain unless ``mass_centre: estimated``). Features seen for the first time
are registered in the map with the updated estimate (eq. 30's ``r_i^t``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from tumblenav import rotations as rot
from tumblenav.estimators.base import Belief, StateLayout, StepInfo
from tumblenav.estimators.chang2021.init import (
    FeatureMap,
    Start,
    _lever_cov,
    _rate,
    first_usable_epoch,
    start,
)
from tumblenav.estimators.chang2021.measurements import (
    FeatureTracks,
    PoseFix,
    feature_tracks,
    pose_fix,
)
from tumblenav.estimators.chang2021.model import (
    DIM,
    E_ATT,
    E_OFF,
    E_POS,
    E_RATE,
    E_VEL,
    LAYOUT,
    X_ATT,
    X_OFF,
    X_POS,
    X_RATE,
    X_VEL,
    omega_LI_L,
    propagate,
)
from tumblenav.estimators.chang2021.tuning import PoseTuning

Array = NDArray[np.float64]

_MAX_SIGMA = 1e6  # a covariance beyond this (or not finite) means the run diverged


def disturbance_rate_noise(tun: PoseTuning, q_r: float) -> float | Array:
    """The rate random walk (rad^2/s^3, in That) that the scenario's disturbance torque
    causes (``process_noise.rotational_rad2_s4`` = ``q_r``: the angular acceleration's
    spectral density about the axis of largest moment; about axis ``i`` it is ``q_r (I_max /
    I_i)^2``, :mod:`tumblenav.dynamics.disturbances`): with a given inertia the (3, 3)
    :func:`torque_rate_noise`; with inertia 'sphere' (unknown, That not the principal frame)
    one isotropic value for moments ``k`` (inertia_asymmetry) apart, ``q_r (1 + k)^2``
    (tumblenav default). ``rate_noise_rad2_s3``, when set, replaces it."""
    if tun.rate_noise_rad2_s3 is not None:
        return float(tun.rate_noise_rad2_s3)
    if tun.inertia == "given":
        return torque_rate_noise(q_r, tun.inertia_matrix())
    return float(q_r * (1.0 + tun.inertia_asymmetry) ** 2)


def torque_rate_noise(q_r: float, inertia: Array) -> Array:
    """(3, 3) rate random walk of an isotropic torque on ``inertia`` (3, 3, in That, any
    scale): the torque's density ``q_tau = q_r I_max^2`` (``q_r`` about the axis of largest
    moment) becomes ``q_tau J^-1 J^-T = q_r I_max^2 J^-2`` on the rate, about each principal
    axis ``q_r (I_max / I_i)^2``. Before issue 18's twenty-fifth session the mean of those
    over the axes, isotropic: on a scenario nobody tuned for (inertia (30, 20, 45), the
    smallest axis' walk 5.1 q_r against a stated 2.8 q_r) ekf-pose's rate was over-confident
    (block NEES/dof 1.9, the attitude's 2.7 over runs 0-5; docs/results/consistency.md)."""
    ev, V = np.linalg.eigh(0.5 * (inertia + inertia.T))
    return np.asarray(q_r * (V * (ev.max() / ev) ** 2) @ V.T)


def rate_process_noise(
    x: Array, tun: PoseTuning, n: float, q_dist: float | Array = 0.0
) -> float | Array:
    """Spectral density (rad^2/s^3) of the rate random walk: with inertia 'sphere' the
    unmodelled Euler term, ``2 k^2 |omega_TI|^3 / 27`` (``k``: inertia_asymmetry; the term's
    per-axis RMS ``k |omega|^2 / 3`` over a correlation time ``1/|omega|``), plus the
    disturbance torque's ``q_dist`` (:func:`disturbance_rate_noise`)."""
    q = q_dist
    if tun.inertia == "sphere":
        w_ti = x[X_RATE] + rot.quat_to_matrix(x[X_ATT]) @ omega_LI_L(n)
        # a new value, not in place: q_dist may be a cached (3, 3) array
        q = q + 2.0 * tun.inertia_asymmetry**2 * float(np.linalg.norm(w_ti)) ** 3 / 27.0
    return q


@dataclass(frozen=True)
class PoseMemo:
    """What the filter carries besides the mean and covariance (immutable): the feature map
    and the start it grew from (the frame epoch ``start.k0`` and the map origin
    ``start.origin_L_k0`` define the estimator's frame and offset)."""

    fmap: FeatureMap
    start: Start


@dataclass(frozen=True)
class TrackSteps:
    """What both ekf-pose folds derive from one run's stereo tracks: the triangulated tracks,
    the inertia the dynamics use, and the epoch that defines the estimator's frame."""

    meas: Any
    tun: PoseTuning
    n_orbit: float
    q_rot: float = 0.0  # the scenario's process_noise.rotational_rad2_s4 (rad^2/s^3)
    q_trans: float = 0.0  # the scenario's process_noise.translational_m2_s4 (m^2/s^3)

    @functools.cached_property
    def q_rate_dist(self) -> float | Array:
        """The disturbance torque's rate random walk (:func:`disturbance_rate_noise`)."""
        return disturbance_rate_noise(self.tun, self.q_rot)

    @functools.cached_property
    def q_accel(self) -> float:
        """White-acceleration spectral density of the CW model: ``accel_noise_m2_s3`` or the
        scenario's ``process_noise.translational_m2_s4``."""
        a = self.tun.accel_noise_m2_s3
        return float(self.q_trans if a is None else a)

    def rate_noise(self, x: Array, inertia: Array | None = None) -> float | Array:
        """The rate random walk's spectral density at ``x`` (:func:`rate_process_noise`); with
        inertia 'estimated' the disturbance's share from the current estimate ``inertia``."""
        q_dist = self.q_rate_dist
        if (
            self.tun.inertia == "estimated"
            and inertia is not None
            and self.tun.rate_noise_rad2_s3 is None
        ):
            q_dist = torque_rate_noise(self.q_rot, inertia)
        return rate_process_noise(x, self.tun, self.n_orbit, q_dist)

    @functools.cached_property
    def tracks(self) -> FeatureTracks:
        return feature_tracks(self.meas)

    @functools.cached_property
    def inertia(self) -> Array:
        return self.tun.inertia_matrix()

    @functools.cached_property
    def k0(self) -> int | None:
        """That's defining epoch: the first epoch whose features fix a rotation."""
        return first_usable_epoch(self.tracks, self.tun, len(self.meas.t) - 1)

    def start_at(self, k: int) -> tuple[Start | None, StepInfo]:
        """Chang 2021 Sec. 4.1: the first ``init_frames`` frames from k0 start the filter
        (:func:`tumblenav.estimators.chang2021.init.start`), at the window's last frame;
        None and why before that (or when the window gives no start)."""
        k0 = self.k0
        if k0 is None or k < k0:
            return None, StepInfo(skipped={"no_start_geometry": 1})
        if k < k0 + self.tun.init_frames - 1:
            return None, StepInfo(skipped={"initialising": 1})
        s = start(self.tracks, self.meas.t, k0, k, self.tun, self.n_orbit)
        if s is None:
            return None, StepInfo(skipped={"initialising": 1})
        return s, StepInfo()


@dataclass(frozen=True)
class PoseSteps(TrackSteps):
    """ekf-pose on one run's stereo tracks, folded by :func:`tumblenav.estimators.base.fold`.
    The belief's ``memo`` is a :class:`PoseMemo`; the fold's last memo tells the run where
    the estimator's frame was defined (no mutable state on the steps)."""

    layout: StateLayout = LAYOUT

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        """The start of :meth:`TrackSteps.start_at` as the first belief."""
        s, info = self.start_at(k)
        if s is None:
            return None, info
        return Belief(float(self.meas.t[k]), s.x, s.P, LAYOUT, PoseMemo(s.fmap, s)), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        dt = t - belief.t
        x, P = propagate(
            belief.x,
            belief.P,
            dt,
            self.inertia,
            self.n_orbit,
            self.rate_noise(belief.x),
            self.q_accel,
        )
        return Belief(t, x, P, LAYOUT, belief.memo)

    def _measure(
        self, x: Array, k: int, fmap: FeatureMap
    ) -> tuple[list[tuple[str, Array, Array]], Array, dict[str, int], PoseFix | None]:
        """The blocks of eq. 32 at epoch ``k``: (name, innovation, H rows), their joint R,
        skip counts and the outlier features dropped."""
        tr, tun = self.tracks, self.tun
        skipped: dict[str, int] = {}
        idx = np.flatnonzero(tr.ok_p[k])
        if len(idx) == 0:
            return [], np.zeros((0, 0)), {"no_features": 1}, None
        reg = idx[fmap.count[idx] > 0]
        if len(reg) < tun.min_features:
            return [], np.zeros((0, 0)), {"too_few_features": 1}, None
        fix = pose_fix(
            tr.p[k, reg],
            tr.P[k, reg],
            fmap.s[reg],
            fmap.cov(reg),
            tun.reference,
            tun.feature_gate_probability,
            tun.min_features,
        )
        if fix is None:
            return [], np.zeros((0, 0)), {"degenerate_geometry": 1}, None
        R_ThatL = rot.quat_to_matrix(fix.q_ThatL)
        R_LThat = R_ThatL.T
        b = x[X_OFF]
        blocks: list[tuple[str, Array, Array]] = []
        Rs: list[Array] = []
        # attitude (eq. 27-28)
        H = np.zeros((3, DIM))
        H[:, E_ATT] = np.eye(3)
        blocks.append(("attitude", rot.boxminus(fix.q_ThatL, x[X_ATT]), H))
        # position (eq. 30)
        a = fix.s_bar - b
        z_pos = fix.rho_bar - R_LThat @ a
        J = -R_LThat @ rot.skew(a)  # d z_pos / d dtheta_meas
        H = np.zeros((3, DIM))
        H[:, E_POS] = np.eye(3)
        H[:, E_OFF] = -R_LThat
        blocks.append(("position", z_pos - x[X_POS], H))
        R_pos = fix.C_rho_bar + R_LThat @ fix.C_s_bar @ R_ThatL + J @ fix.P_att @ J.T
        Rs_blocks = {"attitude": fix.P_att, "position": R_pos}
        cross = {("position", "attitude"): J @ fix.P_att}
        if tun.use_rate_velocity:
            iv = np.flatnonzero(tr.ok_v[k])
            r = _rate(tr, k, iv) if len(iv) >= tun.min_features else None
            if r is None:
                skipped["no_rate"] = 1
            else:
                w_L, C_w = r
                H = np.zeros((3, DIM))
                H[:, E_RATE] = np.eye(3)
                blocks.append(("rate", R_ThatL @ w_L - x[X_RATE], H))
                Rs_blocks["rate"] = R_ThatL @ C_w @ R_ThatL.T
                V = tr.V[k, iv]
                w = 3.0 / np.trace(V, axis1=-2, axis2=-1)
                W = w / w.sum()
                p_mid = W @ (0.5 * (tr.p[k, iv] + tr.p[k - 1, iv]))
                c = p_mid - x[X_POS]
                z_vel = W @ tr.v[k, iv] - np.cross(w_L, c)  # eq. 30
                H = np.zeros((3, DIM))
                H[:, E_POS] = -rot.skew(w_L)
                H[:, E_VEL] = np.eye(3)
                blocks.append(("velocity", z_vel - x[X_VEL], H))
                Sc = rot.skew(c)
                Rs_blocks["velocity"] = np.einsum("m,mij->ij", W**2, V) + Sc @ C_w @ Sc.T
                cross[("velocity", "rate")] = Sc @ C_w @ R_ThatL.T
        names = [nm for nm, _, _ in blocks]
        m = 3 * len(blocks)
        R = np.zeros((m, m))
        for i, nm in enumerate(names):
            R[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = Rs_blocks[nm]
        for (p_, q_), C in cross.items():
            i, j = names.index(p_), names.index(q_)
            R[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] = C
            R[3 * j : 3 * j + 3, 3 * i : 3 * i + 3] = C.T
        del Rs
        return blocks, tun.measurement_noise_scale * R, skipped, fix

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        """Epoch ``k``'s measurement (eq. 32), gated block by block; then the new features
        are registered. The start epoch's measurements made the start."""
        if started:
            return belief, StepInfo()
        x, P, memo = belief.x, belief.P, belief.memo
        fmap = memo.fmap
        blocks, R, skipped, fix = self._measure(x, k, fmap)
        if fix is not None and fix.outliers:
            skipped["outlier_features"] = fix.outliers
        nis, dof, rejected = float("nan"), 0, 0
        if blocks:
            gate = chi2.ppf(self.tun.gate_probability, 3)
            keep = []
            for i, (_, nu, H) in enumerate(blocks):
                s = slice(3 * i, 3 * i + 3)
                S = H @ P @ H.T + R[s, s]
                if nu @ np.linalg.solve(S, nu) <= gate:
                    keep.append(i)
            rejected = len(blocks) - len(keep)
            if rejected:
                skipped["gated_out"] = rejected
            if keep:
                rows = np.concatenate([np.arange(3 * i, 3 * i + 3) for i in keep])
                nu = np.concatenate([blocks[i][1] for i in keep])
                H = np.vstack([blocks[i][2] for i in keep])
                Rk = R[np.ix_(rows, rows)]
                S = H @ P @ H.T + Rk
                K = np.linalg.solve(S, H @ P).T
                if self.tun.mass_centre == "consider":
                    K[E_OFF] = 0.0  # Schmidt: the offset keeps its value, not its covariance
                A = np.eye(DIM) - K @ H
                P = A @ P @ A.T + K @ Rk @ K.T  # Joseph form (exact for any gain)
                P = 0.5 * (P + P.T)
                x = LAYOUT.boxplus(x, K @ nu)
                nis, dof = float(nu @ np.linalg.solve(S, nu)), len(nu)
        if (
            not (np.all(np.isfinite(x)) and np.all(np.isfinite(P)))
            or np.max(np.diag(P)) > _MAX_SIGMA**2
        ):
            return belief, StepInfo(diverged=True, skipped={"diverged": 1})
        fmap = self._register(x, P, k, fmap, fix)
        return Belief(belief.t, x, P, LAYOUT, PoseMemo(fmap, memo.start)), StepInfo(
            nis=nis, dof=dof, rejected=rejected, skipped=skipped
        )

    def _register(
        self, x: Array, P: Array, k: int, fmap: FeatureMap, fix: PoseFix | None
    ) -> FeatureMap:
        """Eq. 30's ``r_i^t`` about the map origin: ``s_i = R_ThatL (rho_i - c)`` with the
        updated attitude, for the features seen fewer than ``register_frames`` times. The
        origin ``c`` is this epoch's own (``rho_bar - R_LThat s_bar`` of the pose fix), so the
        map stays consistent with itself whatever the filter's translational error; without
        a fix, the estimate's ``r - R_LThat b``."""
        tr = self.tracks
        idx = np.flatnonzero(tr.ok_p[k])
        if len(idx) == 0:
            return fmap
        R = rot.quat_to_matrix(x[X_ATT])
        c = fix.rho_bar - R.T @ fix.s_bar if fix is not None else x[X_POS] - R.T @ x[X_OFF]
        s_obs = (tr.p[k, idx] - c) @ R.T
        S_obs = R @ tr.P[k, idx] @ R.T + _lever_cov(s_obs, P[E_ATT, E_ATT])
        return fmap.register(idx, s_obs, S_obs, self.tun.register_frames)

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P
