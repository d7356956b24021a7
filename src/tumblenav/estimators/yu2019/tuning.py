"""Yu 2019 ekf-depth settings (:class:`DepthTuning`) and the rules behind their defaults."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from tumblenav.errors import InputError
from tumblenav.estimators.base import nest_front_end_keys, parse_tuning
from tumblenav.frontends.depth_pose import PlanesTuning
from tumblenav.settings_rules import positive_or_rule

Array = NDArray[np.float64]


class DepthTuning(BaseModel):
    """``estimator.tuning`` keys of ekf-depth (Yu 2019 Sec. 4 values as defaults)."""

    model_config = ConfigDict(extra="forbid")
    P0_sigma_position_m: float = Field(
        1.0, gt=0, description="initial 1-sigma of the position r (m; Yu 2019 Sec. 4)"
    )
    P0_sigma_velocity_m_s: float = Field(
        0.1, gt=0, description="initial 1-sigma of the velocity v (m/s)"
    )
    P0_sigma_offset_m: float = Field(
        0.1, gt=0, description="initial 1-sigma of the mass-centre offset b (m)"
    )
    P0_sigma_attitude_rad: float = Field(0.1, gt=0, description="initial attitude 1-sigma (rad)")
    P0_sigma_rate_rad_s: float = Field(
        0.1,
        gt=0,
        description="initial 1-sigma of the rate (rad/s); the filter starts at rate 0, so this "
        "must cover the tumble (tumblenav default 0.1 rad/s, ~6 deg/s; Yu 2019 Sec. 4 uses "
        "0.01 for its 1 deg/s spin, set in the yu2019 scenario)",
    )
    P0_sigma_inertia: float | Literal["inertia_init"] = Field(
        "inertia_init",
        description="initial 1-sigma of each inertia ratio; 'inertia_init': the one that "
        "matches the initial guess, P0_sigma_inertia_given or P0_sigma_inertia_sphere",
    )
    P0_sigma_inertia_given: float = Field(
        0.1,
        gt=0,
        description="with P0_sigma_inertia 'inertia_init' and inertia_init 'given' (Yu 2019 "
        "Sec. 4: a guess near the truth)",
    )
    P0_sigma_inertia_sphere: float = Field(
        0.5,
        gt=0,
        description="with P0_sigma_inertia 'inertia_init' and inertia_init 'sphere' (a sphere "
        "is 0.3-0.5 off a typical satellite's ratios)",
    )
    Q_diag: float | Literal["scenario"] = Field(
        "scenario",
        description="spectral density of the 6 disturbances (Yu 2019's single Q: angular "
        "acceleration about x in rad^2/s^3, the others x (Ixx/Iii)^2, and the mass centre's "
        "acceleration in m^2/s^3); 'scenario': the scenario's process_noise "
        "(rotational_rad2_s4 and translational_m2_s4, each its own)",
    )
    frontend: PlanesTuning = Field(
        default_factory=PlanesTuning,
        description="the planes front end's settings (PlanesTuning)",
    )
    gate_probability: float = Field(
        0.9999,
        gt=0,
        lt=1,
        description="NIS gate per fix (6 dof); rejections are counted as gated_out (off "
        "without the multi-solution fix)",
    )
    inertia_init: Literal["sphere", "given"] = Field(
        "sphere",
        description="initial inertia ratios: 'sphere' (1, 1, 0, 0, 0: nothing known) or "
        "'given' (inertia_init_ratios, a prior the user states)",
    )
    inertia_init_ratios: list[float] = Field(
        [1.0, 1.0, 0.0, 0.0, 0.0],
        min_length=5,
        max_length=5,
        description="with inertia_init 'given': [Iyy/Ixx, Izz/Ixx, Ixy/Ixx, Ixz/Ixx, Iyz/Ixx]",
    )
    inertia_init_perturb: bool = Field(
        False,
        description="add an error drawn from P0 to the given ratios (Yu 2019's protocol: its "
        "initial state is 'the truth corrupted by initial errors'; the yu2019 recipe gives the "
        "true ratios with this on)",
    )
    position_noise_scale: float = Field(
        1.0,
        gt=0,
        description="variance multiplier on each fix's centre error model (fixes.fix_noise: "
        "the ray grid's edge phase h^2/12 in the plane, foreshortened along the view's trace, "
        "and sigma^2 cos(i)/n along the normal)",
    )
    attitude_noise_scale: float = Field(
        1.0,
        gt=0,
        description="variance multiplier on each fix's attitude error model (fixes.fix_noise: "
        "the tilts from the plane fit, eq. 4-5 with sigma^2 cos(i), the turn about the "
        "normal from the edges' phase)",
    )
    fix_error_states: bool = Field(
        True,
        description="carry the slowly varying part of each rectangle's fix errors (the ray "
        "grid's edge phase, the same from scan to scan until the view turns) as first-order "
        "Gauss-Markov states, six per model rectangle, so that R is the white part only "
        "(tumblenav, beyond Yu 2019); false: all of it white",
    )
    fix_error_slow_fractions: list[float] = Field(
        [0.3, 0.3, 0.3, 0.5, 0.5, 0.3],
        min_length=6,
        max_length=6,
        description="the slowly varying share of each fix component's variance: the attitude "
        "about the rectangle's short side, long side and normal, the centre along them "
        "(measured on the yu scenarios of issue 18 at a decorrelation of 7 spacings: 0-0.06, "
        "0-0.18, 0-0.28, 0.07-0.56, 0.07-0.57, 0.01-0.06; 0.3 on the attitude and the normal "
        "covers the slow errors the autocorrelation over 40 scans misses)",
    )
    fix_error_decorrelation_spacings: float = Field(
        7.0,
        gt=0,
        description="the view turn over which the slow part decorrelates (e-fold), in ray "
        "spacings across the face: this x h/a rad (fitted 5-9 spacings, 0.11-0.37 rad, on "
        "the yu scenarios of issue 18, at 0.009-0.035 rad per scan)",
    )
    fix_error_oblique_spacings: float = Field(
        0.2,
        ge=0,
        description="1-sigma, in ray spacings h times sin(i), of a face's centre error along "
        "the view's trace on it that the view's obliquity makes (a slow state, not scaled "
        "by the learnt scales; measured: -0.3 h grazing to +0.15 h near face on, the same "
        "in every run)",
    )
    fix_error_oblique_normal: float = Field(
        0.5,
        ge=0,
        description="1-sigma, in threshold^2 / (2 b) times sin(i), of the plane's offset "
        "that the strip of the face-on neighbour in its slab makes when the face is seen "
        "obliquely (a slow state; measured 0.5 of it, inward, at grazing)",
    )
    fix_range_bias_spacings: float = Field(
        0.15,
        ge=0,
        description="1-sigma of the fixes' common bias along the line of sight, in ray "
        "spacings h of the start's fixes: a random constant the filter carries (tumblenav; "
        "measured on the yu scenarios of issue 18: the rectangles' centres sit 0.08-0.12 h "
        "nearer the sensor, averaged over the views, the same in every run; 0: none)",
    )
    edge_turn_floor: float = Field(
        0.12,
        ge=0,
        description="with frontend.edge_turn: a fix's turn about its normal from the edges "
        "gets the edges' own variance (planes.edge_turn: the grid's phase drifting along each "
        "side), but at least this fraction of the second moments' (the edge phase across the "
        "short side over half the long side, 4 h^2/(12 a^2)): the edges' errors are 0.3-0.5x "
        "the moments' RMS but come in runs of one sign at oblique views, which the sawtooth "
        "model misses. Measured, 20 runs (docs/results/consistency.md, Yu section): 0.12 puts "
        "yu2019 (0.946), yu_small_10m, yu_large_50m, yu_outliers and yu_tumble inside; "
        "without a floor yu_large_50m was 1.34 (before the grid steps were taken from the "
        "rays)",
    )
    fix_noise_adaptive: bool = Field(
        True,
        description="learn a variance scale per fix component (attitude about and centre "
        "along the rectangle's short side, long side and normal) from the innovations "
        "(weighted covariance matching, tumblenav): the ray grid's errors are 0.04-1x the "
        "model's, as the grid happens to lie on the faces; false: the model's variances",
    )
    fix_noise_learnt: list[bool] = Field(
        [True, True, False, True, True, True],
        min_length=6,
        max_length=6,
        description="with fix_noise_adaptive: which components' scales are learnt (attitude "
        "about the short side, long side, normal; centre along them). The turn about the "
        "normal keeps the model's: it comes from the edges alone, carries the model's own "
        "asymmetries (a per-face bias of 1 mrad on yu2019's bus-y) and heavy tails, and a "
        "learnt scale (0.05-0.2) let the attitude about the normal drift on yu_large_50m (9 "
        "of 20 runs lost track)",
    )
    fix_noise_memory_fixes: float = Field(
        100.0,
        gt=1,
        description="with fix_noise_adaptive: the number of fixes the learnt scales remember "
        "(the evidence fades by 1 - 1/this per fix)",
    )
    fix_noise_prior_fixes: float = Field(
        4.0,
        gt=0,
        description="with fix_noise_adaptive: the weight, in fixes, of the start's scale 1 "
        "(the model's variances)",
    )
    consider_unexcited_ratios: bool = Field(
        True,
        description="Schmidt (consider) update for the inertia ratios whose effect on the "
        "dynamics the rate's own noise could produce (a spin about a principal axis): beyond "
        "Yu 2019, the EKF otherwise gains spurious information on them",
    )
    second_order_fixes: bool = Field(
        True,
        description="each fix's origin gets the mean and covariance of its terms of second "
        "order in the attitude and offset errors (model.measurement_second_order, the "
        "Gaussian second-order filter; tumblenav, beyond Yu 2019): at the start (attitude "
        "0.1 rad, offset 0.1 m) the neglected [dtheta x] db moves the origin by ~1 cm, which "
        "a precise sensor's first-order update takes as information. yu2019 at 1 mm range "
        "noise (docs/results/scenarios/consistency/yu_1mm.yaml): NEES/dof 230 over 10 runs "
        "without (the offset 0.1 m off at 2 mm, every fix gated out from 75 s on), 1.34 over "
        "20 with; at 1 cm (yu2019, 20 runs) 0.892 -> 0.779, the translation blocks no longer "
        "over-confident. False: first order only",
    )
    start_replay_rad: float = Field(
        4.4,
        ge=0,
        description="the start window replayed (filter.DepthSteps._replay; tumblenav, beyond "
        "Yu 2019): once the view has turned this far (rad, the view clock) since the track's "
        "start, the filter runs again over the window from the start's state and P0 with the "
        "inertia ratios the first pass ended with (a relinearisation: an EKF started at a "
        "sphere linearises eq. 28 along its own changing estimate and gains spurious "
        "information on the ratios). 4.4 rad (50 s of yu_tumble); 20 runs each (python "
        "benchmarks/consistency.py -o OUT --workers 1 --only yu_tumble_depth,yu2019_depth,"
        "yu_outliers_depth,yu_small_10m_depth), NEES/dof before -> with it: yu_tumble 2.18 -> "
        "1.24 (still above 1.14: run 17 alone 7.2, its replay wandered off in its first 30 "
        "scans; inertia RMSE 0.037 -> 0.023, attitude 0.187 -> 0.236 deg), yu_outliers 1.43 "
        "-> 1.35, yu2019 0.882 -> 0.896, yu_small_10m 0.928 -> 0.968 (attitude 0.281 -> 0.329 "
        "deg), NIS unchanged; yu_large_50m turns less (no replay). Per block on yu_tumble, "
        "seeds 0,1,2 (benchmarks/block_nees.py): inertia 5.03 -> 1.17, all 1.91 -> 0.78. "
        "2.2 rad: yu_tumble 1.32. 0: no replay",
    )
    start_replays: int = Field(
        1,
        ge=0,
        description="passes of the start replay (start_replay_rad; 0: none). yu_tumble, 20 "
        "runs: 1 pass NEES/dof 1.24, 2 passes 1.68 (measured with the offset and [r, v] "
        "relinearised too; the failing runs move: 13 at 12.0, 17 at 7.0; the others "
        "0.47-1.39)",
    )
    start_replay_disagreement: bool = Field(
        True,
        description="after the start replay, add d d^T to its covariance, d the first pass's "
        "end state minus the replay's (error state; filter.DepthSteps._replay; tumblenav): "
        "the two passes differ only in their linearisation of the same data, so their "
        "difference measures a linearisation error neither covariance holds (yu_tumble run "
        "17: the first pass ended its window 0.01 off in the ratios, the replay 0.35 off at "
        "0.04 sigma). 20 runs each, python benchmarks/consistency.py -o OUT --workers 1 "
        "--only yu_tumble_depth,yu_outliers_depth,yu2019_depth,yu_small_10m_depth,"
        "yu_large_50m_depth, NEES/dof without -> with: yu_tumble 1.24 -> 0.93 (attitude RMSE "
        "0.236 -> 0.148 deg), yu_outliers 1.35 -> 1.08 (0.62 -> 0.50 deg), yu2019 0.896 -> "
        "0.892, yu_small_10m 0.968 -> 0.947, yu_large_50m 1.03 (no replay), NIS unchanged; "
        "the paper's setting (tumblenav montecarlo docs/results/scenarios/yu2019_1cm_noise.yaml "
        "-e ekf-depth --runs 20): attitude 0.068 deg, position 98.4 mm, unchanged. On other "
        "seeds (montecarlo.seed 2803, 2804; 20 runs): yu_tumble 0.82 -> 0.74 (both below "
        "0.866, no tail there), yu_outliers 2.00 -> 1.81 (still over: a product of inertia "
        "frozen in the first pass, run 5 10.2). False: the replay's own covariance",
    )
    reinit_after_gated: int = Field(
        5,
        ge=1,
        description="epochs in a row whose every rectangle fix the NIS gate rejects before "
        "the run is taken as lost and started again from that epoch's fixes (tumblenav "
        "default; counted in skipped['reinitialised'], times in info['reinit_times_s'])",
    )
    start_agreement_deg: float = Field(
        10.0,
        gt=0,
        description="a (re)start needs the rectangles of its scan to agree on the attitude "
        "within this angle (tumblenav default: a plane taken for the wrong rectangle does not)",
    )
    start_agreement_sides: float = Field(
        0.1,
        gt=0,
        description="... and on the model origin within this fraction of the model's largest "
        "rectangle side",
    )
    consider_spin_axis_offset: bool = Field(
        True,
        description="while the spin axis may stay put in T (model.spin_axis_fixed, within "
        "the rate's and the ratios' uncertainty), the update gets no component along "
        "(dr, db) = (R_LT u, u), which no fix sees: only the Hill model's curvature tells "
        "it, and the linearisation at a noisy attitude claims far more (an "
        "observability-constrained gain; tumblenav). False: the plain gain (on yu2019 the "
        "offset along the axis then settled 2-3 sigma off)",
    )
    multi_solution_fix: bool = Field(
        True,
        description="resolve each rectangle's symmetric cases against the prediction "
        "(Yu 2019 eq. 21-25); false reproduces the paper's Fig. 9 (180-degree jumps)",
    )

    @model_validator(mode="before")
    @classmethod
    def _front_end_keys(cls, raw: Any) -> Any:
        """Front-end keys given at the top level (as before they moved) go to ``frontend``."""
        return nest_front_end_keys(raw, PlanesTuning)

    @field_validator("Q_diag", mode="before")
    @classmethod
    def _q_number_or_rule(cls, v: Any) -> Any:
        """A number >= 0, or 'scenario' (``null`` means 'scenario')."""
        if v is None or v == "scenario":
            return "scenario"
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
            raise ValueError(f"Q_diag must be a number >= 0 or 'scenario', got {v!r}")
        return float(v)

    @field_validator("P0_sigma_inertia", mode="before")
    @classmethod
    def _number_or_rule(cls, v: Any, info: ValidationInfo) -> Any:
        """A positive number, or the rule named by the default (``null``, the former default,
        means the rule too)."""
        assert info.field_name is not None  # a field validator's info names its field
        return positive_or_rule(v, cls.model_fields[info.field_name].default)


def _sigma_inertia(tun: DepthTuning) -> float:
    """P0 sigma of the ratios: as given, else the one that matches the initial guess."""
    if tun.P0_sigma_inertia != "inertia_init":
        return tun.P0_sigma_inertia
    if tun.inertia_init == "given":
        return tun.P0_sigma_inertia_given
    return tun.P0_sigma_inertia_sphere


# the half turns about x, y, z (the model's symmetric frames) flip these signs of the products
# of inertia [Ixy, Ixz, Iyz]; the diagonal ratios stay
_HALF_TURN_PRODUCT_SIGNS = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)


def given_ratios_warning(tuning: dict[str, Any], inertia_T: Any) -> list[str]:
    """ekf-depth's given inertia ratios (``inertia_init: given``, Yu 2019 eq. 29's
    [Iyy/Ixx, Izz/Ixx, Ixy/Ixx, Ixz/Ixx, Iyz/Ixx]) against the simulated target's
    ``inertia_T`` (3, 3), in the closest of the model's half-turn frames (one line each, for
    :func:`tumblenav.evaluation.assumption_warnings`): with ``inertia_init_perturb`` (Yu's protocol, the truth plus an
    error drawn from P0) they stand for the truth, so any difference over 1e-3 contradicts it;
    without, they are a prior, contradicted beyond 3 of its stated sigma. A copied scenario
    whose target was changed keeps the old ratios, and the filter trusts them."""
    if tuning.get("inertia_init") != "given":
        return []
    try:  # the settings as ekf-depth reads them (its defaults and its P0 rule)
        tun = parse_tuning(tuning, DepthTuning)
    except InputError:
        return []  # not ekf-depth's: the estimator says what is wrong with them
    stated = np.asarray(tun.inertia_init_ratios, dtype=float)
    J = np.asarray(inertia_T, dtype=float)
    J = J / J[0, 0]
    diag, prod = np.array([J[1, 1], J[2, 2]]), np.array([J[0, 1], J[0, 2], J[1, 2]])
    sigma = _sigma_inertia(tun)
    off = min(
        float(np.max(np.abs(stated - np.r_[diag, signs * prod])))
        for signs in _HALF_TURN_PRODUCT_SIGNS
    )
    if off <= (1e-3 if tun.inertia_init_perturb else 3.0 * sigma):
        return []
    true = np.round(np.r_[diag, prod], 4).tolist()
    said = (
        "with inertia_init_perturb they stand for the truth (the start adds an error drawn "
        f"from P0, sigma {sigma:g})"
        if tun.inertia_init_perturb
        else f"more than 3 times their stated sigma {sigma:g}"
    )
    return [
        f"estimator.tuning.inertia_init_ratios {np.round(stated, 4).tolist()} differ from the "
        f"simulated target's {true} (target.inertia_kg_m2) by up to {off:.3g}; {said}, and "
        "the filter starts from them as known to that sigma (inertia_init: given): if the "
        "target's inertia is not meant to be known, set inertia_init: sphere, otherwise give "
        "the target's ratios"
    ]


def plane_threshold(tun: DepthTuning, range_noise_m: float) -> float:
    """Inlier distance (m) of the RANSAC plane fits (:meth:`PlanesTuning.threshold`)."""
    return tun.frontend.threshold(range_noise_m)


def process_noise(tun: DepthTuning, process_noise_cfg: Any) -> tuple[float, float | None]:
    """``(q_rot, q_trans)`` of the filter's Q: the scenario's process-noise spectral densities
    (``Q_diag: scenario``, the default), or ``(Q_diag, None)``: Yu 2019's single Q."""
    if tun.Q_diag == "scenario":
        return (
            float(process_noise_cfg.rotational_rad2_s4),
            float(process_noise_cfg.translational_m2_s4),
        )
    return float(tun.Q_diag), None
