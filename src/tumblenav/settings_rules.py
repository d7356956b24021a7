"""Settings validated the same way everywhere: a settings model's errors as one line naming
the key (:func:`validate`), and settings whose default is a named rule (e.g.
``'range_noise'``: computed from the sensor): a positive number, or the rule's name."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from tumblenav.errors import InputError

ModelT = TypeVar("ModelT", bound=BaseModel)


def validate(model: type[ModelT], raw: dict[str, Any] | None, prefix: str) -> ModelT:
    """``raw`` validated against ``model``; an InputError naming the key otherwise
    (``<prefix>.KEY: unknown key`` / the reason), e.g. prefix ``estimator.tuning``."""
    try:
        return model.model_validate(raw or {})
    except ValidationError as exc:
        e = exc.errors()[0]
        loc = ".".join(str(p) for p in e["loc"])
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
        raise InputError(f"{prefix}.{loc}: {msg}") from None


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
