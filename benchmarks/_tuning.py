"""Shared by the Hu 2024 benchmarks: ``--set key=value`` overrides of ``estimator.tuning``."""

from __future__ import annotations

import yaml


def with_tuning(scenario, sets: list[str], **updates):
    """``scenario`` with ``estimator.tuning`` updated by ``key=value`` strings (values read as
    YAML: ``null``, ``false``, ``1e-8``) and any further ``with_updates`` keys."""
    tuning = dict(scenario.estimator.tuning)
    for kv in sets:
        key, value = kv.split("=", 1)
        tuning[key] = yaml.safe_load(value)
    return scenario.with_updates(**{"estimator.tuning": tuning, **updates})
