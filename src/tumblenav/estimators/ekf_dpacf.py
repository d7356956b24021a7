"""Former home of the Hu 2024 estimators (ekf-dpacf, ekf-baseline): they live in the package
:mod:`tumblenav.estimators.hu2024` now (tuning, model, init, frame, update, filter,
kernels). This module re-exports their names for existing scripts."""

# ruff: noqa: F401

from tumblenav.estimators.hu2024 import HuEKF
from tumblenav.estimators.hu2024.filter import (
    ENGINE,
    HuMemo,
    HuSteps,
    _run_view,
    filter_view,
    frontend,
    histories,
    run_filter,
)
from tumblenav.estimators.hu2024.frame import (
    P_TURN_MIN,
    _chol3,
    _follow_dpacf_branch,
    _reframe,
    _turn_moments,
    _turn_state,
    branch_mixture_cov,
    frame_consider_cov,
    frame_jacobian,
)
from tumblenav.estimators.hu2024.init import (
    _Init,
    _initial_state,
    _R_LI_at,
    _rotation_window,
    features_from_rotation,
    mass_centre_from_rotation,
    mass_centre_prior,
    refine_start_pose,
)
from tumblenav.estimators.hu2024.model import (
    _FLIPS,
    CONSTRAIN_EVERY,
    MAX_RATE_RAD_S,
    _diverged,
    _neutral_state,
    _translation_discrete,
    constrain_inertia,
    core_F,
    core_Qc,
    curvature_variance,
    euler_ratios_rhs,
    feature_measurement,
    inertia_constraint,
    layout,
    noise_gain,
    project_inertia,
    propagate_rotation,
)
from tumblenav.estimators.hu2024.tuning import (
    BaselineTuning,
    HuTuning,
    parse_tuning,
)
from tumblenav.estimators.hu2024.update import (
    _feature_cols,
    _inv3,
    _update,
    _update_sequential,
    frame_measurement,
)
