"""Yu 2019's EKF as stateless steps (:class:`DepthSteps`) folded per run."""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
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
from tumblenav.estimators.yu2019.fixes import _only_model_symmetric, fix_noise
from tumblenav.estimators.yu2019.model import (
    _E_ATT,
    _E_INERTIA,
    _E_OFFSET,
    _E_POS,
    _E_RATE,
    _P0,
    _X_ATT,
    _X_INERTIA,
    _X_POS,
    _X_RATE,
    LAYOUT,
    SLOW_PER_RECTANGLE,
    _initial_inertia,
    _propagate,
    filter_layout,
    measurement,
    measurement_second_order,
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
class DepthMemo:
    """What ekf-depth carries from step to step besides the mean and covariance.

    ``gated_run``: epochs in a row whose every fix the NIS gate rejected; ``restarts``: the
    times the run started again; ``clock``: the view clock (rad), how far the view of the
    target has turned since the start (the estimated rate plus the orbit's, integrated);
    ``last_seen``: each model rectangle's view clock at its last fix (-inf: never);
    ``noise_shape``, ``noise_rate``: half the faded sums of the weights and weighted
    samples of the fixes' variance scale per component (:data:`fixes.COMPONENTS`;
    :meth:`DepthSteps._learn_noise`); ``start``: the track's start, ``(k0, x0, P0, memo0)``,
    kept until the start window is replayed (:meth:`DepthSteps._replay`; None: replayed, or
    no replay)."""

    gated_run: int
    restarts: tuple[float, ...]
    clock: float
    last_seen: tuple[float, ...]
    noise_shape: tuple[float, ...]
    noise_rate: tuple[float, ...]
    start: tuple[int, Array, Array, DepthMemo] | None = None


def _variance_scales(shape: Array, rate: Array) -> Array:
    """The fixes' learnt variance scales per component, ``rate / shape`` (at least 1e-3)."""
    return np.maximum(rate / shape, 1e-3)


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
    symmetric frame of the model nearest its last estimate.

    Beyond Yu 2019 (tumblenav), the fixes' errors as measured against the truth (their
    autocorrelation over scans, :func:`fixes.fix_noise`): the slowly varying part of each
    rectangle's fix errors (the ray grid's edge phase, the errors of an oblique view) is a
    state of the filter, six first-order Gauss-Markov states per model rectangle
    (normalised to unit variance, seen in each fix through :meth:`FixNoise.slow_factor`),
    which decorrelate as the view of the target turns, by ``exp(-turn /
    decorrelation_rad)`` between two fixes of that rectangle, the turn counted by a view
    clock (the estimated rate plus the orbit's, integrated); the fixes' common bias along the
    line of sight is a random constant; R is the white part only, its variance per component
    scaled by a factor learnt from the innovations (:meth:`_learn_noise`). The layout is
    :func:`model.filter_layout`; the estimate reports LAYOUT. The belief's ``memo`` is a
    :class:`DepthMemo`."""

    model: Any
    meas: Any
    tun: DepthTuning
    sigma: float
    n_orbit: float
    rng: np.random.Generator
    q_rot: float = 1e-12
    q_trans: float | None = None

    @functools.cached_property
    def symmetries(self) -> list[Array]:
        return model_symmetries(self.model.rectangles)

    @functools.cached_property
    def _rect_index(self) -> dict[str, int]:
        return {r.name: i for i, r in enumerate(self.model.rectangles)}

    @functools.cached_property
    def _rect_centre(self) -> dict[str, Array]:
        return {r.name: np.asarray(r.centre_M, dtype=float) for r in self.model.rectangles}

    @functools.cached_property
    def layout(self) -> StateLayout:
        # without the multi-solution fix (the paper's Fig. 9) the symmetric jumps go through
        # ungated: the fixes' error states would take them in, so there are none
        gated = self.tun.multi_solution_fix
        n = len(self.model.rectangles) if self.tun.fix_error_states and gated else 0
        return filter_layout(n, self.tun.fix_range_bias_spacings > 0 and gated)

    def _start_memo(self, previous: DepthMemo | None = None, t_restart: float = 0.0) -> DepthMemo:
        """The memo of a start; of a restart at ``t_restart`` after ``previous`` (its view
        clock and the learnt noise scales stay: they describe the sensor, not the track)."""
        n = len(self.model.rectangles)
        if previous is None:
            a0 = self.tun.fix_noise_prior_fixes / 2.0
            return DepthMemo(0, (), 0.0, (-np.inf,) * n, (a0,) * 6, (a0,) * 6)
        return DepthMemo(
            0,
            (*previous.restarts, t_restart),
            previous.clock,
            (-np.inf,) * n,
            previous.noise_shape,
            previous.noise_rate,
        )

    @functools.cached_property
    def _max_rate(self) -> float:
        """The fastest rate the scans resolve (rad/s): pi per median scan interval."""
        return float(np.pi / self._scan_interval)

    @functools.cached_property
    def _scan_interval(self) -> float:
        dt = np.diff(np.asarray(self.meas.t, dtype=float))
        dt = dt[dt > 0]
        return float(np.median(dt)) if len(dt) else np.inf

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
            pts,
            self.model,
            thr,
            self.rng,
            self.sigma,
            R_SM_pred,
            p_MinS_predicted=p_pred,
            edge_turn=self.tun.frontend.edge_turn,
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
        lay = self.layout
        x = np.zeros(lay.nominal_dim)
        x[_X_ATT] = rot.matrix_to_quat(R_TI)
        x[_X_INERTIA] = _initial_inertia(self.tun, self.rng)
        x[_X_POS] = R_LS @ p0
        P = np.eye(lay.dim)  # the fixes' slow errors: unit variance, none seen yet
        P[: LAYOUT.dim, : LAYOUT.dim] = _P0(self.tun)
        if "fix_range_bias" in lay.names():
            # the common bias along the line of sight: a random constant, its 1-sigma
            # fix_range_bias_spacings x the start's ray spacing (m)
            h = np.median(
                [np.sqrt(f.sides_m[0] * f.sides_m[1] / max(f.n_points, 3)) for f in fixes]
            )
            e = lay.err("fix_range_bias")
            P[e, e] = (self.tun.fix_range_bias_spacings * h) ** 2
        memo = self._with_start(self._start_memo(), k, x, P)
        return Belief(float(self.meas.t[k]), x, P, lay, memo), StepInfo()

    def _with_start(self, memo: DepthMemo, k: int, x: Array, P: Array) -> DepthMemo:
        """``memo`` keeping the track's start at epoch ``k`` for the start replay."""
        if self.tun.start_replays == 0 or self.tun.start_replay_rad <= 0:
            return memo
        return replace(memo, start=(k, x.copy(), P.copy(), memo))

    def _replay(self, belief: Belief, k1: int) -> Belief:
        """The start window replayed (tumblenav, beyond Yu 2019): an EKF started far from the
        truth (the inertia ratios of a sphere) linearises eq. 28 along its own changing
        estimate and gains spurious information along the weakly observable directions of
        the ratios (in a three-axis tumble the products of inertia froze 2-3 sigma off; cf.
        Huang, Mourikis & Roumeliotis 2010 for EKF-SLAM). At epoch ``k1``, once the view has
        turned ``start_replay_rad`` since the track's start ``k0`` (the view clock), the
        filter runs again over ``k0 .. k1`` from the start's state and covariance P0 with the
        ratios of the last pass at ``k1``: a relinearisation, as an iterated filter
        (``start_replays`` passes). P0 stays: the prior is as loose as before around a better
        point, so the window's data count once more only through the linearisation point
        (the prior's 0.5 against a posterior sigma of 0.01-0.1). The estimates before ``k1``
        stay the first pass's (causal); a pass that loses track (a restart) is dropped. With
        ``start_replay_disagreement`` the replay's covariance takes in the passes' difference
        at ``k1`` (a replay can wander from a good start as the first pass did from the
        sphere: yu_tumble run 17, yu_outliers run 3)."""
        memo: DepthMemo = belief.memo
        assert memo.start is not None
        k0, x0, P0, memo0 = memo.start
        t = self.meas.t
        b = belief
        for _ in range(self.tun.start_replays):
            x = self._relinearised_start(x0, b.x)
            if x is None:
                break
            bb = Belief(float(t[k0]), x, P0.copy(), belief.layout, memo0)
            for k in range(k0 + 1, k1 + 1):
                bb, _ = self.update(self.predict(bb, float(t[k])), k, False)
                if bb.memo.restarts != memo0.restarts:
                    return replace(belief, memo=replace(memo, start=None))
            if self.tun.start_replay_disagreement:
                # the two passes ran over the same data and differ only in their
                # linearisation: their difference measures the linearisation's error,
                # which neither pass's covariance holds (tumblenav): the replay's
                # covariance takes it in, d d^T along it (positive semi-definite added)
                d = belief.layout.boxminus(b.x, bb.x)
                bb = replace(bb, P=bb.P + np.outer(d, d))
            b = bb
        return replace(b, memo=replace(b.memo, start=None))

    def _relinearised_start(self, x0: Array, x1: Array) -> Array | None:
        """The replay's start: ``x0`` (the start's) with the inertia ratios of ``x1`` (the
        last pass at the window's end; constants). None when those are not physical."""
        l = x1[_X_INERTIA]
        if not physical_inertia(l):
            return None
        x = x0.copy()
        x[_X_INERTIA] = l
        return x

    def predict(self, belief: Belief, t: float) -> Belief:
        dt = t - belief.t
        x, P = _propagate(belief.x, belief.P, dt, self.n_orbit, self.q_rot, self.q_trans)
        # the view clock: how far the view of the target has turned (the estimated rate and
        # the orbit's turn of L; tumblenav), the time base of the fixes' slow errors
        m = belief.memo
        turn = (float(np.linalg.norm(belief.x[_X_RATE])) + self.n_orbit) * abs(dt)
        return Belief(t, x, P, belief.layout, replace(m, clock=m.clock + turn))

    def _decay(self, x: Array, P: Array, j: int, turn: float, psi_c: float) -> None:
        """Rectangle ``j``'s slow-error pair over a view turn ``turn`` (rad), in place: the
        first-order Gauss-Markov step ``s' = a s + sqrt(1 - a^2) w``, ``a = exp(-turn /
        psi_c)`` (tumblenav)."""
        a = float(np.exp(-max(turn, 0.0) / max(psi_c, 1e-12)))
        lay = self.layout
        e0, x0 = lay.err("fix_errors").start, lay.nom("fix_errors").start
        e = slice(e0 + SLOW_PER_RECTANGLE * j, e0 + SLOW_PER_RECTANGLE * (j + 1))
        xs = slice(x0 + SLOW_PER_RECTANGLE * j, x0 + SLOW_PER_RECTANGLE * (j + 1))
        x[xs] *= a
        P[e, :] *= a
        P[:, e] *= a
        P[e, e] += (1.0 - a * a) * np.eye(SLOW_PER_RECTANGLE)

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        """Each fix of epoch ``k`` (Yu 2019 eq. 34-41), gated by its NIS; the start epoch's
        fixes made the start."""
        if started:
            return belief, StepInfo()
        tun = self.tun
        lay = belief.layout
        x, P = belief.x.copy(), belief.P.copy()
        memo: DepthMemo = belief.memo
        last = list(memo.last_seen)
        shape, rate = np.array(memo.noise_shape), np.array(memo.noise_rate)
        fixes = self._fixes(k, x)
        skipped = {
            "no_rectangle": 0 if fixes else 1,
            "gated_out": 0,
            "nonphysical_inertia": 0,
            "nonphysical_rate": 0,
        }
        R_CL, R_LI = self._frames
        R_LS = R_CL[k].T
        thr = plane_threshold(tun, self.sigma)
        names = lay.names()
        slow_states = "fix_errors" in names
        nis, dof, far = 0.0, 0, 0.0
        # the scales are learnt, and the offset along a fixed spin axis constrained, behind
        # the NIS gate only: without it (no multi-solution fix, the paper's Fig. 9) the
        # symmetric jumps would be learnt as noise and would turn the spin axis
        gated = tun.multi_solution_fix
        learn = tun.fix_noise_adaptive and gated
        for fx in fixes:
            q_meas = rot.matrix_to_quat((R_LI[k].T @ R_LS @ fx.R_SM).T)  # R_TI = R_MS R_SL R_LI
            p_ML = R_LS @ fx.p_MinS
            centre_M = self._rect_centre.get(fx.rectangle)
            noise = fix_noise(
                fx,
                self.sigma,
                thr,
                tun.fix_error_slow_fractions if slow_states else (0.0,) * 6,
                tun.fix_error_decorrelation_spacings,
                centre_M,
                fx.p_MinS + fx.R_SM @ (centre_M if centre_M is not None else np.zeros(3)),
                tun.attitude_noise_scale,
                tun.position_noise_scale,
                tun.fix_error_oblique_spacings if slow_states else 0.0,
                tun.fix_error_oblique_normal if slow_states else 0.0,
                tun.edge_turn_floor,
            )
            scales = None
            if learn:
                learnt = np.asarray(tun.fix_noise_learnt, dtype=bool)
                scales = np.where(learnt, _variance_scales(shape, rate), 1.0)
            R_LP = R_LS @ fx.R_SM @ fx.R_MP if fx.R_MP is not None else np.eye(3)
            R_TP = fx.R_MP if fx.R_MP is not None else np.eye(3)
            y, Hp = measurement(x, R_LI[k])
            H = np.zeros((6, lay.dim))
            H[:3, _E_ATT] = np.eye(3)
            H[3:, : LAYOUT.dim] = Hp
            T = np.zeros((6, 6))
            T[:3, :3], T[3:, 3:] = R_TP, R_LP
            if slow_states:
                # this rectangle's slow in-plane error (tumblenav): decayed over the view's
                # turn since its last fix, then seen through this fix's in-plane axes
                j = self._rect_index[fx.rectangle]
                self._decay(x, P, j, memo.clock - last[j], noise.decorrelation_rad)
                last[j] = memo.clock
                e = lay.err("fix_errors").start + SLOW_PER_RECTANGLE * j
                H[:, e : e + SLOW_PER_RECTANGLE] = T @ noise.slow_factor(scales)
            if "fix_range_bias" in names:
                # the fixes' common bias along the line of sight (tumblenav): the centroid
                # of a face sits a fraction of the ray spacing nearer the sensor than its
                # centre, averaged over the views (m; its prior from the start's fixes)
                los = R_LS @ (fx.p_MinS / np.linalg.norm(fx.p_MinS))
                H[3:, lay.err("fix_range_bias")] = los[:, None]
            # the measurement's mean includes the fixes' error states' (zero unless estimated)
            extra = H[:, LAYOUT.dim :] @ x[LAYOUT.nominal_dim :]
            nu = np.r_[rot.boxminus(q_meas, x[_X_ATT]), p_ML - y] - extra
            R = T @ noise.cov(scales) @ T.T
            if tun.second_order_fixes:
                # the origin's terms of second order in (attitude, offset): their mean and
                # covariance (Gaussian second-order filter; beyond Yu 2019)
                m2, C2 = measurement_second_order(x, P, R_LI[k])
                R[3:, 3:] += C2
                nu[3:] -= m2
            S = H @ P @ H.T + R
            d2 = nu @ np.linalg.solve(S, nu)
            if tun.multi_solution_fix and d2 > chi2.ppf(tun.gate_probability, 6):
                # NIS gate (rejections counted); off without the fix, to show its jumps
                skipped["gated_out"] += 1
                far = max(far, float(np.linalg.norm(nu[:3])))
                continue
            HPH_prior = T.T @ H @ P @ H.T @ T
            K = np.linalg.solve(S, H @ P).T
            unexcited = unexcited_ratios(x[_X_RATE], x[_X_INERTIA], P[_E_RATE, _E_RATE])
            if tun.consider_unexcited_ratios:
                # Schmidt (consider) update for the ratios the motion does not excite: no
                # gain, so no information from nothing; their covariance and its coupling to
                # the rate stay, and the Joseph form below is exact for any gain
                K[_E_INERTIA][unexcited] = 0.0
            wl = slice(_E_RATE.start, _E_INERTIA.stop)
            if (
                gated
                and tun.consider_spin_axis_offset
                and spin_axis_fixed(x[_X_RATE], x[_X_INERTIA], unexcited, P[wl, wl])
            ):
                # a spin whose axis u stays put in T (and in L): moving the offset along u
                # and r with it, (dr, db) = (R_LT u, u), changes no fix; only the Hill
                # model's curvature of r over the run (2% at 200 s in LEO) tells them
                # apart, and the linearisation at a noisy attitude and rate (the estimated
                # axis wobbles by mrad) claims far more. The update gets no component along
                # that direction (an observability-constrained gain, cf. Huang, Mourikis &
                # Roumeliotis 2010 for EKF-SLAM; tumblenav): it keeps its prior there
                u = x[_X_RATE] / np.linalg.norm(x[_X_RATE])
                nul = np.zeros(lay.dim)
                nul[_E_POS] = R_LI[k] @ rot.quat_to_matrix(x[_X_ATT]).T @ u
                nul[_E_OFFSET] = u
                K = K - np.outer(nul, nul @ K) / (nul @ nul)
            x_new = lay.boxplus(x, K @ nu)
            if not physical_inertia(x_new[_X_INERTIA]) and physical_inertia(x[_X_INERTIA]):
                # a step that makes the inertia not positive definite would let the Euler
                # equations explode: keep the ratios where they were, take the rest, and
                # count it; the ratios get no gain from this fix, so the covariance says
                # what was done (a Schmidt update of them; tumblenav: the covariance used
                # to take the refused step, and the ratios grew over-confident in a tumble)
                K[_E_INERTIA] = 0.0
                x_new = lay.boxplus(x, K @ nu)
                skipped["nonphysical_inertia"] += 1
            if np.linalg.norm(x_new[_X_RATE]) > self._max_rate:
                # a rate beyond pi per scan interval cannot be told from a slower one (the
                # scans alias it): such a step (a jump between symmetric cases) keeps the
                # previous rate, and is counted (tumblenav default); no gain on it either
                K[_E_RATE] = 0.0
                x_new = lay.boxplus(x, K @ nu)
                skipped["nonphysical_rate"] += 1
            A = np.eye(lay.dim) - K @ H
            P = A @ P @ A.T + K @ R @ K.T  # Joseph form: exact for the gain taken
            if learn:
                shape, rate = self._learn_noise(
                    shape, rate, T.T @ nu, HPH_prior, T.T @ S @ T, noise
                )
            x = x_new
            nis += d2
            dof += 6
        # lost track: epochs in a row whose every fix is gated out, one of them at least
        # start_agreement_deg off in attitude (a wrong rectangle or branch followed; a
        # stretch of grazing views, gated for their centres, is not: tumblenav)
        off = far > np.radians(tun.start_agreement_deg)
        gated_run = memo.gated_run
        gated_run = gated_run + 1 if fixes and dof == 0 and off else 0 if dof else gated_run
        memo = replace(
            memo,
            gated_run=gated_run,
            last_seen=tuple(last),
            noise_shape=tuple(shape),
            noise_rate=tuple(rate),
        )
        if tun.multi_solution_fix and gated_run >= tun.reinit_after_gated:
            # lost track: every fix of the last epochs disagreed with the prediction
            fresh, why = self.initialise(k, previous=x)
            if fresh is not None:
                skipped["reinitialised"] = 1
                memo = self._start_memo(memo, float(self.meas.t[k]))
                memo = self._with_start(memo, k, fresh.x, fresh.P)
                return Belief(belief.t, fresh.x, fresh.P, lay, memo), StepInfo(skipped=skipped)
        info = StepInfo(nis=nis if dof else float("nan"), dof=dof, skipped=skipped)
        out = Belief(belief.t, x, P, lay, memo)
        if memo.start is not None and memo.clock - memo.start[3].clock >= tun.start_replay_rad:
            out = self._replay(out, k)
        return out, info

    def _learn_noise(
        self, shape: Array, rate: Array, nu_P: Array, HPH_P: Array, S_P: Array, noise
    ) -> tuple[Array, Array]:
        """One fix's evidence on the variance scales of the fix model's white part, per
        component (:data:`fixes.COMPONENTS`; tumblenav, beyond Yu 2019). The ray grid's
        errors are 0.04-1x the model's ``h^2 / 12`` in the plane and 0.2-1.2x the first-order
        variances otherwise, as the grid happens to lie on the faces (measured on the five yu
        scenarios of issue 18): no fixed model fits them all, so each scale is learnt from
        the innovations (covariance matching, Mehra 1972, IEEE TAC 17(5)): ``nu^2 - (H P
        H^T)`` estimates ``s r`` (``nu_P``, ``HPH_P``, ``S_P``: the innovation, ``H P- H^T``
        and ``S`` in P; ``r``: the white variance at scale 1), with a variance ``~ 2 S^2``,
        so each sample is weighted by ``(s r / S)^2``, the share of ``S`` that is the fix's
        own noise. The weights and weighted samples are summed with a fading memory of
        ``fix_noise_memory_fixes`` fixes (``shape``, ``rate``: their sums, half each; the
        scale is ``rate / shape``; a start worth ``fix_noise_prior_fixes`` at scale 1)."""
        base = np.maximum(np.diag(noise.cov()), 1e-300)
        lam = 1.0 - 1.0 / self.tun.fix_noise_memory_fixes
        s_prev = _variance_scales(shape, rate)
        w = (s_prev * base / np.maximum(np.diag(S_P), 1e-300)) ** 2
        sample = (nu_P**2 - np.diag(HPH_P)) / base
        return lam * shape + 0.5 * w, lam * rate + 0.5 * w * sample

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P
