"""Former home of Kabir 2025's UKF (ukf, ukf-mult): it lives in the package
:mod:`tumblenav.estimators.kabir2025` now (tuning, model, observations, init, unscented,
filter). This module re-exports their names for existing scripts."""

# ruff: noqa: F401

from tumblenav.estimators.kabir2025 import KabirUKF
from tumblenav.estimators.kabir2025.filter import (
    _MAX_STATE,
    _MAX_VARIANCE,
    UKFSteps,
    _filter,
    _gate,
    _history,
    _sane,
    _skipped,
    _UKFModel,
    run_ukf,
)
from tumblenav.estimators.kabir2025.init import (
    _triangulated_start,
    initial_state,
)
from tumblenav.estimators.kabir2025.model import (
    KabirGeometry,
    _boxplus,
    _euler_coefficients,
    _filter_layout,
    _mass_centre,
    _process_noise,
    additive_to_error_cov,
    check_scenario,
    euler_rhs_k,
    geometry,
    layout,
    propagate_rotation,
    quat_cov_map,
)
from tumblenav.estimators.kabir2025.observations import (
    measurement_model,
    projection_sigmas,
    stereo_measurements,
)
from tumblenav.estimators.kabir2025.tuning import (
    _PAPER_PER_FREQUENCY,
    KabirTuning,
    paper_tuning,
    parse_tuning,
)
from tumblenav.estimators.kabir2025.unscented import (
    _sqrt_psd,
    _Unscented,
)
