"""Hu 2024's filter run: the front end, the filter's view of it, the steps on a frozen belief
(:class:`HuSteps`, folded per run: the reference engine) and :func:`run_filter` (that fold, or
the compiled kernel, :mod:`.kernels`), and the histories it returns."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import discretise
from tumblenav.errors import InputError
from tumblenav.estimators.base import (
    Belief,
    EstimateHistory,
    StateLayout,
    StepInfo,
    fold,
)
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.hu2024.frame import (
    _follow_dpacf_branch,
    _reframe,
    frame_consider_cov,
    frame_error_transition,
)
from tumblenav.estimators.hu2024.init import _initial_state
from tumblenav.estimators.hu2024.model import (
    _FLIPS,
    CONSTRAIN_EVERY,
    MAX_RATE_RAD_S,
    MAX_REINITS,
    _diverged,
    _neutral_state,
    _translation_discrete,
    constrain_inertia,
    core_F,
    core_Qc,
    frame_error_Qc,
    frame_error_rate_jacobian,
    layout,
    propagate_rotation,
    recentre_unseen,
)
from tumblenav.estimators.hu2024.tuning import HuTuning, parse_tuning
from tumblenav.estimators.hu2024.update import _update, _update_sequential
from tumblenav.frontends import stereo_points
from tumblenav.frontends.inertia import branch_statistics

Array = NDArray[np.float64]


def run_filter(
    scenario: Any,
    meas_list: list,
    use_dpacf: bool,
    p_every: int = 1,
    engine: Literal["auto", "numpy", "compiled"] | None = None,
) -> dict[str, Any]:
    """Run the EKF on B runs at once. Returns the histories ``x`` (B, n, nom) and ``P``
    (B, ceil(n / p_every), d, d), the covariance of every ``p_every``-th epoch (campaigns need
    it only for the NEES, at about 1 Hz), the NIS and what each run skipped. It never
    sees the truth: errors are the evaluation's (:mod:`tumblenav.evaluation`).

    ``engine``: the compiled per-run loop (:mod:`tumblenav.estimators.hu2024.kernels`) or the
    batched numpy loop below; both give the same result (tests). ``auto`` takes the compiled
    one wherever it covers the tuning (eq. 31 attitude measurement, no innovation gate).
    ``None``: the module's ``ENGINE`` (benchmarks set it to time the numpy loop)."""
    scenario = context_from_scenario(scenario)  # never the target's truth
    engine = engine or ENGINE
    tun = parse_tuning(scenario.estimator.tuning, use_dpacf)
    consider = use_dpacf and tun.dpacf_frame_error == "consider"
    # the frame error as a consider (Schmidt) parameter: 3 more rows and columns of P (the
    # gated batch update works on the state's own: there the white model stands in)
    schmidt = (
        consider
        and tun.frame_error_dynamics_s > 0
        and tun.frame_error_model == "state"
        and tun.gate_probability is None
    )
    refine = tun.refine_start
    # iterated update: prior attitude variance (trace) above this (0: never)
    iter_var = 3.0 * tun.iterate_sigma_rad**2
    s_t2 = (
        tun.sigma_t2_m2_s4
        if tun.sigma_t2_m2_s4 is not None
        else scenario.process_noise.translational_m2_s4
    )
    s_r2 = (
        tun.sigma_r2_rad2_s4
        if tun.sigma_r2_rad2_s4 is not None
        else scenario.process_noise.rotational_rad2_s4
    )
    n_orbit = scenario.chaser.orbit.mean_motion_rad_s if scenario.chaser.orbit else 0.0
    covered = tun.dpacf_measurement == "attitude" and tun.gate_probability is None
    if engine == "compiled" and not covered:
        raise ValueError("the compiled engine covers dpacf_measurement 'attitude' without a gate")
    fe_all = frontend(meas_list, tun, s_r2, disturbed=scenario.process_noise.disturb_truth)
    fe = filter_view(fe_all, tun.max_dpacf_sigma_rad)
    B, n, N = fe.usable.shape
    lay = layout(N)
    init = _initial_state(fe, tun, use_dpacf, lay, n_orbit, frame_in_P0=not consider,
                          refine=refine, q_t=s_t2)  # fmt: skip
    p_turn = np.zeros((B, n, 3))
    mu_turn = np.zeros((B, n, 3, 3))
    S_turn = np.zeros((B, n, 3, 3, 3))
    if consider and tun.branch_mixture:
        # the front end re-solves its frame every ls_every epochs and holds it in between
        every = stereo_points.FrontEndSettings().ls_every
        stat = branch_statistics(fe.R_GT[:, ::every], fe.cov_frame[:, ::every])
        p_turn, mu_turn, S_turn = (np.repeat(a, every, axis=1)[:, :n] for a in stat)
    d = lay.dim
    gate = stats.chi2.ppf(tun.gate_probability, 3) if tun.gate_probability else np.inf
    if np.isfinite(gate) and tun.dpacf_measurement == "frame":
        raise InputError(
            "estimator.tuning: gate_probability works with dpacf_measurement 'attitude' only"
        )
    dt_nom = float(np.median(np.diff(fe.t)))
    att_inflation = max(1.0, tun.attitude_corr_time_s / (dt_nom * tun.attitude_meas_every))
    if consider:  # the attitude measurement's noise: its white (G attitude) part only
        att_inflation = 0.0
    t = fe.t
    out_x = np.full((B, n, lay.nominal_dim), np.nan)
    out_P = np.full((B, -(-n // p_every), d, d), np.nan)  # epochs 0, p_every, 2 p_every, ...
    nis = np.full((B, n), np.nan)
    nis_dof = np.zeros((B, n))
    rejected = np.zeros(B, dtype=np.int64)
    diverged = np.zeros(B, dtype=bool)
    flips = np.zeros(B, dtype=np.int64)

    def pack() -> dict[str, Any]:
        return {
            "t": t,
            "x": out_x,
            "P": out_P,
            "nis": nis,
            "nis_dof": nis_dof,
            "layout": lay,
            "frontend": fe,
            "k0": init.k0,
            "rejected": rejected,
            "diverged": diverged,
            "frame_flips": flips,
            "dpacf_q_TI": fe_all.q_TI,
        }

    uniform = bool(np.allclose(np.diff(t), dt_nom, rtol=1e-9, atol=0))
    compiled_ok = covered and uniform
    if engine == "compiled" and not uniform:
        raise ValueError("the compiled engine needs a uniform time grid")
    use_kernel = engine != "numpy" and compiled_ok

    def run_engine(idx: NDArray[np.intp], k0: NDArray[np.int64], x0: Array, P0: Array) -> dict:
        """Runs ``idx`` from the starts ``k0``, ``x0``, ``P0`` (one per run of ``idx``)."""
        m = len(idx)
        r: dict[str, Any] = {
            "x": np.full((m, n, lay.nominal_dim), np.nan),
            "P": np.full((m, -(-n // p_every), d, d), np.nan),
            "nis": np.full((m, n), np.nan),
            "nis_dof": np.zeros((m, n)),
            "rejected": np.zeros(m, dtype=np.int64),
            "diverged": np.zeros(m, dtype=np.bool_),
            "flips": np.zeros(m, dtype=np.int64),
        }
        assert fe.R_LI is not None  # set by frontend()

        def sel(a: Any) -> Any:  # no copy of the largest arrays for the whole batch
            return a if m == B else a[idx]

        if use_kernel:
            from tumblenav.estimators.hu2024 import kernels as _hu_kernel

            R0 = np.nan_to_num(sel(fe.cov_TI) + (att_inflation - 1.0) * sel(fe.cov_frame))
            Pht, Qt = _translation_discrete(n_orbit, s_t2, dt_nom)  # uniform grid: one dt
            _hu_kernel.run_filter_kernel(
                t, sel(fe.p_L), np.ascontiguousarray(sel(fe.cov_L)), sel(fe.usable),
                sel(fe.known_at), sel(fe.q_TI), R0, sel(fe.R_LI), k0, x0, P0, use_dpacf,
                bool(tun.first_estimates_jacobian), tun.attitude_meas_every, tun.flip_epochs,
                CONSTRAIN_EVERY, tun.constraint_curvature,
                tun.constraint_update == "projection", MAX_RATE_RAD_S,
                s_r2, Pht, Qt, tun.sigma_f2_m2_s * dt_nom,
                _FLIPS, rot.matrix_to_quat(_FLIPS), p_every, _neutral_state(lay), r["x"],
                r["P"], r["nis"], r["nis_dof"], r["diverged"], r["flips"], consider,
                sel(fe.R_GT), np.nan_to_num(sel(fe.cov_frame)), sel(p_turn), sel(mu_turn),
                sel(S_turn), refine, bool(tun.attitude_update), iter_var, tun.iterate_max,
                float(tun.frame_error_dynamics_s), schmidt,
            )  # fmt: skip
            return r
        # the reference engine: each run folded through Hu's steps (base.fold)
        for j, b in enumerate(idx):
            steps = HuSteps(
                fe=_run_view(fe, b),
                tun=tun,
                use_dpacf=use_dpacf,
                layout=lay,
                k0=int(k0[j]),
                x0=x0[j],
                P0=P0[j],
                n_orbit=n_orbit,
                s_r2=s_r2,
                s_t2=s_t2,
                consider=consider,
                refine=refine,
                iter_var=iter_var,
                gate=float(gate),
                att_inflation=att_inflation,
                p_turn=p_turn[b : b + 1],
                mu_turn=mu_turn[b : b + 1],
                S_turn=S_turn[b : b + 1],
                schmidt=schmidt,
            )
            f = fold(steps, t, p_every)
            r["x"][j], r["P"][j], r["nis"][j], r["nis_dof"][j] = f.x, f.P, f.nis, f.nis_dof
            r["rejected"][j], r["diverged"][j] = f.rejected, f.diverged
            r["flips"][j] = f.memo.flips if f.memo is not None else 0
        return r

    allr = np.arange(B)
    r = run_engine(allr, init.k0, init.x0, init.P0)
    out_x[:], out_P[:], nis[:], nis_dof[:] = r["x"], r["P"], r["nis"], r["nis_dof"]
    rejected[:], diverged[:], flips[:] = r["rejected"], r["diverged"], r["flips"]
    # A run that lost track (its state left every physical range: _diverged; or, for
    # ekf-dpacf with restart_on_alarm, its lost-track alarm fired since its last start:
    # nis_alarm) is started again from the measurements after that epoch, as at the start
    # (tumblenav default; ekf-baseline after a long occlusion), at most MAX_REINITS times;
    # counted in ``reinitialised`` and the epochs of each restart in ``reinit_epochs``
    reinit_at: list[list[int]] = [[] for _ in range(B)]
    started = init.k0.copy()  # each run's last start (-1: none)
    # runs whose alarm has not been tested since their last start (a run whose alarm fired
    # and that found no new start keeps what it had and is not tested again)
    check = started >= 0
    for _ in range(MAX_REINITS):
        k_lost = np.full(B, -1)  # the epoch after which each lost run starts again
        for b in np.flatnonzero(diverged):
            fin = np.isfinite(out_x[b, :, 0])
            k_lost[b] = n - int(np.argmax(fin[::-1])) if fin.any() else 0
        if use_dpacf and tun.restart_on_alarm:
            for b in np.flatnonzero(check & ~diverged):
                since = np.arange(n) >= started[b]  # the windows after the last start only
                alarm = nis_alarm(
                    fe.t, np.where(since, nis[b], 0.0), np.where(since, nis_dof[b], 0)
                )
                if alarm.any():
                    k_lost[b] = int(np.argmax(alarm)) + 1
        check[:] = False
        lost = np.flatnonzero(k_lost >= 0)
        if not len(lost):
            break
        k_div = k_lost[lost]
        sub = _subset(fe, lost)
        re = _initial_state(sub, tun, use_dpacf, lay, n_orbit, frame_in_P0=not consider,
                            refine=refine, not_before=k_div, q_t=s_t2)  # fmt: skip
        go = re.k0 >= 0
        if not go.any():
            break
        idx, k0r = lost[go], re.k0[go]
        r = run_engine(idx, k0r, re.x0[go], re.P0[go])
        for j, b in enumerate(idx):
            k, kp = int(k0r[j]), -(-int(k0r[j]) // p_every)
            out_x[b, k:], nis[b, k:], nis_dof[b, k:] = (
                r["x"][j, k:],
                r["nis"][j, k:],
                r["nis_dof"][j, k:],
            )
            out_P[b, kp:] = r["P"][j, kp:]
            rejected[b] += r["rejected"][j]
            flips[b] += r["flips"][j]
            diverged[b] = r["diverged"][j]
            reinit_at[b].append(k)
            started[b] = k
            check[b] = True
    out = pack()
    out["reinit_epochs"] = reinit_at
    return out


def _subset(
    fe: stereo_points.PointsFrontEnd, idx: NDArray[np.intp]
) -> stereo_points.PointsFrontEnd:
    """The runs ``idx`` of a batched front end (the arrays keep their run axis)."""
    B = fe.usable.shape[0]
    upd: dict[str, Any] = {}
    for f in dataclasses.fields(fe):
        v = getattr(fe, f.name)
        if f.name != "t" and isinstance(v, np.ndarray) and v.ndim and v.shape[0] == B:
            upd[f.name] = v[idx]
    upd["skipped"] = {k: np.asarray(v)[idx] for k, v in fe.skipped.items()}
    if fe.template_history is not None:
        upd["template_history"] = [(k_v[idx], tm[idx]) for k_v, tm in fe.template_history]
    return dataclasses.replace(fe, **upd)


def _run_view(fe: stereo_points.PointsFrontEnd, b: int) -> stereo_points.PointsFrontEnd:
    """Run ``b`` of a batched front end, as a batch of one (the arrays keep their run axis)."""
    return _subset(fe, np.array([b]))


@dataclass(frozen=True)
class HuMemo:
    """What Hu's filter carries from epoch to epoch besides x and P (one run): the
    consecutive DPACF measurements a half turn away and the half turns followed
    (:func:`_follow_dpacf_branch`), the features' first estimates (FEJ linearisation points,
    (N, 3), NaN before), and with the 'consider' frame model the front end's frame the state
    is in and the epoch it is from."""

    votes: int
    flips: int
    f_first: Array
    R_used: Array
    k_used: int


@dataclass(frozen=True)
class HuSteps:
    """Hu 2024's EKF (eq. 36-44) as stateless steps on one run's front-end output, folded by
    :func:`tumblenav.estimators.base.fold`: the reference engine of :func:`run_filter`. The
    compiled kernel (:mod:`.kernels`) is the fast fold of the same steps (tested equal on
    runs drawn at random). The arrays are those of a batch of one (leading axis 1), so that
    the batched model pieces of this module serve both."""

    fe: stereo_points.PointsFrontEnd
    tun: HuTuning
    use_dpacf: bool
    layout: StateLayout
    k0: int
    x0: Array
    P0: Array
    n_orbit: float
    s_r2: float
    s_t2: float
    consider: bool
    refine: bool
    iter_var: float
    gate: float
    att_inflation: float
    p_turn: Array
    mu_turn: Array
    S_turn: Array
    schmidt: bool = False

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        """The start prepared by :func:`_initial_state`, at its epoch ``k0``. With the frame
        error as a consider parameter (``schmidt``) P has three more rows and columns, u's:
        uncorrelated with the start's error (which is in the front end's frame), covariance
        the frame's."""
        if k != self.k0:
            return None, StepInfo()
        N = self.fe.usable.shape[2]
        memo = HuMemo(0, 0, np.full((N, 3), np.nan), self.fe.R_GT[0, k].copy(), k)
        t = float(self.fe.t[k])
        P = self.P0.copy()
        if self.schmidt:
            d = self.layout.dim
            P = np.zeros((d + 3, d + 3))
            P[:d, :d] = self.P0
            P[d:, d:] = np.nan_to_num(self.fe.cov_frame[0, k])
        return Belief(t, self.x0.copy(), P, self.layout, memo), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        """Hu 2024 eq. 36-39: F is block diagonal, rotation (9, state dependent) and
        translation (6, constant)."""
        lay, tun = self.layout, self.tun
        sq, sw, sp = lay.nom("attitude"), lay.nom("rate"), lay.nom("inertia")
        srv = slice(lay.nom("position").start, lay.nom("velocity").stop)
        dt = t - belief.t
        x, P = belief.x[None].copy(), belief.P[None].copy()
        F = core_F(x[:, sw], x[:, sp], self.n_orbit, rotation_only=True)
        Qc = core_Qc(x[:, sp], self.s_r2, self.s_t2)[:, :9, :9]
        d = lay.dim
        rot_rows = np.arange(9)
        if self.schmidt:  # the frame error u: d(omega)/dt gains G u, u constant
            Fa = np.zeros((1, 12, 12))
            Fa[:, :9, :9] = F
            # -G: u here is frame_jacobian's (T coordinates = exp([u x]) times T''s), the
            # inverse rotation of frame_error_rate_jacobian's
            Fa[:, 3:6, 9:12] = -frame_error_rate_jacobian(x[:, sw], x[:, sp])
            Qa = np.zeros((1, 12, 12))
            Qa[:, :9, :9] = Qc
            F, Qc = Fa, Qa
            rot_rows = np.concatenate([rot_rows, d + np.arange(3)])
        elif self.consider and tun.frame_error_dynamics_s > 0:  # white: the frame error's share
            C = self.fe.cov_frame[:, belief.memo.k_used]
            Qc[:, 3:6, 3:6] += frame_error_Qc(x[:, sw], x[:, sp], C, tun.frame_error_dynamics_s)
        Phr, Qr = discretise(F, Qc, dt)
        Pht, Qt = _translation_discrete(self.n_orbit, self.s_t2, dt)
        q_new, w_new = propagate_rotation(x[:, sq], x[:, sw], x[:, sp], dt)
        x[:, sq], x[:, sw] = q_new, w_new
        x[:, srv] = x[:, srv] @ Pht.T
        rr = np.ix_(rot_rows, rot_rows)
        P[:, rot_rows, :] = Phr @ P[:, rot_rows, :]
        P[:, 9:15, :] = Pht @ P[:, 9:15, :]
        P[:, :, rot_rows] = P[:, :, rot_rows] @ np.swapaxes(Phr, -1, -2)
        P[:, :, 9:15] = P[:, :, 9:15] @ Pht.T
        P[(slice(None),) + rr] += Qr
        P[:, 9:15, 9:15] += Qt
        if tun.sigma_f2_m2_s > 0:
            sf = lay.err("features")
            P[:, sf, sf] += tun.sigma_f2_m2_s * dt * np.eye(sf.stop - sf.start)
        return dataclasses.replace(belief, t=t, x=x[0], P=P[0])

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        """Epoch ``k``'s measurements: the frame change ('consider'), the DPACF branch, the
        feature (eq. 32-35) and attitude (eq. 31) updates, iterated where the prior attitude
        is poorly known, the inertia constraint; a blown-up state is reported diverged."""
        lay, tun, fe = self.layout, self.tun, self.fe
        m = belief.memo
        x, P = belief.x[None].copy(), belief.P[None].copy()
        f_first, R_used = m.f_first[None].copy(), m.R_used[None].copy()
        k_used = np.array([m.k_used])
        votes, flips = np.array([m.votes]), np.array([m.flips])
        active, start = np.array([True]), np.array([started])
        if self.consider:
            R_prev, C_prev = R_used.copy(), fe.cov_frame[:, m.k_used]
            ok = _reframe(x, P, fe.R_GT[:, k], R_used, active, lay, f_first)
            k_used[ok] = k
            if self.schmidt and ok[0] and np.any(R_used != R_prev):
                # re-solved: u's coordinates turned with the state (_turn_state), then the
                # new frame's error follows the old one's (frame_error_transition)
                F = np.swapaxes(R_used, -1, -2) @ R_prev
                A = frame_error_transition(F @ C_prev @ np.swapaxes(F, -1, -2), fe.cov_frame[:, k])
                d = lay.dim
                P[:, :, d:] = P[:, :, d:] @ np.swapaxes(A, -1, -2)
                P[:, d:, :] = A @ P[:, d:, :]
        if tun.dpacf_measurement == "frame":
            use_att = "frame" if self.use_dpacf and k % tun.frame_meas_every == 0 else False
        else:
            use_att = self.use_dpacf and tun.attitude_update and (k % tun.attitude_meas_every == 0)
        # a refined start has used its epoch's measurements already (refine_start_pose)
        upd = active & ~start if self.refine else active
        if self.use_dpacf and k % tun.attitude_meas_every == 0:
            x, P, votes = _follow_dpacf_branch(
                x, P, fe.q_TI[:, k], upd, lay, votes, tun.flip_epochs, flips, f_first
            )
        # features first seen now (not at the start): their prior mean to the sighting
        N = f_first.shape[1]
        at_start = start[:, None] & fe.known_at[:, k]
        late = active[:, None] & fe.usable[:, k] & ~np.isfinite(f_first[..., 0]) & ~at_start
        if late.any():
            assert fe.R_LI is not None
            x = recentre_unseen(x, fe.R_LI[:, k], np.nan_to_num(fe.p_L[:, k]), late, lay)
        # the features' first estimates (FEJ linearisation points; kept in every mode,
        # they also mark the features seen so far)
        fnow = x[:, lay.nom("features")].reshape(1, N, 3)
        fresh = at_start | (active[:, None] & fe.usable[:, k] & ~np.isfinite(f_first[..., 0]))
        f_first = np.where(fresh[..., None], fnow, f_first)
        if np.isfinite(self.gate):
            x, P, nis_k, dof_k, rej = _update(
                x, P, fe, k, lay, use_att, self.gate, self.att_inflation, upd
            )
        else:
            f_l = f_first if tun.first_estimates_jacobian else None
            x_pr, P_pr = x, P
            x, P, nis_k, dof_k, rej = _update_sequential(
                x_pr, P_pr, fe, k, lay, use_att, self.att_inflation, upd, f_lin=f_l
            )
            # iterated update where the prior attitude is poorly known (after a gap)
            its = upd & (
                np.trace(P_pr[:, lay.err("attitude"), lay.err("attitude")], axis1=-2, axis2=-1)
                > self.iter_var
            )
            if self.iter_var > 0 and its.any():
                for _ in range(tun.iterate_max):
                    x2, P2, nis2, _dof2, _r = _update_sequential(
                        x_pr, P_pr, fe, k, lay, use_att, self.att_inflation, upd, f_lin=f_l,
                        x_lin=x,
                    )  # fmt: skip
                    x = np.where(its[:, None], x2, x)
                    P = np.where(its[:, None, None], P2, P)
                    nis_k = np.where(its, nis2, nis_k)
        if started or k % CONSTRAIN_EVERY == 0:
            x, P = constrain_inertia(
                x, P, lay, active, curvature=tun.constraint_curvature,
                project=tun.constraint_update == "projection",
            )  # fmt: skip
        if self.schmidt:  # u is considered, never updated: its covariance is the frame's
            d = lay.dim
            P[:, d:, d:] = np.nan_to_num(fe.cov_frame[:, k_used])
        memo = HuMemo(int(votes[0]), int(flips[0]), f_first[0], R_used[0], int(k_used[0]))
        out = dataclasses.replace(belief, x=x[0], P=P[0], memo=memo)
        if _diverged(x, P, lay)[0]:
            return out, StepInfo(diverged=True)
        return out, StepInfo(float(nis_k[0]), int(dof_k[0]), int(rej[0]))

    def report(self, belief: Belief, k: int) -> Array:
        """The covariance reported: with the 'consider' frame model it also holds the
        frame's own error and half turns (:func:`frame_consider_cov`)."""
        if not self.consider:
            return belief.P
        ku = (np.array([0]), np.array([belief.memo.k_used]))
        d = self.layout.dim
        P_xu = belief.P[None, :d, d:] if self.schmidt else None
        return frame_consider_cov(
            belief.x[None], belief.P[None, :d, :d], self.fe.cov_frame[ku], self.layout,
            self.p_turn[ku], self.mu_turn[ku], self.S_turn[ku], P_xu=P_xu,
        )[0]  # fmt: skip


def filter_view(
    fe: stereo_points.PointsFrontEnd, max_sigma_rad: float
) -> stereo_points.PointsFrontEnd:
    """The front end as the filter uses it: DPACF frames (attitude measurement, frame, moments)
    only where the frame's 1-sigma (largest axis) is below ``max_sigma_rad``. The front end
    itself reports them from ``dpacf_emit_sigma_rad`` on (Hu 2024 Fig. 5)."""
    # frames are re-solved every ls_every epochs and held in between: test the solved ones
    every = stereo_points.FrontEndSettings().ls_every
    n = fe.cov_frame.shape[1]
    C = np.nan_to_num(fe.cov_frame[:, ::every], nan=1e6)
    sig = np.sqrt(np.linalg.eigvalsh(C)[..., -1])
    if fe.frame_gate is not None:  # the residuals' excess over the model (front end)
        sig = sig * np.nan_to_num(fe.frame_gate[:, ::every], nan=1.0)
    sig = np.repeat(sig, every, axis=1)[:, :n]
    keep = sig < max_sigma_rad
    view = dataclasses.replace(
        fe,
        q_TI=np.where(keep[..., None], fe.q_TI, np.nan),
        cov_TI=np.where(keep[..., None, None], fe.cov_TI, np.nan),
        cov_frame=np.where(keep[..., None, None], fe.cov_frame, np.nan),
        cov_ratios=np.where(keep[..., None, None], fe.cov_ratios, np.nan),
        R_GT=np.where(keep[..., None, None], fe.R_GT, np.nan),
        moments=np.where(keep[..., None], fe.moments, np.nan),
    )  # R_LI kept
    return view


def frontend(
    meas_list, tun: HuTuning, q_r: float = 0.0, disturbed: bool = False
) -> stereo_points.PointsFrontEnd:
    """The stereo-points front end on B runs, with the settings ``tun.frontend`` and the
    disturbance torque the filter assumes (``q_r``, rad^2/s^3, its sigma_r^2: the inertia
    least squares' momentum random-walks with it), unless ``tun.frontend.ls_torque_rad2_s4``
    says otherwise; with its default 'auto' only where the scenario states that the
    disturbance is real (``disturbed``: process_noise.disturb_truth), else torque-free (Hu
    2024 eq. 10)."""
    fe = tun.frontend
    torque = fe.ls_torque_rad2_s4
    if torque == "auto":
        torque = "process_noise" if disturbed else 0.0
    out = stereo_points.process(
        meas_list,
        stereo_points.FrontEndSettings(
            rate_half_window=fe.rate_half_window,
            min_ls_epochs=fe.min_ls_epochs,
            max_dpacf_sigma_rad=max(fe.dpacf_emit_sigma_rad, tun.max_dpacf_sigma_rad),
            g_fit=fe.g_attitude_fit,
            template_refine_s=tuple(np.atleast_1d(np.asarray(fe.template_refine_s, float))),
            unbiased_last=bool(fe.ls_unbiased_rates),
            unbiased_early=fe.ls_unbiased_rates is True,
            q_r=float(q_r if torque == "process_noise" else torque),
        ),
    )
    out.R_LI = rot.quat_to_matrix(np.stack([m.q_LI for m in meas_list]))
    return out


ENGINE: Literal["auto", "numpy", "compiled"] = "auto"  # default of run_filter(engine=None)


NIS_WINDOW_S = 10.0  # the lost-track test's window (nis_alarm)


def nis_alarm(t: Array, nis: Array, dof: Array, window_s: float = NIS_WINDOW_S) -> NDArray:
    """Epochs at which the NIS summed over the last ``window_s`` exceeds the chi-square
    quantile 1 - 1e-4 of its summed degrees of freedom: the innovations no longer fit the
    filter's covariance (it has lost track, or its model does not fit, as ekf-baseline's
    free frame). A window needs at least 5 updates."""
    v = np.where(dof > 0, np.nan_to_num(nis), 0.0)
    cv, cd = np.concatenate([[0.0], np.cumsum(v)]), np.concatenate([[0.0], np.cumsum(dof)])
    cn = np.concatenate([[0], np.cumsum(dof > 0)])
    lo = np.searchsorted(t, t - window_s, side="right")
    k = np.arange(len(t)) + 1
    s_nis, s_dof, cnt = cv[k] - cv[lo], cd[k] - cd[lo], cn[k] - cn[lo]
    bound = stats.chi2.isf(1e-4, np.maximum(s_dof, 1))
    return (cnt >= 5) & (s_nis > bound)


def histories(res: dict[str, Any], scenario: Any) -> list[EstimateHistory]:
    """One :class:`EstimateHistory` per run of a :func:`run_filter` result."""
    fe = res["frontend"]
    max_sigma = parse_tuning(scenario.estimator.tuning).max_dpacf_sigma_rad
    out = []
    for b in range(res["x"].shape[0]):
        skipped = {k: int(v[b]) for k, v in fe.skipped.items()}
        skipped["gated_out"] = int(res["rejected"][b])
        skipped["diverged"] = int(res["diverged"][b])
        skipped["frame_flips"] = int(res["frame_flips"][b])
        reinit = res.get("reinit_epochs", [[]] * len(res["x"]))[b]
        skipped["reinitialised"] = len(reinit)
        # a filter that has lost track says so: epochs whose innovations over the last
        # NIS_WINDOW_S fail a chi-square test at 1e-4 (tumblenav default)
        skipped["nis_alarm"] = int(nis_alarm(res["t"], res["nis"][b], res["nis_dof"][b]).sum())
        k0 = res["k0"][b]
        out.append(
            EstimateHistory(
                t=res["t"],
                x=res["x"][b],
                P=res["P"][b],
                P_every=-(-len(res["t"]) // res["P"].shape[1]),
                layout=res["layout"],
                nis=res["nis"][b],
                nis_dof=res["nis_dof"][b],
                skipped=skipped,
                info={
                    "convention": "hu2024",  # the run's DPACF frame: evaluation.alignment
                    "template_G": fe.template_G[b],
                    "known": fe.known[b],
                    "start_time_s": float(res["t"][k0]) if k0 >= 0 else None,
                    "dpacf_q_TI": res["dpacf_q_TI"][b],
                    # restarts after the run lost track (run_filter): their times
                    "reinit_times_s": [float(res["t"][k]) for k in reinit],
                    "start_condition": (
                        "(the DPACF frame never reached a 1-sigma below max_dpacf_sigma_rad = "
                        f"{max_sigma} rad; epochs with >= 3 triangulated features: "
                        f"{int((fe.usable[b].sum(axis=1) >= 3).sum())} of {len(fe.t)})"
                    ),
                },
            )
        )
    return out
