"""Chang 2021 (Aerospace 8, 230) Sec. 2: relative pose EKF on stereo feature tracks
(``ekf-pose``).

Per epoch the stereo tracks give feature positions (two-ray triangulation) and velocities
(eq. 26) in the chaser's LVLH frame L; Davenport's q-method (eq. 27-28) on the features
registered in the estimator's target frame gives the attitude, eq. 29 the rate, eq. 30 the
mass centre's position and velocity; an EKF (eq. 1-25, measurement eq. 32) with the chaser
frame c = L and CW relative orbit filters them. See :mod:`.model` (state, dynamics, the
corrected eq. 23), :mod:`.measurements`, :mod:`.qmethod`, :mod:`.init` (the truth-free start
from the first ``init_frames`` frames) and :mod:`.filter`.

The estimator's frame That is defined at its first usable epoch k0 by ``R_ThatL(k0) = I``; the
history's ``info`` says so (``convention: chang2021``, ``frame_epoch``, ``R_ThatL_k0``) and
:func:`tumblenav.evaluation.alignment` expresses the truth in it. State blocks: attitude
``q_ThatL``, rate ``omega_ThatL_That`` (relative to L, Chang's ``omega_tc^t``), position
``r_L``, velocity ``v_L`` (the mass centre, as seen from L) and ``offset`` ``b`` (the mass
centre about the feature map's origin ``info['map_origin_L_k0']``, in That; tumblenav's, see
:mod:`.model`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tumblenav.errors import InputError
from tumblenav.estimators.base import EstimateHistory, fold, parse_tuning, register
from tumblenav.estimators.chang2021.filter import PoseMemo, PoseSteps
from tumblenav.estimators.chang2021.model import LAYOUT
from tumblenav.estimators.chang2021.qmethod import start_attitude_sigma_deg
from tumblenav.estimators.chang2021.slam import (
    LAYOUT_POSE,
    MapMemo,
    StateSteps,
    inertia_of,
    tuning_for_tracks,
)
from tumblenav.estimators.chang2021.tuning import PoseTuning
from tumblenav.estimators.context import context_from_scenario
from tumblenav.measurements import STEREO_TRACKS

__all__ = [
    "LAYOUT",
    "LAYOUT_POSE",
    "MapMemo",
    "PoseEKF",
    "PoseMemo",
    "PoseSteps",
    "PoseTuning",
    "StateSteps",
]

SKIP_REASONS = (
    "no_start_geometry",
    "initialising",
    "no_features",
    "too_few_features",
    "degenerate_geometry",
    "no_rate",
    "outlier_features",
    "gated_out",
    "wild_epoch",
    "failed_checks",
    "slips",
)


class PoseEKF:
    name = "ekf-pose"
    consumes: tuple[str, ...] = (STEREO_TRACKS,)
    needs = (
        "stereo feature tracks (any calibrated rig; Chang 2021 uses a convergent one); the "
        "chaser's orbit (CW) or none; the target's inertia is not needed (estimated from "
        "the nutation, inertia: estimated)"
    )
    description = (
        "Chang 2021: triangulation, q-method attitude, eq. 29 rate and eq. 30 centroid -> EKF "
        "on relative attitude, rate, position and velocity (LVLH, CW)"
    )

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        if scenario.sensor.kind != "stereo":
            raise InputError(
                f"ekf-pose needs stereo feature tracks; scenario {scenario.name} has a "
                f"{scenario.sensor.kind} sensor"
            )
        tun = parse_tuning(scenario.estimator.tuning, PoseTuning)
        if tun.inertia == "estimated" and tun.map != "state" and "inertia" in tun.model_fields_set:
            raise InputError(
                "ekf-pose: estimator.tuning.inertia 'estimated' needs map: state (the inertia "
                "is learnt with the feature map in the state)"
            )

    def run(self, scenario: Any, meas: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        self.check(scenario)
        tun = parse_tuning(scenario.estimator.tuning, PoseTuning)
        if tun.map != "state" and tun.inertia == "estimated":  # the default: map: state's
            tun = tun.model_copy(update={"inertia": "sphere"})
        tun = tuning_for_tracks(tun, meas)  # template tracks' slip test and gate
        orbit = scenario.chaser.orbit
        n = float(orbit.mean_motion_rad_s) if orbit is not None else 0.0
        pn = scenario.process_noise  # the mission's disturbance assumption (never the truth)
        q_r, q_t = float(pn.rotational_rad2_s4), float(pn.translational_m2_s4)
        steps: PoseSteps | StateSteps
        if tun.map == "state":
            steps = StateSteps(meas=meas, tun=tun, n_orbit=n, q_rot=q_r, q_trans=q_t)
        else:
            steps = PoseSteps(meas=meas, tun=tun, n_orbit=n, q_rot=q_r, q_trans=q_t)
        r = fold(steps, meas.t)
        skipped = {k: 0 for k in SKIP_REASONS} | r.skipped
        info: dict[str, Any] = {
            "convention": "chang2021",
            "estimates_offset": tun.map == "registered",
            "map": tun.map,
            "diverged": bool(r.diverged),
        }
        s = r.memo.start if r.memo is not None else None  # the fold's last memo
        if s is not None:
            info.update(
                frame_epoch=int(s.k0),
                R_ThatL_k0=np.eye(3).tolist(),  # That := L's orientation at frame_epoch
                start_epoch=int(s.k),
                start_fit=s.fit,
            )
            if s.fit_cost is not None:  # the batch start's (slam.StateSteps._batch)
                info["start_fit_cost_per_dof"] = float(s.fit_cost)
                info["start_fit_noise_ratio"] = float(s.fit_noise_ratio or 0.0)
            if tun.map == "registered":
                info["map_origin_L_k0"] = [float(v) for v in s.origin_L_k0]
            j = getattr(r.memo, "j", None)
            if tun.inertia == "estimated" and j is not None:
                # the last estimate: the tensor in That (mean moment 1) and, frame-free, its
                # principal moments over the largest
                J = inertia_of(j)
                ev = np.linalg.eigvalsh(J)
                info["inertia_That"] = J.tolist()
                info["inertia_principal_ratios"] = [float(v) for v in ev[::-1] / ev.max()]
            sig = start_attitude_sigma_deg(steps.tracks, s.k0, s.k)
            info["epoch_attitude_sigma_deg"] = sig
            if sig > tun.epoch_attitude_warn_deg:
                info["warnings"] = [
                    f"ekf-pose: one epoch's features fix the attitude to {sig:.1f} deg (1 sigma "
                    "about the axes across the line of sight, the start window's median; over "
                    f"{tun.epoch_attitude_warn_deg:g} deg): the stereo depth noise is too large "
                    "for the target's size at this range, so the estimate can drift far beyond "
                    "its covariance without any check noticing (a closer range, a longer "
                    "baseline or a finer camera would help)"
                ]
        return EstimateHistory(
            t=meas.t,
            x=r.x,
            P=r.P,
            layout=steps.layout,
            nis=r.nis,
            nis_dof=r.nis_dof,
            skipped=skipped,
            info=info,
        )


register("ekf-pose")(PoseEKF)
