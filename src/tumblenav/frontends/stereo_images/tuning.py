"""Settings of the image front end (Chang 2021 Sec. 2.3-2.4 and 3.3): :class:`ImageFrontEndTuning`.

Chang 2021 gives almost none of these numbers (notes sec. 1.9): every default the paper does not
state is ours and marked ``# tumblenav default (Chang 2021 silent)``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["DEFAULT_TUNING", "ImageFrontEndTuning"]

LK_SLIDE_PX2_PER_FRAME = 0.006  # LK alone: track_slide_px2_per_frame's description
REFINED_TRACK_NOISE_PX = 0.06  # the affine refinements: track_noise_px's description


class ImageFrontEndTuning(BaseModel):
    """Settings of the stereo-image front end: FAST corners, pyramidal LK tracking of the left
    image, left -> right matching along the calibrated rig's epipolar line, and Chang 2021's
    feature management (IDs, survival time, n_min / n_max, maximum age)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # --- detection (Chang 2021 Sec. 2.3: FAST segment test, ranked by response) ---
    fast_threshold: int = Field(
        20,  # tumblenav default (Chang 2021 silent)
        ge=1,
        le=254,
        description="FAST intensity threshold (grey levels) of OpenCV's TYPE_9_16 segment test, "
        "with non-maximum suppression",
    )
    response: Literal["opencv", "sad"] = Field(
        "sad",
        description="corner ranking: 'sad' is Chang 2021's response (sum of absolute "
        "differences between the centre pixel and its 16 circle neighbours); 'opencv' is "
        "OpenCV's FAST score (KeyPoint.response)",
    )
    mask_px: int = Field(
        5,  # Chang 2021 Sec. 2.4: a 5 x 5 pixel mask around each existing feature
        ge=1,
        description="side (px) of the square around each existing feature (and each new corner "
        "taken) inside which no new corner is accepted",
    )
    border_px: int = Field(
        8,  # tumblenav default (Chang 2021 silent)
        ge=0,
        description="new corners closer than this (px) to the image border are ignored (the "
        "match patch must fit in the image)",
    )

    # --- feature management (Chang 2021 Sec. 2.4, Figs. 6-7) ---
    n_min: int = Field(
        120,  # Chang 2021 Sec. 3.3 keeps 120 features; n_min itself is not given
        ge=0,
        description="features wanted: each frame fills the vacancy n_min - m with the best new "
        "matched corners (Chang 2021 Sec. 2.4)",
    )
    n_max: int = Field(
        120,  # Chang 2021 Sec. 3.3: 120 features are maintained
        ge=1,
        description="most features kept: above it the (m - n_max) most-tracked ones are "
        "removed (Chang 2021 Sec. 2.4)",
    )
    max_age_frames: int = Field(
        60,  # tumblenav default (Chang 2021 silent); see the description
        ge=1,
        description="a feature is dropped once it has been tracked in more than this many "
        "frames (its survival time, counting the first; Chang 2021 Sec. 2.4 caps the age but "
        "gives no number). 60 frames (6 s at 10 Hz, ~30 deg of Chang's tumble) rather than "
        "the notes' 30: half the feature IDs and twice the track length for the estimators, "
        "the fewest match outliers of 30/60/100, and an LK drift (~0.02 px per frame, from "
        "the translational LK model on a rotating patch) of about 1 px at 60 frames, i.e. "
        "under 6 mm on the target at 3-10 m (benchmarks/image_frontend.py)",
    )

    # --- pyramidal Lucas-Kanade, left image k-1 -> k (Chang 2021 Fig. 5) ---
    lk_window_px: int = Field(
        5,  # tumblenav default (Chang 2021 silent); measured, see the description
        ge=3,
        description="side (px) of the LK integration window. 5 (was OpenCV's 21): the "
        "translational LK model tracks a rotating patch's texture, not its centre, so a track "
        "slides over the surface, linearly with its age and in part coherently (it reads as a "
        "rate error). Measured on chang2021_close rendered images (5 Hz, 1 deg of tumble per "
        "frame, run 0, against the renderer's surface point under the first corner): lateral "
        "drift at age 30 / 59 frames 1.2 / 3.4 px with 21, 0.59 / 2.1 px with 11, 0.52 / 1.2 "
        "px with 7, 0.50 / 0.80 px with 5; ekf-pose attitude RMS per axis 4.2/0.73/1.7 deg "
        "(21), 1.1/0.29/0.30 (11), 0.58/0.23/0.14 (7), 0.36/0.31/0.41 (5); over runs 0-3, "
        "0.53/0.38/0.43 (7) and 0.33/0.34/0.27 (5). The pyramid (lk_levels) still takes the "
        "large motions; tests/test_image_frontend.py and the fault-injection tests pass",
    )
    lk_levels: int = Field(
        3,  # tumblenav default (Chang 2021 silent)
        ge=0,
        description="pyramid levels above the full-resolution image (OpenCV maxLevel)",
    )
    lk_max_iterations: int = Field(
        30,  # tumblenav default (Chang 2021 silent)
        ge=1,
        description="LK termination: most iterations per pyramid level",
    )
    lk_epsilon_px: float = Field(
        0.01,  # tumblenav default (Chang 2021 silent)
        gt=0,
        description="LK termination: smallest update (px)",
    )
    lk_min_eigen: float = Field(
        1e-4,  # tumblenav default (Chang 2021 silent): OpenCV's default
        gt=0,
        description="LK minEigThreshold: points whose normalised gradient matrix has a smaller "
        "eigenvalue are lost (flat regions, black frames)",
    )
    fb_max_px: float = Field(
        0.5,  # tumblenav default (Chang 2021 silent)
        gt=0,
        description="forward-backward check: a track k-1 -> k -> k-1 must come back within "
        "this distance (px) of where it started",
    )

    # --- left -> right matching along the epipolar line (Chang 2021 Sec. 2.3) ---
    patch_px: int = Field(
        11,  # tumblenav default (Chang 2021 silent: no similarity measure is given)
        ge=3,
        description="side (px, odd) of the square patch compared by normalised "
        "cross-correlation; it is sampled along the epipolar direction in both images",
    )
    ncc_min: float = Field(
        0.8,  # tumblenav default (Chang 2021 silent)
        gt=-1.0,
        le=1.0,
        description="lowest accepted normalised cross-correlation of a match",
    )
    ncc_unique_margin: float = Field(
        0.02,  # tumblenav default (Chang 2021 silent)
        ge=0.0,
        description="a match searched along the whole epipolar segment is refused when "
        "another peak (more than one patch away) scores within this margin of the best "
        "(repetitive texture, Chang 2021's motivation for the epipolar constraint)",
    )
    min_patch_std: float = Field(
        2.0,  # tumblenav default (Chang 2021 silent)
        ge=0.0,
        description="a left patch whose grey-level standard deviation is below this is not "
        "matched (no texture: black frames, saturated regions)",
    )
    epipolar_tol_px: float = Field(
        1.0,  # tumblenav default (Chang 2021 silent)
        gt=0,
        description="largest distance (px) of the refined right pixel from the epipolar line "
        "of the left pixel (known F of the calibrated rig)",
    )
    lk_refine: bool = Field(
        False,  # tumblenav default (Chang 2021 silent): measured worse than the parabola
        description="refine the NCC match (parabola peak along the epipolar line) with one "
        "full-resolution LK step from the left to the right image (OPTFLOW_USE_INITIAL_FLOW); "
        "a refinement that fails, moves by more than epipolar_tol_px or leaves the epipolar "
        "band is ignored (the NCC match is kept). Off by default: on the synthetic planes of "
        "tests/test_image_frontend.py it doubled the median error of the convergent rig",
    )
    # --- affine template refinement (tumblenav's, beyond Chang 2021; stereo_images.refine) ---
    template_refine: bool = Field(
        True,  # tumblenav's (beyond Chang 2021); measured, see the description
        description="refine each LK-tracked left pixel by an affine ECC warp of the patch at "
        "the feature's first sighting (never replaced, so the track does not slide over the "
        "surface); a track whose refinement fails (no convergence, score below "
        "template_min_cc, or a move over template_max_shift_px) ends there. Measured "
        "(benchmarks/image_frontend.py --ranges-m 9, 130 pairs, the text rig): the left pixel "
        "against the surface point it started on, median 0.16 / 0.18 / 0.30 / 0.53 px at age "
        "2 / 10 / 30 / 60 frames with LK alone, 0.11 / 0.07 / 0.06 / 0.05 px refined",
    )
    affine_match_refine: bool = Field(
        True,  # tumblenav's (beyond Chang 2021); measured, see the description
        description="refine each right match by an affine ECC warp of the left patch of the "
        "same frame (the NCC peak is biased along the epipolar line where the two views of a "
        "slanted patch differ, the same way at every frame of a track); refused (the NCC match "
        "kept) when it fails, scores below template_min_cc, moves more than epipolar_tol_px or "
        "leaves the epipolar band. On chang2021_close run 0 (rendered), each track's mean "
        "depth error against the renderer's surface point: robust sigma 1.54 -> 0.32 "
        "px-equivalent",
    )
    template_px: int = Field(
        15,  # tumblenav's: a patch large enough for six affine parameters
        ge=5,
        description="side (px, odd) of the patches the affine refinements warp",
    )
    template_min_cc: float = Field(
        0.7,  # tumblenav's
        gt=-1.0,
        le=1.0,
        description="lowest accepted ECC score (a correlation coefficient) of a refinement",
    )
    template_max_shift_px: float = Field(
        2.0,  # tumblenav's
        gt=0,
        description="largest move (px) of a left refinement from the LK pixel",
    )
    min_depth_m: float = Field(
        1.0,  # tumblenav default (Chang 2021 silent)
        gt=0,
        description="nearest depth (m, along the left optical axis) searched for a new "
        "feature's match",
    )
    max_depth_m: float | None = Field(
        None,  # tumblenav default (Chang 2021 silent): up to the vanishing point
        gt=0,
        description="farthest depth (m) searched for a new feature's match (none: up to the "
        "vanishing point of the left ray in the right image)",
    )
    track_search_px: int = Field(
        12,  # tumblenav default (Chang 2021 silent)
        ge=2,
        description="a tracked feature is searched for in the right image this far (px) either "
        "side of where its previous depth puts it on the new epipolar line",
    )

    track_slide_px2_per_frame: float | None = Field(
        None,  # tumblenav's, measured (Chang 2021 silent); see the description
        ge=0.0,
        description="what the front end states of its tracks' slide over the surface, as a "
        "random walk across the line of sight (px^2 per frame, each of u and v; the tracks' "
        "slide_px2_per_frame): ekf-pose lets each map point walk by it "
        "(slam.StateSteps.map_walk). None (the default): 0 with template_refine (the tracks "
        "hold their first-sighting patch and do not slide: the left pixel against the surface "
        "point it started on stays at a median 0.05-0.11 px from age 2 to 60 frames, "
        "benchmarks/image_frontend.py --ranges-m 9), else 0.006, measured for LK alone on chang2021_close rendered images (5 Hz, 1 deg "
        "of tumble per frame, lk_window_px 5, runs 0-1 of the campaign's seeds; each track's "
        "triangulated point in T against its first sighting, truth poses, in px of the left "
        "camera's x / z; a session script, 2026-11-25): robust sigma 0.272 / 0.138 px at age "
        "1, 0.394 / 0.229 at 10, 0.559 / 0.320 at 20, 0.763 / 0.414 at 30, 1.147 / 0.753 at 58 "
        "frames; the variance's growth over the first ten frames, 0.0090 / 0.0037 px^2 per "
        "frame, averaged over the two axes. Later the slide runs faster than a walk (0.022 / "
        "0.0096 px^2 per frame up to age 58): the front end's max_age_frames bounds it. It "
        "grows with the tumble per frame: the same scene at 10 / 5 / 2.5 Hz (0.5 / 1 / 2 deg "
        "per frame) gives 0.0010 / 0.0064 / 0.0115, and at 2.5 Hz ekf-pose's NEES/dof (runs "
        "0-3) is 1.23 with 0.006 and 0.92 with 0.0115. Set it for your frame rate and "
        "tumble: python benchmarks/image_track_slide.py SCENARIO prints it from a simulated "
        "scenario's tracks against its truth. 0: the tracks are taken as white noise about "
        "fixed surface points",
    )
    track_noise_px: float | None = Field(
        None,  # tumblenav's, measured (Chang 2021 silent); see the description
        gt=0.0,
        description="what the front end states of the noise of a track's sightings after its "
        "first (px, each of u and v; the tracks' track_noise_px; the first sighting keeps the "
        "sensor's noise, sensor.noise). ekf-pose weights its updates by it. None (the "
        "default): 0.06 px with template_refine and affine_match_refine (the sensor's noise "
        "where that is smaller), else the sensor's noise. Measured on chang2021_close rendered images (run 0, against the renderer's "
        "surface point under each track's first corner): robust sigma of a sighting's error "
        "about its track's mean 0.09 / 0.06 px across the line of sight and 0.54 "
        "px-equivalent in depth, of the tracks' means 0.07 / 0.07 / 0.32, with heavy tails "
        "(RMS 2 px: slips, which ekf-pose's slip test re-anchors). 0.15 px is what ekf-pose "
        "needs rather than the scatter: on the cached tracks of runs 0-3, 17 and 19 (window "
        "40-120 s) with its batch start, NEES/dof 0.95 at 0.15 px (NIS 0.19), 1.16 at 0.125 "
        "(NIS 0.27), 0.5 at 0.25; with the replay start (sixteenth session) 0.25 px was "
        "needed, the start leaving the mass centre's error along the rotation axis in runs 17 "
        "and 19 (NEES/dof 3.2 and 4.7 there at 0.25 px; docs/results/consistency.md, "
        "Chang section). 0.08 px since the eighteenth session, with ekf-pose's slip test at "
        "0.99 for such tracks (template_slip_probability): against each track's best rigid point under the true "
        "poses, a tracked sighting scatters ~0.04 / 0.06 px (left / right, robust, white "
        "from frame to frame) with slips beyond 0.3 px in half the long tracks, which the "
        "tighter slip test re-anchors; cached runs 0-3: NEES/dof 0.96, NIS 0.36, attitude "
        "0.026 deg at 0.08 px (1.27 / 0.57 / 0.024 at 0.06, 0.78 / 0.25 / 0.028 at 0.1, "
        "0.44 / 0.11 / 0.028 at 0.15). 0.06 px since the nineteenth session, with ekf-pose's "
        "feature gate at 0.99 for such tracks too (template_gate_probability): cached runs "
        "0-7, NEES/dof 1.00, NIS 0.46, attitude 0.020 deg (0.80 / 0.32 / 0.021 at 0.08). At 59 m (the built-in chang2021) the sightings "
        "scatter 0.17 px and are correlated from frame to frame: that scenario states 0.15 "
        "px (docs/results/consistency/prototype/chang_far_tracks.py)",
    )

    def slide_px2(self) -> float:
        """The slide stated for the tracks (``track_slide_px2_per_frame`` or its default)."""
        if self.track_slide_px2_per_frame is not None:
            return float(self.track_slide_px2_per_frame)
        return 0.0 if self.template_refine else LK_SLIDE_PX2_PER_FRAME

    def tracked_noise_px(self, first_px: float) -> float | None:
        """The noise stated for the tracked sightings: ``track_noise_px``, or by default
        REFINED_TRACK_NOISE_PX with both refinements where that is below the first sightings'
        ``first_px`` (a tracked feature is held at least as well as it was found); None: the
        first sightings' noise."""
        if self.track_noise_px is not None:
            return float(self.track_noise_px)
        refined = self.template_refine and self.affine_match_refine
        return REFINED_TRACK_NOISE_PX if refined and REFINED_TRACK_NOISE_PX < first_px else None

    @model_validator(mode="after")
    def _consistent(self) -> ImageFrontEndTuning:
        if self.n_min > self.n_max:
            raise ValueError(f"n_min ({self.n_min}) must not exceed n_max ({self.n_max})")
        if self.patch_px % 2 == 0:
            raise ValueError(f"patch_px must be odd, got {self.patch_px}")
        if self.lk_window_px % 2 == 0:
            raise ValueError(f"lk_window_px must be odd, got {self.lk_window_px}")
        if self.template_px % 2 == 0:
            raise ValueError(f"template_px must be odd, got {self.template_px}")
        if self.max_depth_m is not None and not self.max_depth_m > self.min_depth_m:
            raise ValueError("max_depth_m must exceed min_depth_m")
        return self


DEFAULT_TUNING = ImageFrontEndTuning()  # the defaults (frozen), for argument defaults
