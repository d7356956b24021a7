"""The ``tumblenav`` command (typer).

Exit status: 0 ok, 2 bad input (one-line message, no traceback), 1 anything else.
Set ``TUMBLENAV_DEBUG=1`` to see the traceback of an unexpected error.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from tumblenav.errors import InputError

app = typer.Typer(
    help="Relative navigation of a tumbling, non-cooperative spacecraft: simulate, sense, "
    "estimate, evaluate.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
scenarios_app = typer.Typer(help="Built-in scenarios.", no_args_is_help=True)
app.add_typer(scenarios_app, name="scenarios")

out = Console()
err = Console(stderr=True)

ScenarioArg = Annotated[str, typer.Argument(help="built-in scenario name or path to a YAML file")]
OutOpt = Annotated[Path, typer.Option("-o", "--output", help="output folder")]
EstimatorOpt = Annotated[
    str | None,
    typer.Option("--estimator", "-e", help="see `tumblenav estimators` (default: the scenario's)"),
]


@scenarios_app.command("list")
def scenarios_list() -> None:
    """List the built-in scenarios."""
    from tumblenav.scenario import builtin_names, load_scenario

    table = Table("name", "sensor", "duration [s]", "rate [Hz]", "description")
    for name in builtin_names():
        s = load_scenario(name)
        table.add_row(name, s.sensor.kind, f"{s.duration_s:g}", f"{s.rate_hz:g}", s.description)
    out.print(table)


@scenarios_app.command("show")
def scenarios_show(name: Annotated[str, typer.Argument(help="built-in scenario name")]) -> None:
    """Print a built-in scenario as YAML (save it, edit it, pass its path to other commands)."""
    from tumblenav.scenario import builtin_text

    sys.stdout.write(builtin_text(name))


@app.command()
def simulate(
    scenario: ScenarioArg,
    output: OutOpt = Path("out/simulate"),
    seed: Annotated[int | None, typer.Option(help="run seed (default: the scenario's)")] = None,
    plots: Annotated[bool, typer.Option(help="also write PNG figures")] = True,
) -> None:
    """Simulate the truth and the measurements; write truth.nc and measurements.nc."""
    from tumblenav.pipeline import run_simulate

    files = run_simulate(scenario, output, seed=seed, plots=plots, console=err)
    for f in files:
        out.print(f"wrote {f}")


@app.command()
def estimate(
    scenario: ScenarioArg,
    estimator: EstimatorOpt = None,
    output: OutOpt = Path("out/estimate"),
    measurements: Annotated[
        Path | None, typer.Option(help="folder with measurements.nc (and truth.nc) to use")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="run seed (default: the scenario's)")] = None,
) -> None:
    """Estimate one run; write estimates.nc, summary.json and error figures."""
    from tumblenav.pipeline import print_summary, run_estimate

    summary = run_estimate(scenario, estimator, output, measurements, seed, console=err)
    print_summary(summary, out)
    out.print(f"results in {output}")


@app.command()
def montecarlo(
    scenario: ScenarioArg,
    estimator: EstimatorOpt = None,
    runs: Annotated[
        int | None, typer.Option(min=1, help="number of runs (default: the scenario's)")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(min=1, help="processes (default: all cores)")
    ] = None,
    scheduler: Annotated[str | None, typer.Option(help="Dask scheduler address")] = None,
    output: OutOpt = Path("out/montecarlo"),
) -> None:
    """Seeded Monte Carlo campaign; resumable: rerun with the same -o to finish it."""
    from tumblenav.pipeline import print_summary, run_montecarlo

    summary = run_montecarlo(scenario, estimator, runs, output, workers, scheduler, console=err)
    print_summary(summary, out)
    out.print(f"results in {output}")


@app.command()
def reproduce(
    paper: Annotated[str, typer.Argument(help="hu2024, yu2019, chang2021 or kabir2025")],
    runs: Annotated[
        int | None, typer.Option(min=1, help="runs per case (default: the paper's)")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(min=1, help="processes (default: all cores)")
    ] = None,
    output: OutOpt = Path("out/reproduce"),
) -> None:
    """Reproduce a paper's simulation section: figures and summary.json with its values."""
    from tumblenav.papers import reproduce as rep

    summary = rep(paper, output, runs=runs, workers=workers, console=err)
    out.print(f"{len(summary.get('cases', []))} cases; results in {output}")


@app.command()
def estimators() -> None:
    """List the estimators and what each needs."""
    from tumblenav.estimators.base import available

    table = Table("name", "needs", "description")
    for name, est in available().items():
        table.add_row(name, est.needs, est.description)
    out.print(table)


@app.command()
def demo(output: OutOpt = Path("out/demo")) -> None:
    """Run the main job on the built-in default scenario (hu2024) and say where results are."""
    from tumblenav.pipeline import run_demo

    run_demo(output, console=out)


def main(argv: list[str] | None = None) -> None:
    """Entry point: maps InputError to exit 2 and unexpected errors to exit 1, one line each."""
    try:
        app(args=argv, standalone_mode=False)
    except InputError as exc:
        err.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        err.print("aborted")
        sys.exit(130)
    except KeyboardInterrupt:
        err.print("interrupted; finished results are kept")
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - the one place that turns crashes into a line
        # click (vendored by recent typer) usage errors: show them as click does, exit 2
        if callable(getattr(exc, "show", None)) and isinstance(
            getattr(exc, "exit_code", None), int
        ):
            exc.show()
            sys.exit(exc.exit_code)
        if os.environ.get("TUMBLENAV_DEBUG"):
            raise
        err.print(
            f"[bold red]internal error:[/] {exc.__class__.__name__}: {escape(str(exc))} "
            "(set TUMBLENAV_DEBUG=1 for the traceback)",
            highlight=False,
            soft_wrap=True,
        )
        sys.exit(1)
    sys.exit(0)


if __name__ == "__main__":
    main()
