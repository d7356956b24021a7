"""Yu 2019's EKF as stateless steps (:class:`DepthSteps`) folded per run."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from tumblenav import rotations as rot
from tumblenav.estimators.base import (
    Belief,
    StateLayout,
    StepInfo,
)
from tumblenav.estimators.yu2019.fixes import _only_model_symmetric, fix_covariance
from tumblenav.estimators.yu2019.model import (
    _E_ATT,
    _E_INERTIA,
    _E_RATE,
    _P0,
    _X_ATT,
    _X_INERTIA,
    _X_POS,
    _X_RATE,
    LAYOUT,
    _initial_inertia,
    _propagate,
    measurement,
    physical_inertia,
    unexcited_ratios,
)
from tumblenav.estimators.yu2019.tuning import DepthTuning, plane_threshold
from tumblenav.frontends.depth_pose import consistent_start, model_symmetries, pose_fixes

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DepthSteps:
    """Yu 2019's EKF as stateless steps on one run's point clouds, folded by
    :func:`tumblenav.estimators.base.fold`: the plane front end turns each scan into pose
    fixes (with the predicted attitude for the multi-solution fix, eq. 21-25), the filter
    starts from the first scan with an unambiguous fix (Sec. 4) and updates with each fix
    (eq. 34-41). ``rng`` is the run's random stream (RANSAC, the initial inertia error),
    drawn in the order of the epochs."""

    model: Any
    meas: Any
    tun: DepthTuning
    sigma: float
    n_orbit: float
    rng: np.random.Generator
    layout: StateLayout = LAYOUT

    @functools.cached_property
    def symmetries(self) -> list[Array]:
        return model_symmetries(self.model.rectangles)

    @functools.cached_property
    def _frames(self) -> tuple[Array, Array]:
        return rot.quat_to_matrix(self.meas.q_CL), rot.quat_to_matrix(self.meas.q_LI)

    def _fixes(self, k: int, x: Array | None) -> list:
        """Epoch ``k``'s pose fixes (Yu 2019 Sec. 2-3), with the predicted attitude ``x``."""
        R_CL, R_LI = self._frames
        pts = self.meas.points[k][self.meas.observed[k]]
        R_SM_pred = None
        if x is not None and self.tun.multi_solution_fix:
            R_SM_pred = R_CL[k] @ R_LI[k] @ rot.quat_to_matrix(x[_X_ATT]).T
        thr = plane_threshold(self.tun, self.sigma)
        return pose_fixes(pts, self.model, thr, self.rng, self.sigma, R_SM_pred)[0]

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        """Yu 2019 Sec. 4: start from the first observation, once a scan holds a fix that
        is not ambiguous (one rectangle alone leaves its four symmetric cases and faces of
        equal size undecided: wait for a scan with two or more, Sec. 2.3)."""
        fixes = self._fixes(k, None)
        if not fixes:
            return None, StepInfo(skipped={"no_rectangle": 1})
        if len(fixes) == 1 and not _only_model_symmetric(fixes[0], self.symmetries):
            return None, StepInfo(skipped={"ambiguous_start": 1})
        R_CL, R_LI = self._frames
        R_LS = R_CL[k].T
        R_SM0, p0 = consistent_start(fixes)
        x = np.zeros(LAYOUT.nominal_dim)
        x[_X_ATT] = rot.matrix_to_quat((R_LI[k].T @ R_LS @ R_SM0).T)
        x[_X_INERTIA] = _initial_inertia(self.tun, self.rng)
        x[_X_POS] = R_LS @ p0
        return Belief(float(self.meas.t[k]), x, _P0(self.tun), LAYOUT), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        x, P = _propagate(belief.x, belief.P, t - belief.t, self.n_orbit, self.tun.Q_diag)
        return Belief(t, x, P, LAYOUT)

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        """Each fix of epoch ``k`` (Yu 2019 eq. 34-41), gated by its NIS; the start epoch's
        fixes made the start."""
        if started:
            return belief, StepInfo()
        tun = self.tun
        x, P = belief.x, belief.P
        fixes = self._fixes(k, x)
        skipped = {"no_rectangle": 0 if fixes else 1, "gated_out": 0, "nonphysical_inertia": 0}
        R_CL, R_LI = self._frames
        R_LS = R_CL[k].T
        nis, dof = 0.0, 0
        for fx in fixes:
            q_meas = rot.matrix_to_quat((R_LI[k].T @ R_LS @ fx.R_SM).T)  # R_TI = R_MS R_SL R_LI
            p_ML = R_LS @ fx.p_MinS
            cov_att, cov_pos = fix_covariance(fx, self.sigma)
            cov_att = tun.attitude_noise_scale * cov_att
            cov_pos = tun.position_noise_scale * cov_pos
            R_LP = R_LS @ fx.R_SM @ fx.R_MP if fx.R_MP is not None else np.eye(3)
            R_TP = fx.R_MP if fx.R_MP is not None else np.eye(3)
            y, Hp = measurement(x, R_LI[k])
            H_att = np.zeros((3, LAYOUT.dim))
            H_att[:, _E_ATT] = np.eye(3)
            H = np.vstack([H_att, Hp])
            nu = np.r_[rot.boxminus(q_meas, x[_X_ATT]), p_ML - y]
            R = np.zeros((6, 6))
            R[:3, :3] = R_TP @ cov_att @ R_TP.T
            R[3:, 3:] = R_LP @ cov_pos @ R_LP.T
            S = H @ P @ H.T + R
            d2 = nu @ np.linalg.solve(S, nu)
            if tun.multi_solution_fix and d2 > chi2.ppf(tun.gate_probability, 6):
                # NIS gate (rejections counted); off without the fix, to show its jumps
                skipped["gated_out"] += 1
                continue
            K = np.linalg.solve(S, H @ P).T
            if tun.consider_unexcited_ratios:
                # Schmidt (consider) update for the ratios the motion does not excite: no
                # gain, so no information from nothing; their covariance and its coupling to
                # the rate stay, and the Joseph form below is exact for any gain
                unexcited = unexcited_ratios(x[_X_RATE], x[_X_INERTIA], P[_E_RATE, _E_RATE])
                K[_E_INERTIA][unexcited] = 0.0
            A = np.eye(LAYOUT.dim) - K @ H
            P = A @ P @ A.T + K @ R @ K.T  # Joseph form
            x_new = LAYOUT.boxplus(x, K @ nu)
            if not physical_inertia(x_new[_X_INERTIA]):
                # a step that makes the inertia not positive definite would let the Euler
                # equations explode: keep the ratios where they were, take the rest, and
                # count it
                x_new[_X_INERTIA] = x[_X_INERTIA]
                skipped["nonphysical_inertia"] += 1
            x = x_new
            nis += d2
            dof += 6
        info = StepInfo(nis=nis if dof else float("nan"), dof=dof, skipped=skipped)
        return Belief(belief.t, x, P, LAYOUT), info

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P
