"""Kabir 2025 UKF settings (:class:`KabirTuning`) and the paper's per-frequency tuning (Sec. 3.2)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from tumblenav.errors import InputError
from tumblenav.estimators.base import nest_front_end_keys
from tumblenav.estimators.base import parse_tuning as base_parse_tuning
from tumblenav.frontends.projections import ProjectionsTuning
from tumblenav.settings_rules import positive_or_rule

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


# Kabir 2025 Sec. 3.2, per tumbling frequency f_T (Hz): Q of omega (rad^2/s^2), Q of each
# quaternion component, and sigma_o of the optical flow (rad/s).
_PAPER_PER_FREQUENCY = {
    0.025: (2.5e-9, 4e-10, 1e-5),
    0.075: (2.5e-7, 4e-8, 5e-4),
    0.125: (2.5e-5, 4e-6, 5e-4),
    0.175: (2.5e-5, 4e-6, 1e-3),
}


class KabirTuning(BaseModel):
    """``estimator.tuning`` keys of ukf / ukf-mult (defaults: Kabir 2025 Sec. 3.2 for
    f_T = 0.025 Hz; use :func:`paper_tuning` for the other frequencies). The known mass
    centre, ``mass_centre_L_m``, is required: Kabir 2025 assumes it."""

    model_config = ConfigDict(extra="forbid")
    mass_centre_L_m: list[float] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="the target's mass-centre position at t = 0 in L (= I), m: Kabir 2025 "
        "Sec. 2.1 assumes it known; required (the estimator never reads the target's truth)",
    )
    mass_centre_velocity_L_m_s: list[float] = Field(
        [0.0, 0.0, 0.0],
        min_length=3,
        max_length=3,
        description="its constant velocity in L, m/s (Kabir 2025: an inertially fixed CM)",
    )
    init: Literal["triangulated", "given"] = Field(
        "triangulated",
        description="'triangulated': from the first epochs' measurements alone (q = identity, "
        "features triangulated, omega from the optical flow, k = 0); 'given': init_omega_rad_s, "
        "init_q_TI, init_features_m (the kabir2025 recipe gives Kabir 2025 Sec. 3.2's "
        "truth-based guess this way: tumblenav.papers.kabir2025.paper_start)",
    )
    init_omega_rad_s: list[float] = Field(
        [0.0, 0.0, 0.0], min_length=3, max_length=3, description="given init: omega_TI_T"
    )
    init_q_TI: list[float] = Field(
        [0.0, 0.0, 0.0, 1.0], min_length=4, max_length=4, description="given init: [x,y,z,w]"
    )
    init_features_m: list[list[float]] = Field(
        [], description="given init: each feature's position in T, m (one [x, y, z] each)"
    )
    alpha: float = Field(0.1, gt=0, le=1, description="unscented spread (Sec. 3.2)")
    beta: float = Field(2.0, ge=0, description="unscented transform (Sec. 3.2)")
    kappa: float = Field(0.0, description="unscented transform (Sec. 3.2)")
    p0_omega_var: float = Field(0.1225, gt=0, description="rad^2/s^2")
    p0_quat_var: float = Field(0.04, gt=0, description="per quaternion component")
    p0_k_var: float = Field(0.01, gt=0, description="initial variance of each log-ratio k")
    p0_feature_var: float = Field(2.25, gt=0, description="m^2")
    q_omega_var: float = Field(2.5e-9, ge=0, description="rad^2/s^2 per step")
    q_quat_var: float = Field(4e-10, ge=0, description="per quaternion component per step")
    q_k_var: float = Field(3.6e-5, ge=0, description="per step")
    q_feature_var: float = Field(1e-6, ge=0, description="m^2 per step")
    sigma_p_rad: float | Literal["sensor"] = Field(
        "sensor",
        description="projection noise sigma_p (rad, Kabir 2025 eq. 24); 'sensor': the "
        "measurements' noise_px / focal_px (left camera)",
    )
    sigma_d_rad: float | Literal["sigma_p"] = Field(
        "sigma_p", description="disparity noise (rad); 'sigma_p': the same as sigma_p_rad"
    )
    sigma_flow_rad_s: float = Field(
        1e-5,
        gt=0,
        description="optical flow noise sigma_o; note that eq. 27's truncation error at 1 Hz "
        "is ~3e-3 to 6e-3 rad/s at Kabir's tumbling rates, far above the paper's sigma_o "
        "(docs/results/kabir2025.md)",
    )
    frontend: ProjectionsTuning = Field(
        default_factory=ProjectionsTuning,
        description="the projections front end's settings (ProjectionsTuning)",
    )
    gate_probability: float | None = Field(
        None, gt=0, lt=1, description="per-feature chi-square innovation gate; default: none"
    )

    @field_validator("sigma_p_rad", "sigma_d_rad", mode="before")
    @classmethod
    def _number_or_rule(cls, v: Any, info: ValidationInfo) -> Any:
        """A positive number, or the rule named by the default (``null``, the former default,
        means the rule too)."""
        assert info.field_name is not None  # a field validator's info names its field
        return positive_or_rule(v, cls.model_fields[info.field_name].default)

    @model_validator(mode="before")
    @classmethod
    def _front_end_keys(cls, raw: Any) -> Any:
        """Front-end keys given at the top level (as before they moved) go to ``frontend``."""
        return nest_front_end_keys(raw, ProjectionsTuning)


def parse_tuning(raw: dict[str, Any] | None, model: type[KabirTuning] = KabirTuning) -> KabirTuning:
    """Validate ``estimator.tuning``; InputError naming the key on unknown keys / bad values."""
    return base_parse_tuning(raw, model)


def paper_tuning(f_T_hz: float) -> dict[str, float]:
    """Kabir 2025 Sec. 3.2's per-frequency tuning: ``q_omega_var``, ``q_quat_var``,
    ``sigma_flow_rad_s`` for f_T in 0.025, 0.075, 0.125, 0.175 Hz."""
    for f, (qw, qq, so) in _PAPER_PER_FREQUENCY.items():
        if abs(f_T_hz - f) < 1e-6:
            return {"q_omega_var": qw, "q_quat_var": qq, "sigma_flow_rad_s": so}
    raise InputError(
        f"Kabir 2025 tunes only f_T = {', '.join(map(str, _PAPER_PER_FREQUENCY))} Hz; "
        f"got {f_T_hz:g} Hz"
    )
