"""Former home of ukf-gp (Kabir 2025): :mod:`tumblenav.estimators.kabir2025.ukf_gp` now; this module
re-exports its names for existing scripts."""

# ruff: noqa: F401

from tumblenav.estimators.kabir2025.ukf_gp import (
    KabirUKFGP,
    UKFGPTuning,
    _fit_one,
    _model_summary,
    pseudo_measurements,
    train_feature_models,
)
