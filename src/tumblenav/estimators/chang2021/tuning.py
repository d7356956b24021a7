"""``estimator.tuning`` of ekf-pose (:class:`PoseTuning`). Chang 2021 gives none of these values
(notes Sec. 1.9): every default is tumblenav's and says why."""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

Array = NDArray[np.float64]


class PoseTuning(BaseModel):
    """Settings of ``ekf-pose`` (Chang 2021 Sec. 2 and 4.1)."""

    model_config = ConfigDict(extra="forbid")

    map: Literal["state", "registered"] = Field(
        "state",
        description="where the features' positions about the mass centre live. 'state' "
        "(tumblenav's, default): each live track's position s_i in That is a state and each "
        "triangulated feature a measurement rho_i = r + R_LThat s_i (as Hu 2024's filter), "
        "so the mass centre is what the rotation of the features about it says. "
        "'registered': Chang 2021 as printed, eq. 27-30 pose fixes from features registered "
        "once with the current estimate (r_i = R_ThatL (rho_i - r_hat)); eq. 30 then "
        "reproduces the estimate it registered with and the filter takes it as news "
        "(circular: measured on chang2021_close point tracks, 10 runs, window 40-120 s, "
        "position RMS per axis 0.36-0.57 m with NEES/dof 27, benchmarks/chang2021_estimator.py "
        "with map 'registered'; see the module docstring of tumblenav.estimators.chang2021.slam)",
    )
    max_map_features: int = Field(
        120,
        ge=3,
        description="with map 'state': most tracks held in the state (the longest tracked so "
        "far first; the others are not used). 120 (the image front end's n_max, Chang 2021 "
        "Sec. 3.3: all of them), measured on chang2021_close rendered images, runs 0-3, "
        "window 40-120 s: attitude RMS per axis 0.33/0.34/0.27 deg with 50, 0.31/0.18/0.22 "
        "with 80, 0.14/0.23/0.13 with 120; position 8-13 / 4-8 / 3-5 mm; ~1.4 times the time "
        "of 50 per run. On point tracks (4 runs) 50 and 120 are alike (attitude 0.04-0.05 deg, "
        "position 3-4 mm)",
    )
    fej: bool = Field(
        True,
        description="with map 'state': first-estimate Jacobians, the attitude columns of each "
        "feature's measurement evaluated at the feature's first estimate (with "
        "invariant_errors in the start replay only)",
    )
    invariant_errors: bool = Field(
        True,
        description="with map 'state': after the start, the rotation of That stays "
        "unobservable to the linearised filter (tumblenav's, issue 18; see the module "
        "docstring of tumblenav.estimators.chang2021.slam): the covariance is propagated in "
        "errors in which that rotation is the attitude error alone, re-expressed at each "
        "update's estimate, and the map's Jacobians are taken at the current map (fej then "
        "applies to the start replay only). Chang's printed 59 m on point tracks, runs 0-1, "
        "check off: NEES/dof 441 -> 10.7 (the attitude no longer drifts to 3.5 deg at a "
        "1-sigma of 0.07 deg); without it but with the current map's Jacobians 25.7",
    )
    start_fit: Literal["replay", "batch"] = Field(
        "batch",
        description="with map 'state': how the start window becomes the first belief. "
        "'replay': the filter run over the window start_passes times (start_replay). "
        "'batch' (tumblenav's, issue 18): a Gauss-Newton fit of the window's torque-free "
        "motion, mass centre and map to every sighting (a bundle adjustment; "
        "tumblenav.estimators.chang2021.batch); the fit and its covariance (plus the "
        "window's Q and what the fit absorbs of it into its map, slam.absorbed_walk) are the "
        "first belief where the process noise over the window is within batch_noise_ratio "
        "of the fit's attitude variance (Chang's printed 59 m, ~40 m with disturbances), "
        "elsewhere the replay runs from the fit's rate, mass centre and map (at close range "
        "with disturbances; image tracks: template_batch_noise_ratio; sliding tracks "
        "always); without a fit, the replay as with 'replay'",
    )
    batch_noise_ratio: float = Field(
        60.0,
        gt=0,
        description="with start_fit 'batch': the fit (which takes the window's motion as "
        "torque-free; its covariance then carries the window's Q and, to first order, what "
        "the fit absorbs of the noise's walk into its map) is the first belief when the "
        "scenario's process noise turns the attitude over the window by at most this times "
        "the fit's own variance (the largest eigenvalue of P_fit^-1 Q_window on the "
        "attitude); above it the replay runs from the fit's solution. Measured ratios (runs "
        "0-2, or all 20): Chang's printed 59 m 0.21-0.32, chang2021_close images 61-10030 "
        "(template tracks: template_batch_noise_ratio), chang_range40 18-41 (20 runs), "
        "chang_range20 91-226 (20 runs), chang_features40 235-470, chang_paper 400-1000, "
        "chang_inertia "
        "3900-8500. 60 (twentieth session, issue 18; was 1, before the absorbed walk) lies in "
        "the gap between the two regimes measured, chosen from these cases, not derived: "
        "runs 0-9 with the fit as the first belief against the replay, "
        "NEES/dof chang_range40 (20 runs) 1.04 against 1.52, chang_range20 1.42 against "
        "1.04 (the table's 20 runs), chang_paper 1.61 against 1.02: the first-order account "
        "of what the fit absorbs holds at tens, not at hundreds",
    )
    template_batch_noise_ratio: float | None = Field(
        1.0,
        gt=0,
        description="batch_noise_ratio for tracks whose sightings after the first are stated "
        "more precise than a new corner (a template tracker's, the image front end's; as "
        "template_gate_probability; None: batch_noise_ratio for these too; twentieth "
        "session, issue 18). The fit's absorbed walk was measured on point tracks; on "
        "image tracks (slips, which the rigid fit only gates) it is not shown to hold: "
        "chang2021_close rendered images, cached runs 0 / 5 with 0.15 px stated for the "
        "tracked sightings (ratios 28 / 53; window 40-120 s), NEES/dof 0.87 / 1.32 from the "
        "fit against 0.41 / 0.88 from the replay, NIS equal; with the front end's 0.06 px "
        "the ratios of runs 0-3 and 5 are 61-10030, at the edge of 60",
    )
    replay_gate_probability: float = Field(
        0.99,
        gt=0,
        lt=1,
        description="with start_fit 'batch' where the replay runs from the fit (batch+replay): "
        "chi-square (3 dof) gate on the difference of the replay's end attitude and the fit's, "
        "against the sum of their covariances (the fit's with the window's process noise, "
        "slam.StateSteps._window_noise); beyond it the replay is refused and the fit is the "
        "first belief (info start_fit 'batch (replay refused)'; nineteenth session, issue 18). The sum "
        "over-states the difference's covariance (the two share their data), so the test is "
        "loose. Measured (d^2 per run, runs 0-9): chang_paper and chang_range20 0.0-0.2; "
        "chang_range40 (40 m, disturbed truth, runs 0-7) 0.0-0.7 where the replay holds, "
        "18.9 and 61.4 in runs 7 and 3 where it ended 1.7 and 3.2 deg off at a 1-sigma of "
        "~0.1 deg (NEES/dof 13 and 69 over those runs; 1.08 for run 3 with the fit instead). "
        "Point tracks only: on image tracks (slips, a template tracker's) the rigid fit is the "
        "weaker of the two (chang2021_close rendered images, cached run 5: the replay refused, "
        "NEES/dof 510)",
    )
    start_replay: bool = Field(
        True,
        description="with map 'state': the filter is run over the start window from k0 "
        "(attitude exact there by definition) with the window's rate and mass-centre fit as "
        "its prior, instead of starting from the window's last q-method fix",
    )
    start_rate_inflation: float = Field(
        25.0,
        ge=1,
        description="with start_replay: the window's rate fit covariance is multiplied by this "
        "for the replay's prior (the same frames are used twice: the prior must be loose)",
    )
    divergence_epochs: int = Field(
        10,
        ge=1,
        description="with map 'state': an epoch where fewer than half of the map's observed "
        "features pass the gate is 'wild' (no update); this many wild epochs in a row stop the "
        "run as diverged (2 s at 5 Hz)",
    )
    check_lag_frames: int = Field(
        25,
        ge=0,
        description="with map 'state': independent divergence check (tumblenav's; Chang 2021 "
        "has none). Every check_lag_frames epochs the attitude increment between the last "
        "check epoch and now is measured from the raw tracks alone (Davenport's q-method on "
        "the features triangulated at both epochs, no map, no filter) and compared with the "
        "filter's increment, gated by the sum of both covariances (plus check_floor_deg); "
        "check_fails failed checks in a row stop the run as diverged. 0: off. 25 frames (5 s "
        "at 5 Hz, ~25 deg of Chang's tumble): long enough for a rate error to show, short "
        "enough that most tracks span it",
    )
    check_gate_probability: float = Field(
        0.9999,
        gt=0,
        lt=1,
        description="chi-square (3 dof) gate of the divergence check's increment residual",
    )
    check_fails: int = Field(
        3,
        ge=1,
        description="failed divergence checks in a row that stop the run (15 s at the default "
        "lag and 5 Hz)",
    )
    check_floor_deg: float = Field(
        1.0,
        ge=0,
        description="1-sigma per axis (deg) added to the divergence check's covariance: the "
        "image tracks' slow LK drift (correlated over the lag, which the white pixel noise of "
        "the q-method covariance leaves out) and the q-method's nonlinearity; a filter off by "
        "a few degrees over 5 s is diverged, not noisy",
    )
    start_passes: int = Field(
        5,
        ge=1,
        description="with start_replay: how many times the start window is replayed; each "
        "pass after the first starts from the previous pass's mass centre and velocity at "
        "the window's end, propagated back to k0 (the prior covariance unchanged: a "
        "relinearisation, as an iterated filter). The window's mass-centre fit can be ~0.8 m "
        "off along the rotation axis (the direction one window's rotation hardly observes) "
        "and a filter linearised there takes spurious information along it: on "
        "chang2021_close point tracks (seeds 0-1, window 40-120 s) NEES/dof 2.08 with 1 "
        "pass (per block attitude 2.3, position 4.6), 1.22 with 2, 1.04 with 3 (attitude "
        "1.65, position 1.5); each pass costs init_frames filter steps. With "
        "replay_relinearise_map the map's Jacobians are relinearised as well, and more passes "
        "keep helping at range: chang_range20 (20 runs) 1.12 with 3, 1.06 with 4, 1.03 with 5; "
        "chang_paper 1.08 / 1.06, chang_inertia 1.15 / 1.09 with 3 / 5",
    )
    replay_relinearise_map: bool = Field(
        True,
        description="with start_replay and fej: each pass after the first evaluates the "
        "attitude columns of a map point's measurement (its first-estimate Jacobian) at the "
        "previous pass's estimate of that point instead of its first triangulation (~0.2 m "
        "off in depth at 20 m against a 1-m lever arm), an iterated start as Gauss-Newton "
        "relinearises a batch (tumblenav's; see slam.StateSteps._replay). chang_range20 "
        "(20 runs) NEES/dof 1.43 -> 1.03 with 5 passes (attitude block 1.91 -> 1.05)",
    )
    release_axis: bool = Field(
        True,
        description="with start_replay: after the replay the mass centre along the rotation "
        "axis gets prior_mass_centre_sigma_m back (the window does not observe it; the "
        "linearised filter claims it does: see slam.StateSteps._release_axis)",
    )
    init_frames: int = Field(
        100,
        ge=3,
        description="frames of the start window (Chang 2021 Sec. 4.1: 'the first 100 frames "
        "initialise the filter'); the filter starts at the window's last frame",
    )
    min_features: int = Field(
        3, ge=3, description="fewest matched features for a pose measurement (q-method: 3)"
    )
    inertia: Literal["sphere", "given", "estimated"] = Field(
        "estimated",
        description="target inertia in the dynamics (eq. 3): 'sphere' (unknown: torque-free "
        "with omega_TI constant in the body; the Euler-torque mismatch goes into the rate "
        "process noise, see inertia_asymmetry), 'given' (inertia_kg_m2, a prior expressed in "
        "the estimator's frame That: meaningful only when That is the principal frame, i.e. "
        "with the paper's truth-based start) or 'estimated' (tumblenav default, issue 18; "
        "map: state only, map: registered falls back to 'sphere'): the inertia tensor in "
        "That, up to scale, as five states started at the sphere with a 1-sigma of "
        "inertia_sigma each, learnt from the nutation through eq. 3 (with 'sphere' the "
        "nutation, a deterministic drift of the rate, is a random walk to the filter: rate "
        "NEES/dof 0.3-0.4 and position 1.9-3 on chang_inertia; measured in "
        "docs/results/consistency.md)",
    )
    inertia_kg_m2: list[float] | list[list[float]] = Field(
        [1.0, 1.0, 1.0],
        description="with inertia 'given': principal moments [I1, I2, I3] or the 3x3 tensor "
        "in That (kg m^2; only ratios matter)",
    )
    inertia_sigma: float | Literal["auto"] = Field(
        "auto",
        description="with inertia 'estimated': the 1-sigma of each of the five inertia "
        "parameters about the sphere at the start (J = I + D, D traceless; tumblenav "
        "default). 'auto' (the default since issue 18's twenty-fifth session; 0.05 before): "
        "0.15 where one epoch's features fix the attitude to within epoch_attitude_warn_deg "
        "over the start window, else 0.05 (slam.StateSteps.inertia_sigma_at). Why: a target "
        "nobody tuned for, moments (30, 20, 45), i.e. 0.42 from the sphere, was "
        "over-confident under the 0.05 prior (chang_range15, 20 runs: NEES/dof 1.58, 1.17 at "
        "0.15); where one epoch fixes the attitude only to several degrees the nutation the "
        "inertia is learnt from is buried in the tracks' errors, and a wider prior lets them "
        "move it far (the built-in chang2021 at 59 m on images, 15 deg per epoch: NEES/dof 128 "
        "at 0.05, 1.6e3 at 0.1, 4.1e3 at 0.15, attitude 6.5 -> 31 deg). Earlier: on rendered "
        "images (chang2021_close run 3, before the batch start) 0.3 ran to principal ratios "
        "1 / 0.55 / 0.06 and 5 deg of attitude error, 0.1 to 1 / 0.84 / 0.66 (truth "
        "1 / 0.83 / 0.67) and 0.27 deg (NEES/dof 3.7), 0.05 to 1 / 0.82 / 0.66 and 0.26 deg "
        "(2.9); on point tracks chang_inertia (moments 0.29 from the sphere) converges from "
        "0.05 to 0.3 (docs/results/consistency.md)",
    )

    @field_validator("inertia_sigma")
    @classmethod
    def _inertia_sigma(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and not (np.isfinite(v) and v > 0):
            raise ValueError("inertia_sigma: finite and > 0, or 'auto'")
        return v

    inertia_asymmetry: float = Field(
        0.3,
        ge=0,
        description="RMS over the axes of |I_j - I_k| / I_i of the unknown target (<= 1 for "
        "any body; 0.3: moments that differ by tens of percent). With inertia 'sphere': the "
        "unmodelled Euler term has per-axis RMS ~ k |omega|^2 / 3 and correlation time "
        "~ 1/|omega|, so the rate random walk gets the spectral density "
        "2 k^2 |omega_TI|^3 / 27 (rad^2/s^3), from the current rate estimate",
    )
    rate_noise_rad2_s3: float | None = Field(
        None,
        ge=0,
        description="rate random-walk spectral density of the disturbance torque (rad^2/s^3, "
        "per axis of That; added to the Euler term of inertia 'sphere'). None (default): "
        "derived from the scenario's process_noise.rotational_rad2_s4 q_r (about the axis of "
        "largest moment): q_r times the mean over the axes of (I_max/I_i)^2, i.e. (1 + "
        "inertia_asymmetry)^2 with inertia 'sphere', from inertia_kg_m2 with 'given', from "
        "the current estimate with 'estimated'",
    )
    accel_noise_m2_s3: float | None = Field(
        None,
        ge=0,
        description="white-acceleration spectral density of the CW model (m^2/s^3). None "
        "(default): the scenario's process_noise.translational_m2_s4",
    )
    use_rate_velocity: bool = Field(
        False,
        description="also use the rate (eq. 29) and centroid velocity (eq. 30) measurements of "
        "eq. 32. Off by default (tumblenav's; Chang 2021 uses them): they are differences of "
        "the same pixels whose positions the attitude and position measurements of epochs k "
        "and k-1 already use (v_k = (p_k - p_k-1)/dt to first order), so they add no "
        "information and their noise is correlated with those measurements; taken as white "
        "they count the pixels twice (measured, chang2021_close point tracks, 3 runs: NEES/dof "
        "247 with them, 33 without; attitude and rate errors smaller without)",
    )
    mass_centre: Literal["consider", "estimated"] = Field(
        "consider",
        description="the mass centre about the feature map (offset b): 'consider' keeps the "
        "start's value (Chang's fixed registration, eq. 30) and carries its uncertainty as a "
        "Schmidt state; 'estimated' updates it (beyond the paper)",
    )
    reference: Literal["centroid", "feature"] = Field(
        "centroid",
        description="origin of the q-method's difference vectors (eq. 27): 'feature' is "
        "Chang's reference feature (its noise enters every difference vector); 'centroid' "
        "the weighted centroid of the matched features (a virtual reference feature, the "
        "noise of the reference averaged over all of them)",
    )
    register_frames: int = Field(
        5,
        ge=1,
        description="a feature's position about the mass centre r_i (eq. 30) is the mean of "
        "its first register_frames observations mapped with the current estimate",
    )
    prior_mass_centre_sigma_m: float = Field(
        0.5,
        gt=0,
        description="start: 1-sigma prior of the mass centre about the centroid of the first "
        "frame's features (m; the target's size scale): it regularises the directions the "
        "start window's rotation does not observe (along the rotation axis)",
    )
    feature_gate_probability: float = Field(
        0.9999,
        gt=0,
        lt=1,
        description="chi-square (3 dof) gate on each feature's q-method residual: outlier "
        "matches are dropped and counted as outlier_features. Tracks stated more precise "
        "after their first sighting use template_gate_probability instead",
    )
    slip_probability: float | None = Field(
        0.9999,
        gt=0,
        lt=1,
        description="with map 'state': per-track slip test (tumblenav's; Chang 2021 has none; "
        "slam.slip_test): a track whose displacement since the last epoch departs from the "
        "filter's prediction by more than this chi-square (3 dof) quantile of the epoch's "
        "own tracks (scale estimated robustly) has slipped to another surface point and is "
        "re-anchored (its map point dropped and re-initialised from the current frame) "
        "instead of pulling the pose. None: off. Measured on chang2021_close rendered "
        "images (seeds 0-1, window 40-120 s): NEES/dof per block attitude / rate / "
        "position / velocity / all 13.1 / 0.19 / 10.1 / 3.8 / 6.7 off, 1.8 / 0.08 / 3.8 / "
        "2.1 / 2.1 at 0.9999 (1.7 / 0.08 / 3.5 / 2.1 / 2.0 at 0.999), attitude RMS per axis "
        "0.26-0.39 / 0.24-0.31 / 0.12-0.17 deg off, 0.08-0.09 / 0.13-0.19 / 0.06-0.13 on; "
        "~12 % of the track-epochs re-anchored (the tracks' heavy-tailed slips and the "
        "first sightings' depth outliers). Tracks stated more precise after their first "
        "sighting use template_slip_probability instead",
    )
    template_slip_probability: float | None = Field(
        0.99,
        gt=0,
        lt=1,
        description="the slip test's quantile for tracks whose sightings after the first are "
        "stated more precise than a new corner (track_noise_px below noise_px: a template "
        "tracker, as the image front end with its affine refinement); None: "
        "slip_probability for these too (eighteenth session, issue 18). Why: such a tracker "
        "holds a track to a few hundredths of a pixel, and a slip of a few tenths is common "
        "at that scale (chang2021_close run 0: a tracked sighting scatters ~0.04 / 0.06 px "
        "about its track's best rigid point under the true poses, and half of the long "
        "tracks leave it by more than 0.3 px at some time; "
        "docs/results/consistency/prototype/chang_far_tracks.py). Cached runs 0-3 (window "
        "40-120 s), NEES/dof / NIS / attitude RMSE: 0.81 / 0.19 / 0.040 deg at 0.9999 with "
        "the tracked noise 0.15 px, 0.96 / 0.36 / 0.026 deg at 0.99 with 0.08 px (the front "
        "end's default then; 0.06 px since the nineteenth session). On point tracks, whose sightings are all alike, 0.99 costs "
        "accuracy (20 runs: attitude RMSE chang_paper 0.055 -> 0.075 deg, chang_features40 "
        "0.068 -> 0.148: good tracks re-anchored), so slip_probability stays there",
    )
    template_gate_probability: float | None = Field(
        0.99,
        gt=0,
        lt=1,
        description="feature_gate_probability for tracks whose sightings after the first are "
        "stated more precise than a new corner (as template_slip_probability; None: "
        "feature_gate_probability for these too; nineteenth session, issue 18). Why: a "
        "template track that slips by a few tenths of a pixel, which the slip test misses "
        "between two epochs, stands out against the feature's predicted position and its "
        "few-hundredths-pixel noise. chang2021_close rendered images, cached runs 0-7 "
        "(window 40-120 s), with the front end's tracked noise 0.06 px: NEES/dof 1.00, NIS "
        "0.46, attitude RMSE 0.020 deg (at 0.9999: see the front end's track_noise_px). On "
        "point tracks 0.99 is over-confident (chang_paper runs 0-5: NEES/dof 1.03 -> 1.14: "
        "good features dropped), so feature_gate_probability stays there",
    )
    gate_probability: float = Field(
        0.9999,
        gt=0,
        lt=1,
        description="chi-square (3 dof) NIS gate on each of the four measurements (attitude, "
        "rate, position, velocity); rejections are counted as gated_out",
    )
    epoch_attitude_warn_deg: float = Field(
        5.0,
        gt=0,
        description="the run says (info['warnings'], summary.json) when one epoch's features "
        "fix the attitude worse than this (deg, 1-sigma about the axes across the line of "
        "sight, qmethod.epoch_attitude_sigma, median over the start window): the map and the "
        "filter are linearised about an estimate that each epoch moves by more than a few "
        "degrees, and the covariance no longer covers the drift; the truth-free divergence "
        "check cannot see it either (its raw increments are as noisy). Measured (tumblenav's; "
        "run 0): chang_paper point tracks ~10 m 0.49 deg, chang_features40 1.0 deg, "
        "chang_range20 ~20 m 2.0 deg (NEES/dof 3.05, 0.15 deg accurate), chang2021 at 59 m: "
        "point tracks 17-18 deg (diverge; the check says so), images 14.8 deg (the attitude "
        "drifts to 50 deg with a 3-sigma of 3-6 deg and no check fails: "
        "docs/results/consistency.md)",
    )
    noise_at: Literal["predicted", "measured"] = Field(
        "predicted",
        description="map: state: where each triangulated feature's covariance is evaluated in "
        "the update: 'predicted' (tumblenav default, issue 18) at the filter's predicted point "
        "r + R_LThat s_i, 'measured' at the triangulated point. The triangulation covariance "
        "grows as the depth^4, so weights taken at the measured points lean to the points "
        "measured too near and bias the mass centre towards the camera (~ -4 sigma_depth^2 / "
        "depth; measurements.point_covariance). The batch start (start_fit: batch) weights "
        "point tracks' sightings the same way (nineteenth session: at Chang's printed 59 m on point "
        "tracks, runs 0-7, its measured-point weights had left the start's mass centre "
        "over-confident and the velocity took up the correction, block NEES/dof 7.35 -> 0.49)",
    )
    measurement_noise_scale: float = Field(
        1.0,
        gt=0,
        description="multiplier on every first-order measurement covariance (1: as derived)",
    )

    @field_validator("inertia_kg_m2")
    @classmethod
    def _inertia(cls, v: list[float] | list[list[float]]) -> list[float] | list[list[float]]:
        a = np.asarray(v, dtype=float)
        I = np.diag(a) if a.shape == (3,) else a
        if I.shape != (3, 3) or not np.allclose(I, I.T):
            raise ValueError("three principal moments or a symmetric 3x3 tensor (kg m^2)")
        if not np.linalg.eigvalsh(I)[0] > 0:
            raise ValueError("must be positive definite")
        return v

    def inertia_matrix(self) -> Array:
        """The dynamics' inertia (3, 3): identity for 'sphere' (and the start of
        'estimated')."""
        if self.inertia != "given":
            return np.eye(3)
        a = np.asarray(self.inertia_kg_m2, dtype=float)
        I = np.diag(a) if a.ndim == 1 else a
        return I / np.trace(I) * 3.0
