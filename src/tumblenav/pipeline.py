"""Jobs behind the CLI commands: load, simulate, estimate, write files and figures."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from tumblenav import io
from tumblenav import plots as figures
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate


def run_simulate(
    scenario_ref: str,
    output: Path,
    seed: int | None = None,
    plots: bool = True,
    console: Console | None = None,
) -> list[Path]:
    """Simulate one run of a scenario; write truth.nc, measurements.nc (+ figures)."""
    scenario = load_scenario(scenario_ref)
    con = console or Console(stderr=True)
    with con.status(f"simulating {scenario.name} ({len(scenario.times)} samples)"):
        truth, meas = simulate(scenario, seed)
    output = Path(output)
    files = [io.write_netcdf(truth.to_dataset(scenario.name), output / "truth.nc")]
    if meas is not None:
        files.append(io.write_netcdf(meas.to_dataset(scenario.name), output / "measurements.nc"))
    else:
        con.print(
            f"note: {scenario.sensor.kind} sensor measurements are not simulated yet; "
            "only the truth was written"
        )
    if plots:
        files.append(_plots(truth, meas, output, scenario.name))
    return files


def _plots(truth, meas, output: Path, name: str) -> Path:
    p = figures.plot_truth(truth, output / "truth.png", title=f"{name}: truth")
    if meas is not None:
        figures.plot_measurements(meas, output / "measurements.png", title=f"{name}: measurements")
    return p


def run_demo(output: Path, console: Console) -> None:
    """The main job on the built-in default scenario."""
    output = Path(output)
    run_simulate("hu2024", output, console=console)
    console.print("[bold]tumblenav demo[/] (scenario hu2024): results in " + str(output.resolve()))
    for f in sorted(output.glob("*")):
        console.print(f"  {f}")
