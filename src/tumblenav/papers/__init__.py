"""Paper reproduction recipes: they compose the stages and hold no algorithm of their own."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.console import Console

from tumblenav.errors import InputError

PAPERS = ("hu2024", "yu2019", "chang2021", "kabir2025")

# what a reproduce case keeps of its campaign's summary.json
CASE_KEYS = ("runs", "runs_failed", "runs_without_estimate", "window_s", "rmse", "per_run",
             "nees", "nis")  # fmt: skip


def case_from_campaign(summary: dict[str, Any]) -> dict[str, Any]:
    """The campaign summary's part that a reproduce case reports (``rmse`` {} if none)."""
    case = {k: summary.get(k) for k in CASE_KEYS}
    case["rmse"] = summary.get("rmse", {})
    return case


def reproduce(
    paper: str,
    output: Path,
    runs: int | None = None,
    workers: int | None = None,
    console: Console | None = None,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """One paper's recipe; its campaigns run on ``workers`` local processes, or on the Dask
    cluster at ``scheduler`` (Kabir 2025's GP study stays local: it is not a campaign)."""
    if paper not in PAPERS:
        raise InputError(f"unknown paper '{paper}' (one of {', '.join(PAPERS)})")
    if paper == "hu2024":
        from tumblenav.papers import hu2024

        return hu2024.reproduce(Path(output), runs, workers, console, scheduler)
    if paper == "yu2019":
        from tumblenav.papers import yu2019

        return yu2019.reproduce(Path(output), runs, workers, console, scheduler)
    if paper == "kabir2025":
        from tumblenav.papers import kabir2025

        return kabir2025.reproduce(Path(output), runs, workers, console, scheduler)
    from tumblenav.papers import chang2021

    return chang2021.reproduce(Path(output), runs, workers, console, scheduler=scheduler)
