"""Hu 2024 estimators' settings: ekf-dpacf's (:class:`HuTuning`) and ekf-baseline's defaults."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from tumblenav.estimators.base import nest_front_end_keys
from tumblenav.estimators.base import parse_tuning as base_parse_tuning
from tumblenav.frontends.stereo_points import StereoPointsTuning

Array = NDArray[np.float64]


class HuTuning(BaseModel):
    """``estimator.tuning`` keys of ekf-dpacf (all optional), with its defaults;
    :class:`BaselineTuning` holds ekf-baseline's. Two defaults follow another key, and the
    validated model shows the value used: ``dpacf_frame_error`` is 'white' with
    ``dpacf_measurement: frame``, and ``attitude_update`` is on unless the frame error is
    'consider'."""

    model_config = ConfigDict(extra="forbid")
    uses_dpacf: ClassVar[bool] = True
    sigma_t2_m2_s4: float | None = Field(
        None,
        ge=0,
        description="translational process noise (m^2/s^4); null: the scenario's "
        "process_noise.translational_m2_s4 (the mission's assumption, in the context)",
    )
    sigma_r2_rad2_s4: float | None = Field(
        None,
        ge=0,
        description="rotational process noise (rad^2/s^4); null: the scenario's "
        "process_noise.rotational_rad2_s4",
    )
    p0_rate_rad_s: float = Field(0.02, gt=0, description="initial 1-sigma of the rate (rad/s)")
    p0_inertia: float = Field(
        0.05,
        gt=0,
        description="1-sigma of each ratio p at the start, added (ekf-dpacf) to the front "
        "end's least-squares covariance of the ratios",
    )
    p0_mass_centre_m: float = Field(
        0.5,
        gt=0,
        description="1-sigma per axis of the mass centre's offset from the catalogued features' "
        "centroid, added to their spread about it (init.mass_centre_prior; the spread since "
        "issue 18's twenty-second session): the start's prior, and the joint batch's",
    )
    p0_velocity_m_s: float = Field(0.2, gt=0, description="initial 1-sigma of the velocity (m/s)")
    p0_unseen_feature_m: float = Field(
        3.0, gt=0, description="initial 1-sigma of features not yet seen (m)"
    )
    p0_attitude_rad: float = Field(0.5, gt=0, description="ekf-baseline initial attitude sigma")
    attitude_meas_every: int = Field(1, ge=1, description="use the DPACF attitude every k epochs")
    attitude_corr_time_s: float = Field(
        0.0, ge=0, description="correlation time of the DPACF frame error (R0 inflation)"
    )
    gate_probability: float | None = Field(
        None, gt=0, lt=1, description="per-feature chi-square innovation gate; default: none"
    )
    max_dpacf_sigma_rad: float = Field(0.05, gt=0, description="start once DPACF is this good")
    max_ratio_sigma: float | None = Field(
        0.003,
        gt=0,
        description="the filter starts only once the largest 1-sigma of the front end's "
        "inertia ratios is below this as well (beyond the paper: earlier, the least-squares "
        "ratios can be 4 sigma off, and the filter learns the ratios slowly, so its ratios "
        "stay near their start; ekf-baseline keeps the gate so that both start at the same "
        "epoch); null: no gate. 0.003 against the least squares' covariance without the "
        "(2h + 1) allowance (issue 18) and the unbiased rows (ls_unbiased_rates) starts "
        "hu2024 at 2e-5 rad after a median 17 s, as 0.01 did with the allowance: inertia "
        "RMSE 0.0040 over 40 runs (0.0065 before; 0.0166 with 0.01, a median start at 11 s "
        "on 4.6x smaller sigmas; benchmarks/hu2024_start_gate.py)",
    )
    dpacf_measurement: Literal["attitude", "frame"] = Field(
        "attitude",
        description="'attitude': Hu 2024 eq. 31 (q_TI = q_TG q_GI, every epoch); 'frame': the "
        "DPACF rotation R_TG against the filter's features (beyond the paper)",
    )
    frame_meas_every: int = Field(50, ge=1, description="epochs between frame measurements")
    first_estimates_jacobian: bool = Field(
        True,
        description="linearise dy_i/dtheta at each feature's first estimate (FEJ); off for "
        "ekf-baseline (which starts far from any principal frame, where frozen first "
        "estimates make it diverge)",
    )
    flip_epochs: int = Field(
        50, ge=1, description="DPACF measurements a half turn away before the filter follows"
    )
    constraint_curvature: bool = Field(
        True,
        description="keep the variance that the inertia constraint's curvature leaves along "
        "its gradient (beyond the paper; see constrain_inertia); off for ekf-baseline (whose ratios start at a sphere with 1-sigma 0.5, where the "
        "second-order term is meaningless: 216 instead of 183 of 500 runs at 1e-6 rad "
        "stopped as diverged)",
    )
    constraint_update: Literal["projection", "measurement"] = Field(
        "projection",
        description="how the ratios are kept on Hu 2024 eq. 19's constraint c(p) = 0 (every "
        "10 epochs): 'measurement': a near-perfect scalar pseudo-measurement (Simon 2010's "
        "estimate projection by a Kalman update; before issue 18's twenty-second session); "
        "'projection': the estimate moved onto the surface along its normal, the other "
        "states untouched, and the covariance projected onto the tangent plane "
        "(model.project_inertia; beyond the paper): repeated, the measurement moved the "
        "ratios by the spurious correlation that the linear updates build between their "
        "normal and tangent errors (hu_selfocc20: ratios 0.03 off at a sigma of 0.003). "
        "'measurement' for ekf-baseline (the paper's comparison filter)",
    )
    mass_centre_init: Literal["joint", "rotation", "centroid"] = Field(
        "joint",
        description="'centroid': the filter starts with the mass centre at the feature "
        "centroid (1-sigma p0_mass_centre_m); 'rotation': from a batch least squares over "
        "the rotation seen before the start, with the features fixed at their template "
        "(beyond the paper, mass_centre_from_rotation); 'joint': the same batch with the "
        "features about the mass centre as unknowns (features_from_rotation), which also "
        "gives the features refined over those views; both fall back to the centroid when "
        "the batch cannot tell the mass centre. 'rotation' for ekf-baseline (with 'joint' its tighter start on features expressed in its free, "
        "wrong principal frame stopped 71 instead of 14 of 500 runs at 2e-5 rad as diverged)",
    )
    iterate_sigma_rad: float = Field(
        0.1,
        ge=0,
        description="where the prior attitude's 1-sigma (rms over the axes) exceeds this, "
        "the update is iterated (relinearised at its posterior, from the same prior, "
        "iterate_max more times; beyond the paper): after a long occlusion the attitude "
        "is tens of degrees uncertain and the update linearised at the prior put the "
        "position and features off by several sigma. 0: never, ekf-baseline's default "
        "(the paper's comparison filter, whose free frame starts tens of degrees "
        "uncertain). Not with gate_probability",
    )
    iterate_max: int = Field(2, ge=0, description="the iterated update's extra iterations")

    p0_mass_centre_floor_m: float = Field(
        0.015,
        ge=0,
        description="1-sigma per axis added to the batch mass centre's covariance "
        "(mass_centre_init 'rotation': its least-squares covariance misses the template "
        "and G-attitude errors; measured errors per axis 3-14 mm rms, "
        "benchmarks/hu2024_mass_centre.py). Not with 'joint' (since issue 18): its fit "
        "takes every epoch's attitude as an unknown and the filter's random force over "
        "its window into account, so its covariance is the features' own (common shift "
        "NEES/dof 0.6-1.3 at the start on hu2024 and the consistency/hu_* scenarios; "
        "with the attitudes as measured the shape's was 2.5, and this floor and 1 cm per "
        "feature made the features conservative by 100x)",
    )
    dpacf_frame_error: Literal["consider", "white"] = Field(
        "consider",
        description="how the error of the DPACF frame itself (the least-squares principal axes, "
        "cov_frame, slowly varying) enters: 'white': as part of the eq. 31 attitude noise at "
        "every epoch (Hu 2024); 'consider': the filter works in the front end's frame, "
        "re-expresses its state whenever that frame is re-solved, measures only the white "
        "G-attitude part, and adds the frame's covariance to the covariance it reports "
        "(beyond the paper, see frame_consider_cov); 'white' by default with "
        "dpacf_measurement 'frame', and for ekf-baseline",
    )
    attitude_update: bool = Field(
        False,
        description="update with the DPACF attitude of Hu 2024 eq. 31. With "
        "dpacf_frame_error 'consider' that measurement is only the G attitude, a fit to the "
        "same feature points as the feature measurements (eq. 32-35): fusing both counts "
        "those points twice (beyond the paper). Default: off with 'consider' (the DPACF "
        "frame enters as the frame the state is expressed in, its half-turn votes still "
        "use the attitude), on with 'white' (the default follows dpacf_frame_error)",
    )
    refine_start: bool = Field(
        True,
        description="start from a Gauss-Newton fit of the attitude and position to the start "
        "epoch's feature points with their full covariances (refine_start_pose; beyond the "
        "paper), whose covariance is the initial one, and use that epoch only there; off for "
        "ekf-baseline (which has no principal frame to start in)",
    )
    sigma_f2_m2_s: float = Field(
        0.0,
        ge=0,
        description="random walk of each feature's position in T (m^2/s, per axis): what the "
        "rigid, exactly-known-template model leaves out (beyond the paper; Hu 2024 has none)",
    )
    branch_mixture: bool = Field(
        True,
        description="with dpacf_frame_error 'consider': the reported covariance also holds "
        "the half turns of the frame, weighted by the probability that the true inertia "
        "selects them (frontends.inertia.branch_statistics; beyond the paper)",
    )
    max_ratio_wait_s: float = Field(
        30.0,
        ge=0,
        description="with max_ratio_sigma: start anyway once the DPACF frame has been good "
        "enough for this long (a motion that leaves the ratios poorly determined must not "
        "keep the filter from starting)",
    )
    restart_on_alarm: bool = Field(
        True,
        description="ekf-dpacf: a run whose lost-track alarm fires (its innovations over "
        "the last 10 s fail their chi-square test at 1e-4, skipped.nis_alarm) is started "
        "again from the measurements after that epoch, as one whose state left every "
        "physical range is (tumblenav default since issue 18's twenty-fifth session; "
        "ekf-baseline, whose free frame raises the alarm throughout, never): on a scenario "
        "nobody tuned for (consistency/hu_conv14) two of 20 runs started from a front-end "
        "frame 7 deg off at a 1-sigma of 1 deg and held their inertia 0.2-0.6 off at a "
        "1-sigma of 0.002-0.02 to the end (docs/results/consistency.md)",
    )
    frame_error_dynamics_s: float = Field(
        60.0,
        ge=0,
        description="with dpacf_frame_error 'consider': the DPACF frame's error also enters "
        "the rate dynamics (beyond the paper): in a frame up to max_dpacf_sigma_rad off the "
        "diagonal inertia model is wrong by G u (G = d(Euler)/d(frame)), which the filter "
        "otherwise fits with its ratios, growing over-confident (issue 18, hu_occ30); how: "
        "frame_error_model. With 'white', the process noise G cov_frame G^T tau "
        "(model.frame_error_Qc; tau the polhode's time |omega| / |K(omega)|, at most this "
        "many seconds). 0: off",
    )
    frame_error_model: Literal["state", "white"] = Field(
        "state",
        description="with frame_error_dynamics_s > 0, how the DPACF frame's error u enters "
        "the rate dynamics: 'state': as a consider (Schmidt) parameter of the filter, "
        "u ~ N(0, cov_frame) constant while a frame is held, its cross-covariance with the "
        "state propagated through G (model.frame_error_rate_jacobian) and updated, u itself "
        "never, carried from one solution of the frame to the next as the errors of a "
        "growing least squares are (frame.frame_error_transition), and the cross terms in "
        "the reported covariance (beyond the paper, issue 18: the filter's error is "
        "correlated with u, which the white model misses: attitude, rate and ratios "
        "conservative, features' common rotation too); 'white': the process noise G "
        "cov_frame G^T tau (model.frame_error_Qc)",
    )

    frontend: StereoPointsTuning = Field(
        default_factory=StereoPointsTuning,
        description="the stereo-points front end's settings (StereoPointsTuning); both "
        "estimators share the front end, so that they start on the same data",
    )

    @model_validator(mode="before")
    @classmethod
    def _front_end_keys(cls, raw: Any) -> Any:
        """Front-end keys given at the top level (as before they moved) go to ``frontend``."""
        return nest_front_end_keys(raw, StereoPointsTuning)

    @model_validator(mode="after")
    def _dependent_defaults(self) -> HuTuning:
        """The two defaults that follow another key (see the class docstring), and the one
        combination that cannot work."""
        given = self.model_fields_set
        if "dpacf_frame_error" not in given and self.dpacf_measurement == "frame":
            self.dpacf_frame_error = "white"
        consider = self.uses_dpacf and self.dpacf_frame_error == "consider"
        if consider and self.dpacf_measurement == "frame":
            raise ValueError(
                "dpacf_frame_error 'consider' works with dpacf_measurement 'attitude' only"
            )
        if "attitude_update" not in given:
            self.attitude_update = not consider
        return self


class BaselineTuning(HuTuning):
    """``estimator.tuning`` keys of ekf-baseline: :class:`HuTuning`'s, with the defaults of
    the paper's comparison filter (Aghili & Parsa 2009: no DPACF, a free principal frame)."""

    uses_dpacf: ClassVar[bool] = False
    first_estimates_jacobian: bool = False
    constraint_curvature: bool = False
    constraint_update: Literal["projection", "measurement"] = "measurement"
    mass_centre_init: Literal["joint", "rotation", "centroid"] = "rotation"
    iterate_sigma_rad: float = Field(0.0, ge=0)
    dpacf_frame_error: Literal["consider", "white"] = "white"
    attitude_update: bool = True
    refine_start: bool = False


def parse_tuning(raw: dict[str, Any], use_dpacf: bool = True) -> HuTuning:
    """ekf-dpacf's (``use_dpacf``) or ekf-baseline's settings from ``estimator.tuning``."""
    return base_parse_tuning(raw, HuTuning if use_dpacf else BaselineTuning)
