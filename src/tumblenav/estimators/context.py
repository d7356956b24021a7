"""What an estimator may know: the mission's side of a scenario, never the target's truth.

An estimator receives measurements and an :class:`EstimatorContext`: the sensor's calibration
and noise model, the chaser's own orbit and attitude law, the process noise the filters assume,
the estimator's settings (where priors a user or a paper assumes live, named: e.g. Kabir 2025's
known mass centre ``mass_centre_L_m``), and, as a named assumption, the target's geometry model
(Yu 2019 recognises the target's rectangles from a known model). The target's motion, inertia,
features and relative state are not in it: the same measurements under a scenario whose target
truth differs give the same estimates (tests/test_truth_free.py).

The fields carry the names of the scenario's sections (``context.sensor``,
``context.estimator.tuning``, ...), so estimator code reads the same with either, and reading
``context.target`` fails loudly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["EstimatorContext", "context_from_scenario"]


@dataclass(frozen=True)
class EstimatorContext:
    """The mission knowledge handed to an estimator (see the module docstring).

    name : str -- the scenario's (or data set's) name, for messages.
    sensor -- calibration and noise model (the scenario's ``sensor`` section).
    chaser -- the chaser's own orbit (or none: inertially fixed) and attitude law.
    process_noise -- the process noise the filters assume (a filter setting, not the truth).
    estimator -- the estimator's name and ``tuning`` (its settings and named priors).
    target_model -- the target's geometry model settings (a known CAD model), or None.
    """

    name: str
    sensor: Any
    chaser: Any
    process_noise: Any
    estimator: Any
    target_model: Any = None


def context_from_scenario(scenario: Any) -> EstimatorContext:
    """The mission's side of ``scenario``: everything but the target's truth."""
    if isinstance(scenario, EstimatorContext):
        return scenario
    target = getattr(scenario, "target", None)
    return EstimatorContext(
        name=scenario.name,
        sensor=scenario.sensor,
        chaser=scenario.chaser,
        process_noise=scenario.process_noise,
        estimator=scenario.estimator,
        target_model=getattr(target, "model", None),
    )
