"""Former home of Yu 2019's ekf-depth: it lives in the package
:mod:`tumblenav.estimators.yu2019` now (tuning, model, fixes, filter). This module re-exports
their names for existing scripts."""

# ruff: noqa: F401

from tumblenav.estimators.yu2019 import DepthEKF
from tumblenav.estimators.yu2019.filter import (
    DepthSteps,
)
from tumblenav.estimators.yu2019.fixes import (
    _only_model_symmetric,
    fix_covariance,
)
from tumblenav.estimators.yu2019.model import (
    _E,
    _E_ATT,
    _E_INERTIA,
    _E_OFFSET,
    _E_POS,
    _E_RATE,
    _E_ROT,
    _E_TRANS,
    _E_VEL,
    _P0,
    _X_ATT,
    _X_INERTIA,
    _X_OFFSET,
    _X_POS,
    _X_RATE,
    _X_TRANS,
    _X_VEL,
    LAYOUT,
    _inertia_columns,
    _initial_inertia,
    _propagate,
    _Qc_rot,
    euler_full,
    inertia_matrix,
    measurement,
    physical_inertia,
    rotational_F,
    unexcited_ratios,
)
from tumblenav.estimators.yu2019.tuning import (
    DepthTuning,
    _sigma_inertia,
    plane_threshold,
)
