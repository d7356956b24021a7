"""Jobs behind the CLI commands: load, simulate, estimate, write files, figures and tables."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from tumblenav import io, metrics
from tumblenav import plots as figures
from tumblenav.campaign import runner
from tumblenav.campaign.store import run_seed
from tumblenav.errors import InputError
from tumblenav.estimators import base as est_base
from tumblenav.scenario import Scenario, load_scenario
from tumblenav.simulation import StereoMeasurements, Truth, run_streams, simulate


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
    base = scenario.montecarlo.seed if seed is None else seed
    with con.status(f"simulating {scenario.name} ({len(scenario.times)} samples)"):
        truth, meas = simulate(scenario, run_seed(base, 0))  # = run 0 of a campaign
    output = Path(output)
    files = [io.write_netcdf(truth.to_dataset(scenario.name), output / "truth.nc")]
    files.append(io.write_netcdf(meas.to_dataset(scenario.name), output / "measurements.nc"))
    if plots:
        files.append(figures.plot_truth(truth, output / "truth.png", f"{scenario.name}: truth"))
        plot = figures.plot_measurements if scenario.sensor.kind == "stereo" else figures.plot_depth
        files.append(plot(meas, output / "measurements.png", f"{scenario.name}: measurements"))
    return files


def _load_measurements(folder: Path) -> tuple[StereoMeasurements, Truth | None]:
    folder = Path(folder)
    ds = io.read_netcdf(
        folder / "measurements.nc", required=("uv", "observed", "q_CL", "q_LI", "R_CkC", "p_CkinC")
    )
    try:
        meas = StereoMeasurements.from_dataset(ds)
    except (KeyError, ValueError, IndexError) as exc:
        raise InputError(
            f"malformed measurements ({exc})", str(folder / "measurements.nc")
        ) from None
    truth = None
    if (folder / "truth.nc").exists():
        truth = Truth.from_dataset(io.read_netcdf(folder / "truth.nc"))
    return meas, truth


def run_estimate(
    scenario_ref: str,
    estimator: str,
    output: Path,
    measurements: Path | None = None,
    seed: int | None = None,
    console: Console | None = None,
) -> dict[str, Any]:
    """One run: simulate (or read) measurements, estimate, evaluate, write files and figures."""
    scenario = load_scenario(scenario_ref)
    estimator = estimator or scenario.estimator.name
    est = est_base.get(estimator)
    con = console or Console(stderr=True)
    ss = run_seed(scenario.montecarlo.seed if seed is None else seed, 0)
    if measurements is not None:
        meas, truth = _load_measurements(measurements)
        if len(meas.t) < 2:
            raise InputError("needs at least two epochs", str(measurements))
    else:
        with con.status(f"simulating {scenario.name}"):
            truth, meas = simulate(scenario, ss)
        if meas is None:
            raise InputError(
                f"scenario {scenario.name}: {scenario.sensor.kind} measurements are "
                f"not simulated yet, so {estimator} cannot run on it"
            )
    with con.status(f"{estimator} on {scenario.name} ({len(meas.t)} epochs)"):
        hist = est.run(scenario, meas, run_streams(ss)["estimator"])
    output = Path(output)
    x_true = est.truth_state(truth, hist) if truth is not None else None
    io.write_netcdf(
        io.estimates_dataset(hist, scenario.name, estimator, x_true), output / "estimates.nc"
    )
    summary: dict[str, Any] = {
        "scenario": scenario.name,
        "estimator": estimator,
        "runs": 1,
        "window_s": list(scenario.window_s),
        "skipped": hist.skipped,
    }
    if x_true is not None:
        r = metrics.run_errors(hist, x_true)
        summary["rmse"] = {
            k: metrics.rmse_over_time(v, r.t, scenario.window_s) for k, v in r.errors.items()
        }
        summary["nees"] = metrics.consistency(r.nees[None], r.nees_dof, r.t, scenario.window_s)
        summary["nis"] = metrics.consistency(r.nis[None], r.nis_dof[None], r.t, scenario.window_s)
        figures.plot_error_history(
            hist,
            x_true,
            output / "errors.png",
            f"{scenario.name} / {estimator}: errors and +-3 sigma",
        )
    if not np.isfinite(hist.x).any():
        summary["note"] = (
            f"{estimator} never started: its start condition was not met in this run "
            + str(hist.info.get("start_condition", "(see the estimator's documentation)"))
        )
        con.print(f"[yellow]note:[/] {summary['note']}")
    io.write_json(summary, output / "summary.json")
    return summary


def run_montecarlo(
    scenario_ref: str,
    estimator: str | None,
    runs: int | None,
    output: Path,
    workers: int | None = None,
    scheduler: str | None = None,
    console: Console | None = None,
    scenario: Scenario | None = None,
) -> dict:
    """A resumable campaign plus its figures (RMSE vs time, NEES vs time)."""
    scenario = scenario or load_scenario(scenario_ref)
    estimator = estimator or scenario.estimator.name
    runs = runs or scenario.montecarlo.runs
    est_base.get(estimator)
    summary = runner.run_campaign(
        scenario,
        estimator,
        runs,
        Path(output),
        workers=workers,
        scheduler=scheduler,
        console=console,
    )
    campaign_figures(Path(output), scenario, estimator, runs)
    return summary


def campaign_curves(folder: Path, runs: int) -> tuple[np.ndarray, dict, dict]:
    """RMSE-over-runs curves (Hu 2024 eq. 45) and run-averaged NEES of a campaign folder."""
    from tumblenav.campaign.store import CampaignStore

    t, errs, cons = runner.collect(CampaignStore(Path(folder)), runs)
    curves = {k: metrics.rmse_over_runs(v) for k, v in errs.items()}
    cons["median"] = {k: metrics.nanmedian_quiet(v, axis=0) for k, v in errs.items()}
    return t, curves, cons


def campaign_figures(folder: Path, scenario: Scenario, estimator: str, runs: int) -> None:
    t, curves, cons = campaign_curves(folder, runs)
    if not curves:
        return
    for key, y in curves.items():
        figures.plot_rmse(
            {f"{estimator} RMSE": (t, y), f"{estimator} median": (t, cons["median"][key])},
            f"{key}",
            folder / f"rmse_{key}.png",
            f"{scenario.name}: Monte Carlo RMSE over {len(cons['runs'])} runs",
            window=scenario.window_s,
        )
    nees = metrics.nanmean_quiet(cons["nees"], axis=0) / cons["nees_dof"]
    lo, hi = metrics.chi2_bounds(cons["nees_dof"], len(cons["runs"]))
    figures.plot_consistency(
        t,
        {"NEES / dof": nees},
        (lo, hi),
        folder / "nees.png",
        f"{scenario.name} / {estimator}: consistency",
    )


def print_summary(summary: dict[str, Any], console: Console) -> None:
    """summary.json as a table: RMSE over the window, and for campaigns the median run."""
    w = summary.get("window_s")
    console.print(
        f"[bold]{summary.get('scenario')} / {summary.get('estimator')}[/], "
        f"{summary.get('runs')} run(s), steady-state window {w[0]:g}-{w[1]:g} s"
    )
    table = Table()
    table.add_column("quantity")
    table.add_column("RMSE", justify="right")
    per_run = summary.get("per_run") or {}
    if per_run:
        table.add_column("median run", justify="right")
    for k, v in summary.get("rmse", {}).items():
        row = [k, "-" if v is None else f"{v:.4g}"]
        if per_run:
            row.append(f"{per_run[k]['median']:.4g}" if k in per_run else "-")
        table.add_row(*row)
    for name in ("nees", "nis"):
        c = summary.get(name)
        if c and c.get("mean") is not None:
            lo, hi = c["bounds95"]
            row = [f"{name.upper()}/dof (95%: {lo:.3g}-{hi:.3g})", f"{c['mean']:.3g}"]
            table.add_row(*(row + ([""] if per_run else [])))
    console.print(table)


def run_demo(output: Path, console: Console) -> None:
    """The main job: ekf-dpacf on the built-in hu2024 scenario, with figures."""
    output = Path(output)
    run_simulate("hu2024", output, console=console)
    summary = run_estimate("hu2024", "ekf-dpacf", output, measurements=output, console=console)
    print_summary(summary, console)
    console.print(
        "[bold]tumblenav demo[/] (scenario hu2024, estimator ekf-dpacf): results in "
        + str(output.resolve())
    )
    for f in sorted(output.glob("*")):
        console.print(f"  {f}")
