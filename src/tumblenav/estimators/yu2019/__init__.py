"""Yu 2019 Sec. 3: EKF on depth point clouds with the mass-centre offset (``ekf-depth``).

State: relative position ``r`` and velocity ``v`` of the target's mass centre in L (the Hill
equations of Yu 2019 eq. 26-27, the same matrices as Hu 2024 eq. 4-5), the mass-centre offset
``b`` from the model origin (in T), the attitude ``q_TI``, the rate ``omega`` (in T) and the five
inertia ratios of Yu 2019 eq. 29, ``l = [Iyy, Izz, Ixy, Ixz, Iyz] / Ixx`` (Euler equations with
the full matrix, eq. 28). Error state ``[dtheta, domega, dl, dr, dv, db]`` (20), attitude error
as in :mod:`tumblenav.rotations`.

Measurements (eq. 30-32 written in L): every rectangle recognised in a scan
(:mod:`tumblenav.frontends.depth_pose`) gives the model attitude, i.e. ``q_TI`` (the model frame
is parallel to T), and the model origin ``p_ML = r - R_LT b``; the four-fold symmetry of each
rectangle is resolved against the filter's prediction (eq. 21-25). Yu 2019 gives the fixes no
covariance; tumblenav's error model (:mod:`.fixes`) starts from the first-order scatter of the
plane fit (eq. 3-5) and the ray grid's edge phase, and splits it into a white part (R, each
component's variance scaled by a factor learnt from the innovations) and a slowly varying part
carried as states (six Gauss-Markov states per model rectangle, decorrelating as the view
turns, and a common bias along the line of sight): the fixes' errors against the truth are
correlated from scan to scan (:mod:`.filter`). The estimate reports the 20 states above.

Beyond Yu 2019: the inertia ratios that the motion does not excite (a spin about a principal
axis) get a Schmidt (consider) update, so the EKF does not learn them from its own rate noise
(:func:`unexcited_ratios`); while the spin axis may stay put in T, the update gets no component
along the offset and position moved together along it, which no fix sees
(``consider_spin_axis_offset``); once the view has turned ``start_replay_rad``, the start
window is filtered again from the start with the inertia ratios the first pass ended with (a
relinearisation of eq. 28 away from the sphere the filter starts at: :meth:`DepthSteps._replay`,
``start_replays``); docs/results/yu2019.md and docs/results/consistency.md have
the measurements behind these.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tumblenav.errors import InputError
from tumblenav.estimators.base import (
    EstimateHistory,
    fold,
    register,
)
from tumblenav.estimators.base import parse_tuning as base_parse_tuning
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.yu2019.filter import DepthSteps
from tumblenav.estimators.yu2019.model import LAYOUT
from tumblenav.estimators.yu2019.tuning import DepthTuning, plane_threshold, process_noise
from tumblenav.measurements import DEPTH_CLOUDS

Array = NDArray[np.float64]


class DepthEKF:
    name = "ekf-depth"
    consumes: tuple[str, ...] = (DEPTH_CLOUDS,)  # the measurement types it runs on
    needs = "depth point clouds (depth sensor) and a target model with known rectangles"
    description = "Yu 2019: RANSAC rectangles -> coarse pose -> EKF with mass-centre offset"

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        if scenario.sensor.kind != "depth":
            raise InputError(
                f"ekf-depth needs a depth sensor; scenario {scenario.name} has a "
                f"{scenario.sensor.kind} sensor"
            )
        if not scenario.sensor.range_noise_m > 0:
            raise InputError(
                "sensor.range_noise_m is 0: ekf-depth weights each rectangle fix by the "
                "sensor's range noise and cannot weigh exact measurements; give the sensor's "
                "noise (it may be tiny, e.g. 0.001)"
            )
        base_parse_tuning(scenario.estimator.tuning, DepthTuning)

    def run(self, scenario: Any, meas: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        self.check(scenario)
        tun = base_parse_tuning(scenario.estimator.tuning, DepthTuning)
        from tumblenav.target_model import from_config

        if scenario.target_model is None:
            raise InputError(
                "ekf-depth needs the target's geometry model (Yu 2019 recognises its "
                "rectangles): give target.model in the scenario"
            )
        q_rot, q_trans = process_noise(tun, scenario.process_noise)
        steps = DepthSteps(
            model=from_config(scenario.target_model),
            meas=meas,
            tun=tun,
            sigma=scenario.sensor.range_noise_m,
            n_orbit=scenario.chaser.orbit.mean_motion_rad_s if scenario.chaser.orbit else 0.0,
            rng=rng,
            q_rot=q_rot,
            q_trans=q_trans,
        )
        r = fold(steps, meas.t)
        skipped = {
            "no_rectangle": 0,
            "gated_out": 0,
            "ambiguous_start": 0,
            "nonphysical_inertia": 0,
            "nonphysical_rate": 0,
            "reinitialised": 0,
            **r.skipped,
        }
        restarts = list(r.memo.restarts) if r.memo is not None else []
        n_scans = len(meas.t)
        # (said now, with the run's counts and times; kept in info["warnings"] without them,
        # so that a campaign's summary says each once with its number of runs)
        notes: list[tuple[str, str]] = []
        if n_scans and skipped["no_rectangle"] > 0.5 * n_scans:
            notes.append(
                (
                    f"ekf-depth recognised no rectangle in {skipped['no_rectangle']} of "
                    f"{n_scans} scans (range noise {scenario.sensor.range_noise_m:g} m, plane "
                    f"threshold {plane_threshold(tun, scenario.sensor.range_noise_m):g} m "
                    "against the model's rectangles)",
                    "ekf-depth recognised no rectangle in most scans",
                )
            )
        if restarts:
            times = ", ".join(f"{t:g}" for t in restarts[:5]) + (
                " ..." if len(restarts) > 5 else ""
            )
            notes.append(
                (
                    f"ekf-depth lost track {len(restarts)} time(s) and started again at "
                    f"t = {times} s",
                    "ekf-depth lost track and started again",
                )
            )
        tails = {
            "ekf-depth recognised no rectangle in most scans": ": the filter mostly coasts, and "
            "its few fixes may be wrong rectangles; do not trust its covariance",
            "ekf-depth lost track and started again": f" (every rectangle fix gated out for "
            f"{tun.reinit_after_gated} epochs in a row): the estimates before each restart "
            "were off track",
        }
        for detailed, generic in notes:
            warnings.warn(detailed + tails[generic], stacklevel=2)
        # the estimate is LAYOUT's (the marginal): the fixes' slow errors stay inside
        return EstimateHistory(
            t=meas.t,
            x=r.x[:, : LAYOUT.nominal_dim],
            P=r.P[:, : LAYOUT.dim, : LAYOUT.dim],
            layout=LAYOUT,
            nis=r.nis,
            nis_dof=r.nis_dof,
            skipped=skipped,
            info={
                "convention": "yu2019",
                "symmetries": steps.symmetries,  # evaluation: the model's symmetric frames
                "reinit_times_s": restarts,  # restarts after the run lost track
                "warnings": [generic + tails[generic] for _, generic in notes],
            },
        )


register("ekf-depth")(DepthEKF)
