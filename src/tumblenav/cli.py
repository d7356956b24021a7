"""The ``tumblenav`` command (typer).

Exit status: 0 ok, 1 an internal error, 2 bad input (one-line message, no traceback, nothing
started), 130 interrupted by SIGINT (Ctrl-C), 143 by SIGTERM: the command stops within about a
second, says what was kept and how to resume, and leaves no half-written file.
Set ``TUMBLENAV_DEBUG=1`` to see the traceback of an unexpected error.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import click
import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from typer.core import TyperCommand, TyperGroup

from tumblenav.errors import InputError, Interrupted

if TYPE_CHECKING:
    # recent typer vendors click as typer._click: its commands, contexts and parsers are
    # those classes, not the click package's (annotations only, nothing imported at run time)
    from typer._click import Command as TyperClickCommand
    from typer._click import Context as TyperClickContext


def _refuse_repeated_options(
    cmd: TyperClickCommand, ctx: TyperClickContext, args: list[str]
) -> None:
    """Click silently keeps the last of a repeated option (``-e a -e b`` runs only b):
    refuse it as a usage error (exit 2) instead."""
    try:
        _, _, order = cmd.make_parser(ctx).parse_args(args=list(args))
    except click.UsageError:
        return  # click reports it itself
    seen: set[str] = set()
    for param in order:
        is_option = getattr(param, "param_type_name", "") == "option"
        if is_option and not getattr(param, "multiple", False) and not getattr(param, "count", 0):
            if param.name in seen:
                why = (
                    " (one estimator per command; run the command once per estimator)"
                    if param.name == "estimator"
                    else ""
                )
                raise click.UsageError(
                    f"option {'/'.join(param.opts)} given more than once; give it once{why}",
                    # click's UsageError is annotated with click's Context, but this is typer's
                    # vendored one; show() only reads its command, command_path, color and
                    # usage, which both have
                    ctx=ctx,  # type: ignore[arg-type]
                )
            seen.add(param.name or "")


class StrictCommand(TyperCommand):
    def parse_args(self, ctx: TyperClickContext, args: list[str]) -> list[str]:
        _refuse_repeated_options(self, ctx, args)
        return super().parse_args(ctx, args)


class StrictGroup(TyperGroup):
    def parse_args(self, ctx: TyperClickContext, args: list[str]) -> list[str]:
        if args and args[0].startswith("-"):
            _refuse_repeated_options(self, ctx, [a for a in args if a.startswith("-")])
        return super().parse_args(ctx, args)


_ARGV: list[str] = []  # the command line main() was given (recorded in summary.json)
_OUTPUT: list[tuple[Path, float]] = []  # the command's output folder and its start time


def _written_since(folder: Path, start: float) -> int:
    """How many files under ``folder`` were written at or after ``start`` (epoch s)."""
    try:
        return sum(1 for f in folder.rglob("*") if f.is_file() and f.stat().st_mtime >= start)
    except OSError:
        return 0


def _record(output: Path, report: bool = False) -> None:
    """Add the command line to ``output/summary.json`` (the report shows it) and, with
    ``report``, write ``output/report.html``."""
    from tumblenav import io

    path = Path(output) / "summary.json"
    if path.is_file():
        summary = io.read_json(path)
        summary["command"] = " ".join(["tumblenav", *_ARGV])
        io.write_json(summary, path)
    if report:
        from tumblenav.report import write_report

        out.print(f"report: {write_report(Path(output))}")


# the results a command may write over (its own, and simulate's under estimate: `demo`)
_WRITES_INTO = {
    "simulate": ("a simulation", "one estimate"),
    "estimate": ("a simulation", "one estimate"),
    "demo": ("a simulation", "one estimate"),
    "montecarlo": ("a Monte Carlo campaign",),
    "compare": ("a comparison",),
    "reproduce": ("a paper's reproduction",),
}


def _folder_kind(p: Path) -> str | None:
    """Whose results folder ``p`` holds (None: none, or not a folder)."""
    if not p.is_dir():
        return None
    if (p / "campaign.json").is_file():
        return "a Monte Carlo campaign"
    if (p / "estimates.nc").is_file():
        return "one estimate"
    summary = p / "summary.json"
    if summary.is_file():
        from tumblenav import io

        try:
            keys = io.read_json(summary)
        except (OSError, InputError):
            keys = {}
        keys = keys if isinstance(keys, dict) else {}
        if "paper" in keys:
            return "a paper's reproduction"
        if "same_measurements" in keys or any(p.glob("*/campaign.json")):
            return "a comparison"
    if (p / "truth.nc").is_file():
        return "a simulation"
    return None


def _check_output(output: Path, command: str) -> None:
    """An output folder that cannot be used is bad input, found before any work starts (exit
    2): an empty path, a file (or a path through one), a folder that cannot be written, or a
    folder that holds another command's results which this one would replace in part (a
    campaign's summary.json under a single estimate, or the reverse)."""
    import time

    _OUTPUT[:] = [(Path(output), time.time() - 1.0)]  # mtimes have a coarse resolution
    where = "-o/--output"
    # typer turns an empty path into "." (the current folder): look at what was typed
    typed = [b for a, b in zip(_ARGV, _ARGV[1:], strict=False) if a in ("-o", "--output")]
    typed += [a.split("=", 1)[1] for a in _ARGV if a.startswith("--output=")]
    if not str(output).strip() or any(not t.strip() for t in typed):
        raise InputError("an empty path: give a folder", where)
    p = Path(output)
    # nothing is created before the work starts (a refused command leaves no folder): the
    # nearest existing folder must be a folder and writable (read-only mounts included)
    existing = next((q for q in (p, *p.parents) if q.exists()), Path("."))
    if not existing.is_dir():
        raise InputError(f"{existing} is a file, not a folder", f"{where} {p}")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"cannot write in {existing}", f"{where} {p}")
    held = _folder_kind(p)
    if held is not None and held not in _WRITES_INTO[command]:
        raise InputError(
            f"it holds the results of {held}; {command} would replace them in part (its "
            "summary.json): choose another folder",
            f"{where} {p}",
        )


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import version

        import tumblenav

        try:
            v = version("tumblenav")
        except Exception:  # noqa: BLE001 - not installed as a distribution
            v = tumblenav.__version__
        typer.echo(f"tumblenav {v}")
        raise typer.Exit(0)


app = typer.Typer(
    help="Relative navigation of a tumbling, non-cooperative spacecraft: simulate, sense, "
    "estimate, evaluate.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    cls=StrictGroup,
)
scenarios_app = typer.Typer(help="Built-in scenarios.", no_args_is_help=True)


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="print the version and exit"
        ),
    ] = False,
) -> None:
    """Relative navigation of a tumbling, non-cooperative spacecraft: simulate, sense,
    estimate, evaluate.

    Exit status: 0 ok, 1 internal error, 2 bad input, 130 interrupted (Ctrl-C), 143
    terminated (SIGTERM).
    """


app.add_typer(scenarios_app, name="scenarios")

out = Console()
err = Console(stderr=True)

ScenarioArg = Annotated[str, typer.Argument(help="built-in scenario name or path to a YAML file")]
OutOpt = Annotated[Path, typer.Option("-o", "--output", help="output folder")]
PlotsOpt = Annotated[bool, typer.Option("--plots/--no-plots", help="also write PNG figures")]
WorkersOpt = Annotated[int | None, typer.Option(min=1, help="processes (default: all cores)")]
SchedulerOpt = Annotated[str | None, typer.Option(help="Dask scheduler address")]
RunSeedOpt = Annotated[int | None, typer.Option(help="run seed (default: the scenario's)", min=0)]
SeedOpt = Annotated[
    int | None,
    typer.Option(help="base seed (default: the scenario's montecarlo.seed)", min=0),
]
EstimatorOpt = Annotated[
    str | None,
    typer.Option("--estimator", "-e", help="see `tumblenav estimators` (default: the scenario's)"),
]


@scenarios_app.command("list", cls=StrictCommand)
def scenarios_list() -> None:
    """List the built-in scenarios."""
    from tumblenav.scenario import builtin_names, load_scenario

    table = Table("name", "sensor", "duration [s]", "rate [Hz]", "description")
    for name in builtin_names():
        s = load_scenario(name)
        table.add_row(name, s.sensor.kind, f"{s.duration_s:g}", f"{s.rate_hz:g}", s.description)
    out.print(table)


@scenarios_app.command("show", cls=StrictCommand)
def scenarios_show(name: Annotated[str, typer.Argument(help="built-in scenario name")]) -> None:
    """Print a built-in scenario as YAML (save it, edit it, pass its path to other commands)."""
    from tumblenav.scenario import builtin_names, builtin_text

    if name not in builtin_names() and Path(name).is_file():
        raise InputError(
            "scenarios show prints a built-in scenario (" + ", ".join(builtin_names()) + "); "
            "this is a file: open it, or pass its path to simulate, estimate or montecarlo",
            name,
        )

    sys.stdout.write(builtin_text(name))


@app.command(cls=StrictCommand)
def simulate(
    scenario: ScenarioArg,
    output: OutOpt = Path("out/simulate"),
    seed: RunSeedOpt = None,
    plots: PlotsOpt = True,
) -> None:
    """Simulate the truth and the measurements; write truth.nc and measurements.nc."""
    from tumblenav.pipeline import run_simulate

    _check_output(output, "simulate")

    files = run_simulate(scenario, output, seed=seed, plots=plots, console=err)
    for f in files:
        out.print(f"wrote {f}")


@app.command(cls=StrictCommand)
def estimate(
    scenario: ScenarioArg,
    estimator: EstimatorOpt = None,
    output: OutOpt = Path("out/estimate"),
    measurements: Annotated[
        Path | None, typer.Option(help="folder with measurements.nc (and truth.nc) to use")
    ] = None,
    seed: RunSeedOpt = None,
    plots: PlotsOpt = True,
) -> None:
    """Estimate one run; write estimates.nc, summary.json and error figures."""
    from tumblenav.pipeline import print_summary, run_estimate

    _check_output(output, "estimate")

    summary = run_estimate(
        scenario, estimator, output, measurements, seed, console=err, plots=plots
    )
    _record(output)
    print_summary(summary, out)
    out.print(f"results in {output}")


@app.command(cls=StrictCommand)
def montecarlo(
    scenario: ScenarioArg,
    estimator: EstimatorOpt = None,
    runs: Annotated[
        int | None, typer.Option(min=1, help="number of runs (default: the scenario's)")
    ] = None,
    workers: WorkersOpt = None,
    scheduler: SchedulerOpt = None,
    output: OutOpt = Path("out/montecarlo"),
    seed: SeedOpt = None,
    plots: PlotsOpt = True,
) -> None:
    """Seeded Monte Carlo campaign; resumable: rerun with the same -o to finish it."""
    from tumblenav.pipeline import print_summary, run_montecarlo

    _check_output(output, "montecarlo")

    summary = run_montecarlo(
        scenario,
        estimator,
        runs,
        output,
        workers,
        scheduler,
        console=err,
        seed=seed,
        plots=plots,
    )
    _record(output)
    print_summary(summary, out)
    out.print(f"results in {output}")


@app.command(cls=StrictCommand)
def compare(
    scenario: ScenarioArg,
    estimators: Annotated[
        str,
        typer.Option("--estimator", "-e", help="estimators to compare, comma-separated: -e a,b,c"),
    ],
    runs: Annotated[
        int | None, typer.Option(min=1, help="runs per estimator (default: the scenario's)")
    ] = None,
    workers: WorkersOpt = None,
    scheduler: SchedulerOpt = None,
    output: OutOpt = Path("out/compare"),
    seed: SeedOpt = None,
    plots: PlotsOpt = True,
) -> None:
    """Head to head: the same truth, measurements and seeds for every estimator; one table,
    overlaid figures; resumable (rerun with the same -o)."""
    from tumblenav.pipeline import print_comparison, run_compare

    _check_output(output, "compare")

    summary = run_compare(
        scenario,
        estimators.split(","),
        runs,
        output,
        workers,
        scheduler,
        console=err,
        seed=seed,
        plots=plots,
    )
    _record(output, report=True)
    print_comparison(summary, out)
    out.print(f"results in {output}")


@app.command("import", cls=StrictCommand)
def import_(
    kind: Annotated[str, typer.Argument(help="stereo-tracks, depth-clouds or stereo-images")],
    path: Annotated[
        Path,
        typer.Argument(
            help="the tracks table (CSV/Parquet) or the index table (CSV) of the clouds/images"
        ),
    ],
    output: OutOpt = Path("out/import"),
    calibration: Annotated[
        Path | None,
        typer.Option(help="calibration/context YAML (default: calibration.yaml beside PATH)"),
    ] = None,
    scenario: Annotated[
        str | None,
        typer.Option(
            help="scenario the written scenario.yaml starts from (estimator, tuning); default: "
            "hu2024 for tracks, yu2019 for clouds, chang2021_close for images"
        ),
    ] = None,
) -> None:
    """Your own measurements in: write DIR/measurements.nc and DIR/scenario.yaml (the
    calibration's sensor), for `tumblenav estimate DIR/scenario.yaml --measurements DIR`."""
    from tumblenav.importers import import_measurements

    result = import_measurements(kind, path, output, calibration, scenario)
    for line in result.warnings:
        err.print(f"[bold yellow]warning:[/] {escape(line)}", highlight=False, soft_wrap=True)
    for f in result.files:
        out.print(f"wrote {escape(str(f))}", highlight=False, soft_wrap=True)
    out.print(
        f"{result.epochs} epochs of {kind}; next: tumblenav estimate "
        f"{escape(str(output / 'scenario.yaml'))} --measurements {escape(str(output))}",
        highlight=False,
        soft_wrap=True,
    )


@app.command(cls=StrictCommand)
def reproduce(
    paper: Annotated[str, typer.Argument(help="hu2024, yu2019, chang2021 or kabir2025")],
    runs: Annotated[
        int | None, typer.Option(min=1, help="runs per case (default: the paper's)")
    ] = None,
    workers: WorkersOpt = None,
    scheduler: SchedulerOpt = None,
    output: OutOpt = Path("out/reproduce"),
) -> None:
    """Reproduce a paper's simulation section: figures and summary.json with its values."""
    from tumblenav.papers import reproduce as rep
    from tumblenav.papers.table import print_comparison

    _check_output(output, "reproduce")

    try:
        summary = rep(paper, output, runs=runs, workers=workers, scheduler=scheduler, console=err)
    except Interrupted as exc:
        inner = f" ({exc.kept})" if exc.kept else ""
        exc.kept = (
            f"the campaigns finished so far are stored under {output}{inner}; run the same "
            "command again to resume"
        )
        raise
    _record(output, report=True)
    print_comparison(summary, out)
    out.print(f"{len(summary.get('cases', []))} cases; results in {output}")


@app.command(cls=StrictCommand)
def report(
    folder: Annotated[Path, typer.Argument(help="an output folder of any command")],
) -> None:
    """One self-contained HTML file (report.html in the folder, figures embedded): the
    scenario and what differs from the built-in, the tables, NEES/NIS against their bounds,
    the figures, failed runs, versions and the command that made the results."""
    from tumblenav.report import write_report

    out.print(f"wrote {write_report(folder)}")


@app.command(cls=StrictCommand)
def estimators() -> None:
    """List the estimators and what each needs."""
    from tumblenav.estimators.base import PLUGIN_ERRORS, available, plugin_source
    from tumblenav.frontends import registry

    table = Table("name", "runs on", "needs", "description", "from", title="estimators")
    for name, est in available().items():
        consumes = ", ".join(getattr(est, "consumes", ()) or ("?",))
        table.add_row(name, consumes, est.needs, est.description, plugin_source(name) or "built in")
    out.print(table)
    fes = Table("name", "consumes", "produces", "description", title="front ends")
    for fe in registry.available().values():
        fes.add_row(fe.name, fe.consumes, fe.produces, fe.description)
    out.print(fes)
    for name, why in PLUGIN_ERRORS.items():
        err.print(f"[bold yellow]plugin {escape(name)} not loaded:[/] {escape(why)}")


@app.command(cls=StrictCommand)
def demo(output: OutOpt = Path("out/demo")) -> None:
    """Run the main job on the built-in default scenario (hu2024) and say where results are."""
    from tumblenav.pipeline import run_demo

    _check_output(output, "demo")

    run_demo(output, console=out)


# One interruption can arrive twice: GNU timeout (and other supervisors) signals the process,
# then its whole process group, which holds the process again; both land microseconds apart.
# A second signal within this time of the first is taken as the same interruption, so the
# cleanup still runs and says what was kept (before, 2 of 6 `timeout -s INT` runs ended with
# status 130 and no message at all).
SAME_INTERRUPTION_S = 0.5


def _install_signal_handlers() -> None:
    """SIGINT and SIGTERM raise :class:`Interrupted` in the main thread (typer would turn a
    KeyboardInterrupt into a silent exit status); a second signal during the cleanup (later
    than :data:`SAME_INTERRUPTION_S`) ends the process at once, with one line."""

    def handler(signum: int, frame: Any) -> None:
        first = time.monotonic()

        def hard_exit(signum2: int, frame2: Any) -> None:
            if time.monotonic() - first < SAME_INTERRUPTION_S:
                return  # the first interruption delivered again
            name = signal.Signals(signum2).name
            # os.write, not the console: the main thread may be inside one of its prints
            os.write(
                2,
                f"\ninterrupted again ({name}): stopping at once; results already stored are "
                "kept, each whole\n".encode(),
            )
            os._exit(128 + signum2)

        signal.signal(signal.SIGINT, hard_exit)
        signal.signal(signal.SIGTERM, hard_exit)
        raise Interrupted(signum)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


# After an interruption everything is stored and said; the interpreter's exit then joins the
# process pool's manager thread without a time limit (concurrent.futures' exit hook). Once, in
# a fresh clone's test run on a loaded machine, that join did not end within 60 s after the
# message (not reproduced in 14 tries, cold and warm, loaded and not). The watchdog ends the
# process with its exit status if the exit takes longer than this.
EXIT_GRACE_S = 10.0


def _exit_within(seconds: float, code: int) -> None:
    """End the process with ``code`` in ``seconds`` if the normal exit has not by then
    (a daemon timer: it does not itself keep the process alive)."""
    import threading

    def hard_exit() -> None:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)

    timer = threading.Timer(seconds, hard_exit)
    timer.daemon = True
    timer.start()


def main(argv: list[str] | None = None) -> None:
    """Entry point: exit 0 ok, 2 for an InputError or a usage error, 130/143 when interrupted
    (SIGINT/SIGTERM), 1 for anything unexpected; one line each, no traceback."""
    _ARGV[:] = [str(a) for a in (sys.argv[1:] if argv is None else argv)]
    _OUTPUT.clear()
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    _install_signal_handlers()
    try:
        rv = app(args=argv, standalone_mode=False)
    except InputError as exc:
        err.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except Interrupted as exc:
        name = signal.Signals(exc.signum).name
        kept = exc.kept
        if kept is None and _OUTPUT:
            folder, start = _OUTPUT[0]
            n = _written_since(folder, start)
            if n:
                kept = (
                    f"{n} file(s) were written to {folder} before the interruption, each whole "
                    "but the set incomplete; run the same command again to write them all"
                )
        kept = kept or "no result was written (files already in the output folder are whole)"
        err.print(
            f"[bold yellow]interrupted ({name}):[/] {escape(kept)}",
            highlight=False,
            soft_wrap=True,
        )
        if argv is None:  # this process's own command line: it ends here
            _exit_within(EXIT_GRACE_S, exc.exit_code)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:  # raised before the handlers were installed
        err.print("[bold yellow]interrupted (SIGINT)[/]")
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        err.print("aborted")
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - the one place that turns crashes into a line
        # click (vendored by recent typer) usage errors: show them as click does, exit 2
        show, exit_code = getattr(exc, "show", None), getattr(exc, "exit_code", None)
        if callable(show) and isinstance(exit_code, int):
            show()
            sys.exit(exit_code)
        if os.environ.get("TUMBLENAV_DEBUG"):
            raise
        err.print(
            f"[bold red]internal error:[/] {exc.__class__.__name__}: {escape(str(exc))} "
            "(set TUMBLENAV_DEBUG=1 for the traceback)",
            highlight=False,
            soft_wrap=True,
        )
        sys.exit(1)
    finally:
        for s_, h in previous.items():
            signal.signal(s_, h)
    # standalone_mode=False returns an Exit's code (e.g. 130 from typer's own KeyboardInterrupt
    # handling) instead of raising it: pass it on, never report success for it
    sys.exit(rv if isinstance(rv, int) else 0)


if __name__ == "__main__":
    main()
