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
    _E_OFFSET,
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
    spin_axis_fixed,
    unexcited_ratios,
)
from tumblenav.estimators.yu2019.tuning import DepthTuning, plane_threshold
from tumblenav.frontends.depth_pose import (
    consistent_start,
    model_symmetries,
    pose_fixes,
    start_disagreement,
)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DepthSteps:
    """Yu 2019's EKF as stateless steps on one run's point clouds, folded by
    :func:`tumblenav.estimators.base.fold`: the plane front end turns each scan into pose
    fixes (with the predicted attitude for the multi-solution fix, eq. 21-25), the filter
    starts from the first scan with an unambiguous fix (Sec. 4) and updates with each fix
    (eq. 34-41). ``rng`` is the run's random stream (RANSAC, the initial inertia error),
    drawn in the order of the epochs.

    ``q_rot``, ``q_trans``: the spectral densities of Q (:func:`tuning.process_noise`;
    ``q_trans`` None: Yu's single Q). A run that has lost track (``reinit_after_gated``
    epochs in a row whose every fix the NIS gate rejects: a wrong start, or a wrong rectangle
    match it has followed) starts again from that epoch's fixes (tumblenav default), in the
    symmetric frame of the model nearest its last estimate; the belief's ``memo`` carries
    ``(gated epochs in a row, restart times)``."""

    model: Any
    meas: Any
    tun: DepthTuning
    sigma: float
    n_orbit: float
    rng: np.random.Generator
    q_rot: float = 1e-12
    q_trans: float | None = None
    layout: StateLayout = LAYOUT

    @functools.cached_property
    def symmetries(self) -> list[Array]:
        return model_symmetries(self.model.rectangles)

    @functools.cached_property
    def _max_rate(self) -> float:
        """The fastest rate the scans resolve (rad/s): pi per median scan interval."""
        return float(np.pi / self._scan_interval)

    @functools.cached_property
    def _scan_interval(self) -> float:
        dt = np.diff(np.asarray(self.meas.t, dtype=float))
        dt = dt[dt > 0]
        return float(np.median(dt)) if len(dt) else np.inf

    def _view_step(self, x: Array, P: Array) -> float:
        """How far the view of the target turns between two scans (rad): the estimated
        rate, with its uncertainty (a rate still unknown is not taken as zero), and the
        orbit's turn of L, over one scan interval."""
        w = float(np.sqrt(x[_X_RATE] @ x[_X_RATE] + np.trace(P[_E_RATE, _E_RATE])))
        return (w + self.n_orbit) * self._scan_interval

    @functools.cached_property
    def _frames(self) -> tuple[Array, Array]:
        return rot.quat_to_matrix(self.meas.q_CL), rot.quat_to_matrix(self.meas.q_LI)

    def _fixes(self, k: int, x: Array | None) -> list:
        """Epoch ``k``'s pose fixes (Yu 2019 Sec. 2-3), with the predicted attitude ``x``."""
        R_CL, R_LI = self._frames
        pts = self.meas.points[k][self.meas.observed[k]]
        R_SM_pred, p_pred = None, None
        if x is not None and self.tun.multi_solution_fix:
            R_SM_pred = R_CL[k] @ R_LI[k] @ rot.quat_to_matrix(x[_X_ATT]).T
            p_pred = R_CL[k] @ measurement(x, R_LI[k])[0]
        thr = plane_threshold(self.tun, self.sigma)
        return pose_fixes(
            pts, self.model, thr, self.rng, self.sigma, R_SM_pred, p_MinS_predicted=p_pred
        )[0]

    def initialise(self, k: int, previous: Array | None = None) -> tuple[Belief | None, StepInfo]:
        """Yu 2019 Sec. 4: start from the first observation, once a scan holds a fix that
        is not ambiguous (one rectangle alone leaves its four symmetric cases and faces of
        equal size undecided: wait for a scan with two or more, Sec. 2.3) and whose
        rectangles agree on one pose (tumblenav default: within ``start_agreement_deg`` and
        ``start_agreement_sides`` x the model's largest rectangle side; a plane taken for the
        wrong rectangle disagrees). ``previous``: the last estimate of a run that lost
        track; the start is then taken in the model's symmetric frame nearest to it."""
        fixes = self._fixes(k, None)
        if not fixes:
            return None, StepInfo(skipped={"no_rectangle": 1})
        if len(fixes) == 1 and not _only_model_symmetric(fixes[0], self.symmetries):
            return None, StepInfo(skipped={"ambiguous_start": 1})
        R_CL, R_LI = self._frames
        R_LS = R_CL[k].T
        R_SM0, p0 = consistent_start(fixes)
        angle, dist = start_disagreement(fixes, R_SM0, p0)
        size = max(max(r.sides_m) for r in self.model.rectangles)
        if angle > np.radians(self.tun.start_agreement_deg) or (
            dist > self.tun.start_agreement_sides * size
        ):
            return None, StepInfo(skipped={"ambiguous_start": 1})
        R_TI = (R_LI[k].T @ R_LS @ R_SM0).T
        if previous is not None:
            R_prev = rot.quat_to_matrix(previous[_X_ATT])
            R_TI = max((G @ R_TI for G in self.symmetries), key=lambda R: np.sum(R * R_prev))
        x = np.zeros(LAYOUT.nominal_dim)
        x[_X_ATT] = rot.matrix_to_quat(R_TI)
        x[_X_INERTIA] = _initial_inertia(self.tun, self.rng)
        x[_X_POS] = R_LS @ p0
        return Belief(float(self.meas.t[k]), x, _P0(self.tun), LAYOUT, (0, ())), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        x, P = _propagate(belief.x, belief.P, t - belief.t, self.n_orbit, self.q_rot, self.q_trans)
        return Belief(t, x, P, LAYOUT, belief.memo)

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        """Each fix of epoch ``k`` (Yu 2019 eq. 34-41), gated by its NIS; the start epoch's
        fixes made the start."""
        if started:
            return belief, StepInfo()
        tun = self.tun
        x, P = belief.x, belief.P
        fixes = self._fixes(k, x)
        skipped = {
            "no_rectangle": 0 if fixes else 1,
            "gated_out": 0,
            "nonphysical_inertia": 0,
            "nonphysical_rate": 0,
        }
        R_CL, R_LI = self._frames
        R_LS = R_CL[k].T
        nis, dof = 0.0, 0
        for fx in fixes:
            q_meas = rot.matrix_to_quat((R_LI[k].T @ R_LS @ fx.R_SM).T)  # R_TI = R_MS R_SL R_LI
            p_ML = R_LS @ fx.p_MinS
            cov_att, cov_pos = fix_covariance(
                fx, self.sigma, self._view_step(x, P), plane_threshold(tun, self.sigma)
            )
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
                if tun.consider_spin_axis_offset and spin_axis_fixed(
                    x[_X_RATE], x[_X_INERTIA], unexcited, P[_E_RATE, _E_RATE]
                ):
                    # a spin about a principal axis: the offset along the spin axis (fixed
                    # in T and in inertial space) is told from r only by the Hill model's
                    # curvature of r over the run (2% at 200 s in LEO), which mm of slowly
                    # varying fix error mimic; it gets no gain either (tumblenav default)
                    u = x[_X_RATE] / np.linalg.norm(x[_X_RATE])
                    K[_E_OFFSET] = (np.eye(3) - np.outer(u, u)) @ K[_E_OFFSET]
            A = np.eye(LAYOUT.dim) - K @ H
            P = A @ P @ A.T + K @ R @ K.T  # Joseph form
            x_new = LAYOUT.boxplus(x, K @ nu)
            if not physical_inertia(x_new[_X_INERTIA]) and physical_inertia(x[_X_INERTIA]):
                # a step that makes the inertia not positive definite would let the Euler
                # equations explode: keep the ratios where they were, take the rest, and
                # count it
                x_new[_X_INERTIA] = x[_X_INERTIA]
                skipped["nonphysical_inertia"] += 1
            if np.linalg.norm(x_new[_X_RATE]) > self._max_rate:
                # a rate beyond pi per scan interval cannot be told from a slower one (the
                # scans alias it): such a step (a jump between symmetric cases) keeps the
                # previous rate, and is counted (tumblenav default)
                x_new[_X_RATE] = x[_X_RATE]
                skipped["nonphysical_rate"] += 1
            x = x_new
            nis += d2
            dof += 6
        gated_run, restarts = belief.memo if belief.memo is not None else (0, ())
        gated_run = gated_run + 1 if fixes and dof == 0 else 0 if dof else gated_run
        if tun.multi_solution_fix and gated_run >= tun.reinit_after_gated:
            # lost track: every fix of the last epochs disagreed with the prediction
            fresh, why = self.initialise(k, previous=x)
            if fresh is not None:
                skipped["reinitialised"] = 1
                memo = (0, (*restarts, float(self.meas.t[k])))
                return Belief(belief.t, fresh.x, fresh.P, LAYOUT, memo), StepInfo(skipped=skipped)
        info = StepInfo(nis=nis if dof else float("nan"), dof=dof, skipped=skipped)
        return Belief(belief.t, x, P, LAYOUT, (gated_run, restarts)), info

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P
