"""Yu 2019 ekf-depth settings (:class:`DepthTuning`) and the rules behind their defaults."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from tumblenav.estimators.base import nest_front_end_keys
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
        0.01, gt=0, description="initial 1-sigma of the rate (rad/s); the filter starts at rate 0"
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
    Q_diag: float = Field(1e-12, ge=0, description="process noise of the 6 disturbances")
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
        4.0,
        gt=0,
        description="variance multiplier on each fix's first-order centroid covariance: the "
        "centroid errors of a ray-cast scan are about 2x that variance across the short side "
        "(0.03x along the long side, 1.1x along the normal) and correlated from scan to scan "
        "(lag-1 0.5-0.8 at 1 Hz); 4 makes the translation consistent on the yu2019 runs "
        "(docs/results/yu2019.md)",
    )
    attitude_noise_scale: float = Field(
        1.5,
        gt=0,
        description="variance multiplier on each fix's first-order attitude covariance "
        "(measured 0.6, 1.7 and 0.02x that variance about the three axes, uncorrelated)",
    )
    consider_unexcited_ratios: bool = Field(
        True,
        description="Schmidt (consider) update for the inertia ratios whose effect on the "
        "dynamics the rate's own noise could produce (a spin about a principal axis): beyond "
        "Yu 2019, the EKF otherwise gains spurious information on them",
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


def plane_threshold(tun: DepthTuning, range_noise_m: float) -> float:
    """Inlier distance (m) of the RANSAC plane fits (:meth:`PlanesTuning.threshold`)."""
    return tun.frontend.threshold(range_noise_m)
