"""The attributes every variable of a measurement file carries."""

from __future__ import annotations


def _a(units: str, description: str) -> dict[str, str]:
    return {"units": units, "description": description}
