"""The stereo-points front end's settings (the user's, :class:`StereoPointsTuning`, and the\ninternal :class:`FrontEndSettings`) and its output, :class:`PointsFrontEnd`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FrontEndSettings:
    rate_half_window: int = 10  # epochs on each side of the local rate fit
    min_ls_epochs: int = 20  # epochs of rate data before the inertia is trusted
    max_condition: float = 1e8  # of the column-scaled normal equations
    min_eigengap: float = 0.02  # relative gap between principal moments for a defined DPACF
    max_dpacf_sigma_rad: float = 0.05  # the DPACF frame is used once its 1-sigma error is below
    ls_every: int = 10  # epochs between least-squares solutions
    g_fit: str = "full"  # G attitude: "full" (points' covariances) or "kabsch" (isotropic)
    # refit the template over this much data after G's definition (seconds; one value or
    # several, each a refinement; 0 or empty: never)
    template_refine_s: float | tuple[float, ...] = 0.0
    # after the last refinement, the least squares' rows from the unbiased (cubic) rate fit
    unbiased_last: bool = True
    # ... and in every earlier version too (the rows of the first seconds, which the filter
    # starts from): the line fit's third-order bias is common to neighbouring rows and does
    # not average out (measured: the ratios' NEES/dof at the filter's start 15 -> 2.4)
    unbiased_early: bool = True
    # the disturbance torque the mission assumes (the scenario's process_noise
    # rotational_rad2_s4, rad^2/s^3: the angular acceleration's spectral density about the
    # largest moment's axis; tumblenav.dynamics.disturbances): the inertia least squares'
    # angular momentum random-walks (stereo_points.gls); 0: torque-free (Hu 2024 eq. 10)
    q_r: float = 0.0
    # the rates' noise in the inertia least squares' covariance (stereo_points.gls):
    # "white_attitudes": the moving-sum correlation of G attitude errors independent between
    # epochs (exact for them, verified by Monte Carlo; the rows' noise then nearly cancels
    # over long spans); "independent": each row's noise independent of the others', the
    # long-span variance of a row's own (measured on hu_big12: the rates' errors summed over
    # 20 s have 0.3-0.5 of it, from the template's slowly varying share of the G attitude
    # error, which the white model misses: frame NEES/dof 3-10 torque-free)
    rate_noise: str = "independent"


class StereoPointsTuning(BaseModel):
    """Settings of the stereo-points front end (Hu 2024 Sec. 2-3: triangulation, the
    photogrammetric frame G, the inertia least squares and the DPACF frame), under
    ``estimator.tuning.frontend`` of ekf-dpacf and ekf-baseline (the same keys at the top of
    ``estimator.tuning`` are still read, as before)."""

    model_config = ConfigDict(extra="forbid")
    rate_half_window: int = Field(
        10, ge=1, description="half-width (epochs) of the local fit that gives the rate of G"
    )
    min_ls_epochs: int = Field(
        50, ge=3, description="epochs of rate data needed before the inertia is trusted"
    )
    g_attitude_fit: Literal["full", "kabsch"] = Field(
        "full",
        description="G attitude per epoch: 'full' refines the Kabsch fit in the metric of the "
        "triangulated points' covariances (beyond the paper); 'kabsch' is the isotropic fit",
    )
    dpacf_emit_sigma_rad: float = Field(
        0.2,
        gt=0,
        description="the front end gives a DPACF frame (Hu 2024 Fig. 5, the filter's attitude "
        "measurement) once its 1-sigma is below this; the filter itself starts at "
        "max_dpacf_sigma_rad",
    )
    template_refine_s: float | list[float] = Field(
        [8.0, 10.0, 30.0],
        description="the front end refits its template (the features' G coordinates, from "
        "their first sighting) to all their views over this many seconds after G's "
        "definition, and computes G with it from then on (beyond the paper, "
        "stereo_points._refine_template); a list: a refinement at each (the early one "
        "brings the DPACF in within 10 s, the later one makes it precise); 0 or []: never "
        "(the first sighting's template throughout). Both estimators share the front end, so "
        "that they start on the same data",
    )
    ls_unbiased_rates: bool | Literal["last"] = Field(
        True,
        description="the inertia least squares takes the rates of the cubic (unbiased) fit "
        "at every epoch, in every version of the template's rows (beyond the paper): the "
        "line fit, chosen where its error is smaller epoch by epoch, has a third-order bias "
        "that is common to neighbouring rows and does not average out over the batch "
        "(inertia ratios 1.2e-3 -> 4e-5 off at 200 s, 2e-5 rad, "
        "benchmarks/hu2024_refinement_checks.py schedule; in the first seconds the ratios' "
        "error at the filter's start was 4 times their 1-sigma with the line, NEES/dof 15 "
        "-> 2.4 over 40 hu2024 runs); 'last': only from the template's last refinement on, "
        "past rows reprocessed (the default until issue 18); false: the per-epoch choice "
        "throughout",
    )

    ls_torque_rad2_s4: float | Literal["process_noise", "auto"] = Field(
        "auto",
        description="the disturbance torque the inertia least squares allows for "
        "(rad^2/s^3, the angular acceleration's spectral density about the largest "
        "moment's axis, as process_noise.rotational_rad2_s4): its angular momentum "
        "random-walks with it and the DPACF frame's covariance says so "
        "(stereo_points.gls); 'process_noise': the filter's sigma_r2 (by default the "
        "scenario's process_noise); 0: torque-free, Hu 2024 eq. 10 (the paper's least "
        "squares; with the paper's sigma_r2 = 2.5e-5 allowed for, the frame's 1-sigma stays "
        "above 0.2 rad over hu2024's 200 s: the torque hides the inertia); 'auto' (the "
        "default since issue 18's twenty-fifth session; 0 before): 'process_noise' where the "
        "scenario states that its process noise is a real disturbance "
        "(process_noise.disturb_truth), else 0. With 0 on a disturbed target the frame was "
        "over-confident (a scenario nobody tuned for: attitude block NEES/dof 28, whole "
        "state 4.8e4 over 20 runs; docs/results/consistency.md)",
    )

    @field_validator("ls_torque_rad2_s4")
    @classmethod
    def _torque(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and not (np.isfinite(v) and v >= 0):
            raise ValueError("ls_torque_rad2_s4: finite and >= 0, or 'process_noise'")
        return v

    @field_validator("template_refine_s")
    @classmethod
    def _refine_times(cls, v: float | list[float]) -> float | list[float]:
        if any(x < 0 or not np.isfinite(x) for x in np.atleast_1d(np.asarray(v, dtype=float))):
            raise ValueError("template_refine_s: times must be finite and >= 0 s")
        return v


@dataclass
class PointsFrontEnd:
    t: Array
    p_L: Array  # (B,n,N,3) m
    cov_L: Array  # (B,n,N,3,3) m^2
    usable: NDArray[np.bool_]  # (B,n,N)
    R_GI: Array  # (B,n,3,3)
    cov_G: Array  # (B,n,3,3) rad^2, G attitude error in G
    omega_G: Array  # (B,n,3) rad/s, rate of G wrt I in G
    var_omega: Array  # (B,n) rad^2/s^2, its variance per axis
    template_G: Array  # (B,N,3) m, feature coordinates in G
    known: NDArray[np.bool_]  # (B,N)
    known_at: NDArray[np.bool_]  # (B,n,N) catalogued in the template by epoch k
    R_GT: Array  # (B,n,3,3) DPACF principal frame (NaN until identified)
    moments: Array  # (B,n,3) principal moments / lambda_1
    q_TI: Array  # (B,n,4) DPACF attitude measurement
    cov_TI: Array  # (B,n,3,3) its covariance (frame part + G attitude noise)
    cov_frame: Array  # (B,n,3,3) the slowly varying part: error of the DPACF frame T in G
    cov_ratios: Array  # (B,n,3,3) covariance of the inertia ratios p (Hu 2024 eq. 19)
    skipped: dict[str, Array] = field(default_factory=dict)  # name -> (B,) counts
    # (B,n) the factor (>= 1) on the frame's sigma in the thresholds on it (the front end's
    # max_dpacf_sigma_rad, the filter's view): sqrt of the residuals' excess over the least
    # squares' noise model (inertia_ls._residual_scale); None: 1
    frame_gate: Array | None = None
    cov_omega: Array | None = None  # (B,n,3,3) rad^2/s^2, full covariance of omega_G
    # the template's refinements (template_refine_s): (from epoch (B,), template (B,N,3))
    # for each version in order, the first from epoch 0, the last being template_G (a
    # refinement's epoch is n in runs where it did not happen); None: never refined
    template_history: list[tuple[NDArray[np.int64], Array]] | None = None
    # (B,n,3,3) attitude of L in I per run and epoch; set by the caller that holds the
    # measurements (tumblenav.estimators.hu2024.filter.frontend), None until then
    R_LI: Array | None = None

    def template_at(self, k: int | NDArray[np.int64]) -> Array:
        """The template (B,N,3) as known at epoch ``k`` (scalar or per run): the latest
        version refined at or before ``k`` (causal use of the template)."""
        if self.template_history is None:
            return self.template_G
        out = self.template_history[0][1]
        for k_v, tmpl in self.template_history[1:]:
            now = np.broadcast_to(np.asarray(k) >= k_v, k_v.shape)
            out = np.where(now[:, None, None], tmpl, out)
        return out
