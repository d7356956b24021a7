"""Settings whose default is a named rule (e.g. ``'range_noise'``: computed from the sensor),
validated the same way everywhere: a positive number, or the rule's name."""

from __future__ import annotations

from typing import Any


def positive_or_rule(v: Any, rule: str) -> float | str:
    """``v`` as a positive float, or ``rule`` (``None``, a former default, means the rule);
    ValueError otherwise (pydantic turns it into ``estimator.tuning.KEY: ...``)."""
    if v is None or v == rule:
        return rule
    try:
        number = float("nan") if isinstance(v, bool) else float(v)
    except (TypeError, ValueError):
        number = float("nan")
    if not number > 0:
        raise ValueError(f"a positive number or '{rule}', got {v!r}")
    return number
