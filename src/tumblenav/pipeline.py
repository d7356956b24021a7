"""Jobs behind the CLI commands: load, simulate, estimate, write files, figures and tables."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from tumblenav import evaluation, io, sensors
from tumblenav import plots as figures
from tumblenav.campaign import runner
from tumblenav.campaign.store import CampaignStore, run_seed
from tumblenav.errors import InputError
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation import metrics
from tumblenav.measurements import DepthMeasurements, StereoImageMeasurements, StereoMeasurements
from tumblenav.numba_cache import kernels_compiled
from tumblenav.scenario import Scenario, load_scenario
from tumblenav.simulation import Truth, run_streams, simulate, simulate_truth, with_track_truth


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
    files.append(_write_scenario(scenario, output))
    if isinstance(meas, StereoImageMeasurements):
        with _progress(con) as bar:
            task = bar.add_task("rendering the stereo images", total=len(meas.t))
            files += meas.write(
                output, scenario.name, progress=lambda k: bar.update(task, completed=k + 1)
            )
        if plots:
            files.append(figures.plot_image_pair(meas, output / "images.png", scenario.name))
        return files
    files.append(io.write_netcdf(meas.to_dataset(scenario.name), output / "measurements.nc"))
    nothing = _nothing_seen(meas)
    if nothing:
        con.print(f"[bold yellow]warning:[/] {nothing}", highlight=False)
    if plots:
        files.append(figures.plot_truth(truth, output / "truth.png", f"{scenario.name}: truth"))
        plot = figures.plot_measurements if scenario.sensor.kind == "stereo" else figures.plot_depth
        files.append(plot(meas, output / "measurements.png", f"{scenario.name}: measurements"))
    return files


def _estimator_name(estimator: str | None, scenario: Scenario, scenario_ref: str) -> str:
    """The estimator to run: the option's, else the scenario's ``estimator.name``, which is
    checked here so that an unknown one is blamed on the scenario file, not on the option."""
    if estimator:
        return estimator
    name = scenario.estimator.name
    try:
        est_base.get(name)
    except InputError as exc:
        raise InputError(f"estimator.name: {exc.what}", str(scenario_ref)) from None
    return name


def _keeps_earlier_comparison(output: Path, names: list[str]) -> None:
    """A comparison resumed in ``output`` must name every estimator the folder's comparison
    already holds: its summary would otherwise drop them (InputError)."""
    path = Path(output) / "summary.json"
    if not path.is_file():
        return
    try:
        earlier = io.read_json(path)
    except (OSError, ValueError, InputError):
        return
    cases = earlier.get("cases") if isinstance(earlier, dict) else None
    held = [c.get("estimator") for c in cases or [] if isinstance(c, dict)]
    dropped = [n for n in held if n and n not in names]
    if dropped:
        raise InputError(
            f"holds a comparison of {', '.join(n for n in held if n)}; this one would drop "
            f"{', '.join(dropped)} from its summary: name them too (-e "
            f"{','.join(dict.fromkeys([*(n for n in held if n), *names]))}) or choose another "
            "folder",
            str(output),
        )


def _nothing_seen(meas) -> str | None:
    """A warning when the sensor measured nothing in the whole run (the target out of the
    field of view or behind the chaser, occluded throughout, or lost from the start), else
    None; measurements without an ``observed`` mask (rendered images) are not checked."""
    observed = getattr(meas, "observed", None)
    if observed is None or np.any(np.asarray(observed)):
        return None
    return (
        "the sensor measured nothing in the whole run: the target is out of the field of "
        "view or behind the chaser, occluded throughout, or lost from the start (check "
        "target.r0_L_m, chaser.attitude, occlusion)"
    )


def _front_end_stage(scenario: Scenario, est, meas, con: Console):
    """The measurements the estimator consumes (image pairs through the image front end, with
    a progress bar: it renders and tracks every pair) and the front end's statistics."""
    from tumblenav.frontends import stages

    if not isinstance(meas, StereoImageMeasurements):
        return meas, None
    images = getattr(scenario.sensor, "images", None)
    settings = images.frontend if images is not None else {}
    with _progress(con) as bar:
        task = bar.add_task("finding and tracking features in the images", total=len(meas.t))
        return stages.prepare(
            meas,
            tuple(getattr(est, "consumes", ())),
            settings,
            progress=lambda k: bar.update(task, completed=k + 1),
        )


def _progress(con: Console) -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=con,
        transient=True,
    )


def _write_scenario(scenario: Scenario, output: Path) -> Path:
    """The scenario as run, beside its results (``scenario.yaml``, atomic)."""
    from tumblenav.scenario import scenario_to_yaml

    text = scenario_to_yaml(scenario)
    return io.atomic_write(
        Path(output) / "scenario.yaml", lambda tmp: tmp.write_text(text, encoding="utf-8")
    )


def _rig_differences(file_rig, scenario_rig) -> list[str]:
    """What differs between the rig a measurement file was taken with and the scenario's."""
    out = []
    if file_rig.kind != scenario_rig.kind:
        out.append(f"rig {file_rig.kind} (scenario: {scenario_rig.kind})")
    if not np.isclose(file_rig.baseline_m, scenario_rig.baseline_m, rtol=1e-6, atol=1e-9):
        out.append(f"baseline {file_rig.baseline_m:g} m (scenario: {scenario_rig.baseline_m:g} m)")
    for name, cf, cs in zip(("left", "right"), file_rig.cameras, scenario_rig.cameras, strict=True):
        for attr, unit in (
            ("focal_px", "px"),
            ("principal_point_px", "px"),
            ("resolution_px", "px"),
        ):
            a, b = np.asarray(getattr(cf, attr), float), np.asarray(getattr(cs, attr), float)
            if a.shape != b.shape or not np.allclose(a, b, rtol=1e-6, atol=1e-6):
                out.append(
                    f"{name} {attr} {np.round(a, 6).tolist()} {unit} (scenario: "
                    f"{np.round(b, 6).tolist()} {unit})"
                )
        if not np.allclose(cf.R_CkC, cs.R_CkC, atol=1e-9) or not np.allclose(
            cf.p_CkinC, cs.p_CkinC, atol=1e-9
        ):
            out.append(f"{name} camera pose in the rig (R_CkC, p_CkinC)")
    return out


def _load_images(folder: Path, ds, scenario: Scenario):
    """Stereo image pairs named by ``folder/measurements.nc``, checked against the scenario's
    rig like tracks; the first pair is read at once so that a missing or mis-sized image is an
    error before any work (the others are read, and checked, as they are used)."""
    path = folder / "measurements.nc"
    if scenario.sensor.kind != "stereo":
        raise InputError(
            f"holds stereo images, but scenario {scenario.name} has a {scenario.sensor.kind} "
            "sensor: give the scenario the data were taken with",
            str(path),
        )
    try:
        meas = StereoImageMeasurements.from_dataset(ds, folder)
    except (KeyError, ValueError, IndexError, TypeError) as exc:
        raise InputError(f"malformed measurements ({exc})", str(path)) from None
    diff = _rig_differences(meas.rig, sensors.make_rig(scenario.sensor))
    if diff:
        raise InputError(
            f"taken with another stereo rig than scenario {scenario.name}'s: " + "; ".join(diff),
            str(path),
        )
    if not np.isfinite(meas.noise_px) or meas.noise_px <= 0:
        meas = dataclasses.replace(
            meas, noise_px=scenario.sensor.noise.sigma_px(scenario.sensor.focal_px)
        )
    if len(meas.t):
        meas.source.pair(0)
    truth_path = folder / "truth.nc"
    truth = Truth.from_dataset(io.read_netcdf(truth_path)) if truth_path.is_file() else None
    return meas, truth


def _check_measured_values(ds, meas, where: str) -> None:
    """The values of a measurements file that its structure does not check: the attitudes
    are unit quaternions, ``observed`` is 0 or 1, and every observed measurement is finite
    (an InputError naming the variable and the first bad epoch otherwise)."""
    t = np.asarray(meas.t, dtype=float)
    for name in ("q_CL", "q_LI"):
        q = np.asarray(getattr(meas, name), dtype=float)
        with np.errstate(invalid="ignore"):
            bad = ~(np.abs(np.linalg.norm(q, axis=-1) - 1.0) < 1e-3)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"{name} at epoch {k} (t = {t[k]:g} s) is {q[k].tolist()}, not a unit quaternion",
                where,
            )
    raw = np.asarray(ds["observed"].values)
    if raw.dtype != bool and not np.isin(raw, (0, 1)).all():
        bad_values = sorted({float(v) for v in np.unique(raw) if v not in (0, 1)})[:3]
        raise InputError(f"observed holds {bad_values}: only 0 and 1 (or booleans)", where)
    values, name = (meas.uv, "uv") if hasattr(meas, "uv") else (meas.points, "points")
    seen = np.asarray(meas.observed, dtype=bool)
    finite = np.all(np.isfinite(values), axis=-1)
    bad = seen & ~finite.reshape(seen.shape)
    if bad.any():
        k = int(np.argwhere(bad)[0][0])
        raise InputError(
            f"{name} at epoch {k} (t = {t[k]:g} s) is not finite where observed is 1 (mark "
            "it unobserved, or give the value)",
            where,
        )


def _load_measurements(folder: Path, scenario: Scenario):
    """Read ``folder/measurements.nc`` (and ``truth.nc`` if present), checked against the
    scenario: the sensor kind, the rig and its calibration, the noise the estimators weight
    by. Anything that does not match is an InputError naming the file and what differs."""
    folder = Path(folder)
    path = folder / "measurements.nc"
    ds = io.read_netcdf(path)
    if "left_image" in ds.variables:
        return _load_images(folder, ds, scenario)
    kind = "stereo" if "uv" in ds.variables else "depth" if "points" in ds.variables else None
    if kind is None:
        raise InputError(
            "holds neither stereo tracks (variable uv), stereo images (left_image) nor depth "
            "point clouds (points)",
            str(path),
        )
    if kind != scenario.sensor.kind:
        raise InputError(
            f"holds {kind} measurements, but scenario {scenario.name} has a "
            f"{scenario.sensor.kind} sensor: give the scenario the data were taken with",
            str(path),
        )
    if kind == "depth":
        from_ds = getattr(DepthMeasurements, "from_dataset", None)
        if from_ds is None:
            raise InputError(
                "reading depth measurements from a folder is not supported yet: run "
                f"`tumblenav estimate {scenario.name}` without --measurements",
                str(path),
            )
        meas = from_ds(ds)
    else:
        required = ("uv", "observed", "q_CL", "q_LI", "R_CkC", "p_CkinC", "focal_px")
        missing = [v for v in required if v not in ds.variables]
        if missing:
            raise InputError(f"missing variable(s) {', '.join(missing)}", str(path))
        try:
            meas = StereoMeasurements.from_dataset(ds)
        except (KeyError, ValueError, IndexError, TypeError) as exc:
            raise InputError(f"malformed measurements ({exc})", str(path)) from None
        if not np.isfinite(meas.noise_px) or meas.noise_px <= 0:
            raise InputError(
                "no valid noise_px attribute (the 1-sigma pixel noise the estimators weight "
                "measurements by): add it to the file's global attributes, in px",
                str(path),
            )
        diff = _rig_differences(meas.rig, sensors.make_rig(scenario.sensor))
        if diff:
            raise InputError(
                f"taken with another stereo rig than scenario {scenario.name}'s: "
                + "; ".join(diff)
                + " (give the scenario of the rig that took the data)",
                str(path),
            )
    _check_measured_values(ds, meas, str(path))
    if len(meas.t) < 2:
        raise InputError("needs at least two epochs", str(path))
    if not np.all(np.diff(meas.t) > 0):
        raise InputError("times are not strictly increasing", str(path))
    truth = None
    if (folder / "truth.nc").exists():
        truth = Truth.from_dataset(io.read_netcdf(folder / "truth.nc"))
    return meas, truth


def run_estimate(
    scenario_ref: str,
    estimator: str | None,
    output: Path,
    measurements: Path | None = None,
    seed: int | None = None,
    console: Console | None = None,
    plots: bool = True,
) -> dict[str, Any]:
    """One run: simulate (or read) measurements, estimate, evaluate, write files and figures.

    The estimator is checked against the scenario, and the measurements against both, before
    any work (InputError)."""
    con = console or Console(stderr=True)
    scenario = load_scenario(scenario_ref)
    estimator = _estimator_name(estimator, scenario, scenario_ref)
    scenario = _own_tuning(scenario, estimator, con)
    est = est_base.get_for(estimator, scenario)
    ss = run_seed(scenario.montecarlo.seed if seed is None else seed, 0)
    if measurements is not None:
        meas, truth = _load_measurements(measurements, scenario)
    else:
        with con.status(f"simulating {scenario.name}"):
            truth, meas = simulate(scenario, ss)
        if meas is None:
            raise InputError(
                f"scenario {scenario.name}: {scenario.sensor.kind} measurements are "
                f"not simulated yet, so {estimator} cannot run on it"
            )
    images = meas if isinstance(meas, StereoImageMeasurements) else None
    nothing = _nothing_seen(meas)
    meas, frontend_stats = _front_end_stage(scenario, est, meas, con)
    if getattr(est, "compiled", False) and not kernels_compiled():
        con.print("compiling the numerical kernels (first run after installing: about 30 s, once)")
    with con.status(f"{estimator} on {scenario.name} ({len(meas.t)} epochs)"):
        hist = est.run(context_from_scenario(scenario), meas, run_streams(ss)["estimator"])
    output = Path(output)
    if truth is not None and images is not None and "features" in hist.layout.names():
        truth = with_track_truth(truth, images, meas)  # the tracks' own points
    r = evaluation.evaluate_run(hist, truth) if truth is not None else None
    x_true = evaluation.truth_state(truth, hist) if truth is not None else None
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
    if measurements is not None:
        summary["measurements"] = str(Path(measurements) / "measurements.nc")
    if frontend_stats is not None:
        summary["frontend"] = frontend_stats
    notes = ([nothing] if nothing else []) + [str(w) for w in hist.info.get("warnings", []) or []]
    if notes:  # what the estimator said about its own run
        summary["estimator_warnings"] = notes
    if r is not None:
        summary["rmse"] = {
            k: metrics.rmse_over_time(v, r.t, scenario.window_s) for k, v in r.errors.items()
        }
        summary["nees"] = metrics.consistency(r.nees[None], r.nees_dof, r.t, scenario.window_s)
        summary["nis"] = metrics.consistency(r.nis[None], r.nis_dof[None], r.t, scenario.window_s)
        summary["branches"] = metrics.branch_counts([r.branch])
        if plots:
            assert x_true is not None  # r and x_true both come from the truth
            figures.plot_error_history(
                hist,
                x_true,
                output / "errors.png",
                f"{scenario.name} / {estimator}: errors and ±3σ",
                # the scenario's occlusions are the simulated run's; a user's data have their
                # own gaps, which the figure finds in the history
                occlusions=figures.occlusion_windows(scenario) if measurements is None else (),
                window=scenario.window_s,
            )
    elif plots:  # no truth (a user's own data): the estimates with their ±3σ
        figures.plot_estimates(
            hist, output / "estimates.png", f"{scenario.name} / {estimator}: estimates and ±3σ"
        )
    if not np.isfinite(hist.x).any():
        summary["note"] = (
            f"{estimator} never started: its start condition was not met in this run "
            + str(hist.info.get("start_condition", "(see the estimator's documentation)"))
        )
    _write_scenario(scenario, output)
    summary["warnings"] = assess(summary)
    if truth is not None:
        summary["warnings"] += evaluation.assumption_warnings(scenario.estimator.tuning, truth)
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
    seed: int | None = None,
    plots: bool = True,
) -> dict:
    """A resumable campaign plus its figures (RMSE vs time, NEES vs time). ``seed`` replaces
    the scenario's ``montecarlo.seed`` (run k's streams come from ``SeedSequence(seed,
    spawn_key=(k,))``)."""
    scenario = scenario or load_scenario(scenario_ref)
    if seed is not None:
        scenario = scenario.with_updates(**{"montecarlo.seed": seed})
    estimator = _estimator_name(estimator, scenario, scenario_ref or scenario.name)
    scenario = _own_tuning(scenario, estimator, console or Console(stderr=True))
    runs = runs or scenario.montecarlo.runs
    summary = runner.run_campaign(  # checks the estimator against the scenario first
        scenario,
        estimator,
        runs,
        Path(output),
        workers=workers,
        scheduler=scheduler,
        console=console,
    )
    summary["warnings"] = assess(summary)
    tuning = scenario.estimator.tuning or {}
    if evaluation.states_prior(tuning):
        streams0 = run_streams(run_seed(scenario.montecarlo.seed, 0))
        truth0 = simulate_truth(scenario, streams0["features"], streams0["truth"])
        summary["warnings"] += evaluation.assumption_warnings(tuning, truth0)
    io.write_json(summary, Path(output) / "summary.json")
    if plots:
        campaign_figures(Path(output), scenario, estimator, runs)
    return summary


def campaign_curves(folder: Path, runs: int) -> tuple[np.ndarray, dict, dict]:
    """RMSE-over-runs curves (Hu 2024 eq. 45) and the consistency arrays of a campaign folder.

    Returns ``t`` (n,) s, ``curves`` (quantity key -> (n,) RMSE over runs) and ``cons``: what
    :func:`tumblenav.campaign.runner.collect` gives (``nees``, ``nees_dof``, ``nis``,
    ``nis_dof``, ``runs``) plus ``median`` (key -> (n,) median over runs) and ``nees_per_dof``,
    ``nis_per_dof``: (n,) run averages of each run's value over its dof (NaN where no run has
    one: NEES is stored at 1 Hz, NIS only where an update happened).
    """
    from tumblenav.campaign.store import CampaignStore

    t, errs, cons = runner.collect(CampaignStore(Path(folder)), runs)
    curves = {k: metrics.rmse_over_runs(v) for k, v in errs.items()}
    cons["median"] = {k: metrics.nanmedian_quiet(v, axis=0) for k, v in errs.items()}
    for name in ("nees", "nis") if cons else ():
        v = np.asarray(cons[name], dtype=float)
        dof = np.broadcast_to(np.asarray(cons[f"{name}_dof"], dtype=float), v.shape)
        per_dof = np.where(np.isfinite(v) & (dof > 0), v / np.where(dof > 0, dof, 1.0), np.nan)
        cons[f"{name}_per_dof"] = metrics.nanmean_quiet(per_dof, axis=0)
    return t, curves, cons


def campaign_figures(folder: Path, scenario: Scenario, estimator: str, runs: int) -> None:
    """A campaign's figures: ``rmse_<key>.png`` (RMSE over runs and the median run vs time,
    per quantity) and ``nees.png`` (run-averaged NEES/dof and NIS/dof vs time with their 95%
    chi-square bounds), with the steady-state window shaded and the scenario's occlusions
    hatched."""
    folder = Path(folder)
    t, curves, cons = campaign_curves(folder, runs)
    if not curves:
        return
    n_runs, window = len(cons["runs"]), scenario.window_s
    occlusions = figures.occlusion_windows(scenario)
    for key, y in curves.items():
        r = metrics.rmse_over_time(y, t, window)
        unit = figures.quantity_unit(key)
        figures.plot_rmse(
            {f"{estimator} RMSE": (t, y), f"{estimator} median": (t, cons["median"][key])},
            key,
            folder / f"rmse_{key}.png",
            f"{scenario.name} / {estimator}: RMSE over {n_runs} runs (Hu 2024 eq. 45) and "
            f"median; {r:.3g}{'' if unit == '-' else ' ' + unit} over the window "
            f"{window[0]:g}-{window[1]:g} s",
            window=window,
            occlusions=occlusions,
        )
    panels = []
    for name in ("nees", "nis"):
        c = metrics.consistency(cons[name], cons[f"{name}_dof"], t, window)
        what = "full state" if name == "nees" else "typical"
        panels.append(
            figures.ConsistencyPanel(
                f"{name.upper()} / dof ({what} dof {c['dof']})",
                {f"run-average {name.upper()} / dof": cons[f"{name}_per_dof"]},
                tuple(c["bounds95"]) if c["bounds95"] else None,
            )
        )
    figures.plot_consistency(
        t,
        panels,
        None,
        folder / "nees.png",
        f"{scenario.name} / {estimator}: consistency over {n_runs} runs (95% bounds for the "
        f"average of {n_runs} runs)",
        window=window,
        occlusions=occlusions,
    )


def _outside(c: dict | None) -> str | None:
    """'above' / 'below' when a consistency statistic's mean lies outside its 95% bounds."""
    if not c or c.get("mean") is None or not c.get("bounds95"):
        return None
    lo, hi = c["bounds95"]
    return "above" if c["mean"] > hi else "below" if c["mean"] < lo else None


def assess(summary: dict[str, Any]) -> list[str]:
    """One line for each thing in a summary a user must not miss: a mean NEES or NIS outside
    its 95% chi-square bounds (and what that means), runs that never started, diverged or
    failed. Empty when the result can be taken as it is."""
    out = []
    meaning = {
        ("nees", "above"): "the covariance is over-confident: the errors are larger than the "
        "filter claims, so its 3-sigma bounds cannot be trusted",
        ("nees", "below"): "the covariance is conservative: the errors are smaller than the "
        "filter claims",
        ("nis", "above"): "the innovations are larger than the filter predicts (measurement or "
        "process noise too small, or a wrong model)",
        ("nis", "below"): "the innovations are smaller than the filter predicts (measurement "
        "noise set too large)",
    }
    for name in ("nees", "nis"):
        side = _outside(summary.get(name))
        if side:
            c = summary[name]
            lo, hi = c["bounds95"]
            out.append(
                f"mean {name.upper()}/dof {c['mean']:.3g} is {side} its 95% bounds "
                f"[{lo:.3g}, {hi:.3g}]: {meaning[(name, side)]}"
            )
        negative = (summary.get(name) or {}).get("negative_epochs")
        if negative:
            which = "state covariance" if name == "nees" else "innovation covariance"
            out.append(
                f"{name.upper()} is negative at {negative} epoch(s) of the window: the "
                f"estimator's reported {which} is not positive semi-definite there, so "
                f"its mean {name.upper()} cannot be read (a defect of the estimator: please "
                "report it)"
            )
    runs = summary.get("runs") or 0
    if summary.get("note"):
        out.append(summary["note"])
    elif summary.get("runs_without_estimate"):
        out.append(
            f"{summary['runs_without_estimate']} of {runs} runs produced no estimate in the "
            "steady-state window (never started, or stopped): they are left out of the RMSE"
        )
    diverged = (summary.get("skipped") or {}).get("diverged", 0)
    if diverged:
        out.append("the filter diverged and was stopped: the estimates after that are NaN")
    if summary.get("runs_diverged"):
        out.append(f"{summary['runs_diverged']} of {runs} runs diverged and were stopped")
    skipped = summary.get("skipped") or {}
    reinit = summary.get("runs_reinitialised") or (1 if skipped.get("reinitialised") else 0)
    if reinit:
        out.append(
            f"{reinit} of {runs} run(s) lost track and started again from the measurements "
            "(the errors around each restart are in the window's RMSE)"
        )
    alarm = summary.get("runs_nis_alarm") or (1 if skipped.get("nis_alarm") else 0)
    if alarm:
        out.append(
            f"{alarm} of {runs} run(s) raised the lost-track alarm (the innovations failed their "
            "chi-square test over a window): the model does not fit those runs' measurements"
        )
    note = metrics.branch_warning(summary.get("branches"))
    if note:
        out.append(note)
    out.extend(summary.get("estimator_warnings") or [])
    if summary.get("runs_failed"):
        out.append(
            f"{summary['runs_failed']} run(s) failed with an error (seeds and errors under "
            "'failed' in summary.json)"
        )
    return out


def print_summary(summary: dict[str, Any], console: Console) -> None:
    """summary.json as a table: RMSE over the window, and for campaigns the median run;
    NEES/NIS outside their bounds are marked, and every warning is printed below."""
    w = summary["window_s"]  # written by every run and campaign
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
            side = _outside(c)
            value = f"{c['mean']:.3g}" + (f" [bold red]({side} bounds)[/]" if side else " (ok)")
            row = [f"{name.upper()}/dof (95%: {lo:.3g}-{hi:.3g})", value]
            table.add_row(*(row + ([""] if per_run else [])))
    console.print(table)
    for line in summary.get("warnings") or []:
        console.print(f"[bold yellow]warning:[/] {escape(line)}", highlight=False)


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


def run_compare(
    scenario_ref: str,
    estimators: list[str],
    runs: int | None,
    output: Path,
    workers: int | None = None,
    scheduler: str | None = None,
    console: Console | None = None,
    seed: int | None = None,
    plots: bool = True,
) -> dict[str, Any]:
    """Head to head: one resumable campaign per estimator (``output/<estimator>/``) on the
    same truth, measurements and seeds (run k's streams come from the same base seed, so every
    estimator sees the very same simulated runs), one table, overlaid figures and a summary
    with one case per estimator. Every estimator is checked against the scenario before any
    work (InputError naming the ones that cannot run and why)."""
    import time

    scenario = load_scenario(scenario_ref)
    if seed is not None:
        scenario = scenario.with_updates(**{"montecarlo.seed": seed})
    names = [e.strip() for e in estimators if e.strip()]
    if len(names) < 2:
        raise InputError("compare needs at least two estimators: -e NAME,NAME,...", "--estimator")
    if len(set(names)) != len(names):
        raise InputError(f"an estimator is named twice: {', '.join(names)}", "--estimator")
    refused = []
    scenarios: dict[str, Scenario] = {}
    for name in names:
        try:
            scenarios[name] = _scenario_for(name, scenario)
        except InputError as exc:
            refused.append(f"{name} ({exc})")
    if refused:
        raise InputError(
            f"cannot run on scenario {scenario.name}: " + "; ".join(refused), "--estimator"
        )
    runs = runs or scenario.montecarlo.runs
    output = Path(output)
    _keeps_earlier_comparison(output, names)
    con = console or Console(stderr=True)
    cases = []
    for name in names:
        folder = output / name
        before = len(CampaignStore(folder).done()) if folder.exists() else 0
        t0 = time.perf_counter()
        s = runner.run_campaign(
            scenarios[name], name, runs, folder, workers=workers, scheduler=scheduler, console=con
        )
        sc = scenarios[name]
        if sc.sensor != scenario.sensor:  # its own measurements, from the same truth
            s["sensor"] = f"own {sc.sensor.kind} sensor (other_sensors)"
        if sc.estimator.tuning != scenario.estimator.tuning:
            s["tuning"] = f"defaults (the scenario's tuning is for {scenario.estimator.name})"
        computed = s["runs"] + s.get("runs_failed", 0) - min(before, runs)
        s["warnings"] = assess(s)
        if computed > 0:
            s["seconds_per_run"] = (time.perf_counter() - t0) / computed
        io.write_json(s, folder / "summary.json")
        cases.append(s)
    summary: dict[str, Any] = {
        "scenario": scenario.name,
        "runs": runs,
        "base_seed": scenario.montecarlo.seed,
        "window_s": list(scenario.window_s),
        "same_measurements": all(scenarios[n].sensor == scenario.sensor for n in names),
        "cases": cases,
    }
    io.write_json(summary, output / "summary.json")
    if plots:
        compare_figures(output, scenario, names, runs)
    return summary


def _scenario_for(name: str, scenario: Scenario) -> Scenario:
    """The scenario estimator ``name`` runs on in a comparison: ``scenario``, or, when its
    sensor gives what the estimator cannot use, the same scenario with the first of its
    ``other_sensors`` the estimator runs on (the same truth and seeds: the truth does not
    depend on the sensor); the first refusal otherwise. The scenario's ``estimator.tuning``
    is for its own estimator: one that does not take those settings runs with its defaults."""
    first: InputError | None = None
    for sc in [scenario] + [
        scenario.with_updates(sensor=alt.model_dump(), other_sensors=[])
        for alt in scenario.other_sensors
    ]:
        for candidate in (sc, _with_default_tuning(sc, name)):
            try:
                est_base.get_for(name, candidate)
                return candidate
            except InputError as exc:
                first = first or exc
    assert first is not None
    raise first


def _own_tuning(scenario: Scenario, name: str, con: Console) -> Scenario:
    """The scenario's ``estimator.tuning`` is for its own estimator: another one named with
    ``-e`` that does not take those settings runs with its defaults (said on the console)."""
    other = _with_default_tuning(scenario, name)
    if other is scenario:
        return scenario
    try:
        est_base.get_for(name, scenario)
        return scenario
    except InputError as first:
        try:
            est_base.get_for(name, other)
        except InputError:
            raise first from None  # a refusal that is not about the tuning stays as it was
        con.print(
            f"note: the scenario's estimator.tuning is for {scenario.estimator.name}; "
            f"{name} runs with its own defaults"
        )
        return other


def _with_default_tuning(scenario: Scenario, name: str) -> Scenario:
    if name == scenario.estimator.name or not scenario.estimator.tuning:
        return scenario
    return scenario.with_updates(**{"estimator.tuning": {}})


def compare_figures(folder: Path, scenario: Scenario, names: list[str], runs: int) -> None:
    """Overlaid figures of a comparison: ``rmse_<key>.png`` (each estimator's RMSE over runs
    vs time, per quantity any of them estimates) and ``nees.png`` (each estimator's
    run-averaged NEES/dof against its own 95% bounds, one panel each)."""
    folder = Path(folder)
    data = {name: campaign_curves(folder / name, runs) for name in names}
    window = scenario.window_s
    occlusions = figures.occlusion_windows(scenario)
    keys = list(dict.fromkeys(k for _, curves, _ in data.values() for k in curves))
    for key in keys:
        curves = {f"{n} RMSE": (t, c[key]) for n, (t, c, _) in data.items() if key in c}
        figures.plot_rmse(
            curves,
            key,
            folder / f"rmse_{key}.png",
            f"{scenario.name}: RMSE over {runs} runs, same runs for every estimator",
            window=window,
            occlusions=occlusions,
        )
    panels, t_ref = [], None
    for name, (t, _, cons) in data.items():
        if not cons:
            continue
        t_ref = t if t_ref is None else t_ref
        c = metrics.consistency(cons["nees"], cons["nees_dof"], t, window)
        panels.append(
            figures.ConsistencyPanel(
                f"{name}: NEES / dof (dof {c['dof']})",
                {f"{name} run-average NEES / dof": cons["nees_per_dof"]},
                tuple(c["bounds95"]) if c["bounds95"] else None,
            )
        )
    if panels and t_ref is not None:
        figures.plot_consistency(
            t_ref,
            panels,
            None,
            folder / "nees.png",
            f"{scenario.name}: consistency over {runs} runs (95% bounds for the average of "
            f"{runs} runs)",
            window=window,
            occlusions=occlusions,
        )


def print_comparison(summary: dict[str, Any], console: Console) -> None:
    """The head-to-head table: RMSE per quantity over the steady-state window, mean NEES and
    NIS with their 95% bounds (marked when outside) and the fraction of the window inside,
    runs that failed, never started or diverged, and the time per run."""
    cases = summary.get("cases") or []
    w = summary.get("window_s") or [0.0, 0.0]
    console.print(
        f"[bold]{summary.get('scenario')}[/]: {summary.get('runs')} runs per estimator, the same "
        f"runs (base seed {summary.get('base_seed')}) for each"
        + (
            ""
            if summary.get("same_measurements", True)
            else " (the same truth; some estimators with their own sensor's measurements)"
        )
        + f"; steady-state window {w[0]:g}-{w[1]:g} s"
    )
    table = Table()
    table.add_column("quantity")
    for c in cases:
        table.add_column(str(c.get("estimator")), justify="right")
    keys = list(dict.fromkeys(k for c in cases for k in (c.get("rmse") or {})))
    for k in keys:
        row = [f"RMSE {k}"]
        for c in cases:
            v = (c.get("rmse") or {}).get(k)
            row.append("-" if v is None else f"{v:.4g}")
        table.add_row(*row)
    for name in ("nees", "nis"):
        row = [f"{name.upper()}/dof (95% bounds)"]
        for c in cases:
            s = c.get(name) or {}
            if s.get("mean") is None:
                row.append("-")
                continue
            lo, hi = s["bounds95"]
            side = _outside(s)
            mark = f" [bold red]{side}[/]" if side else ""
            row.append(f"{s['mean']:.3g} ({lo:.2g}-{hi:.2g}){mark}")
        table.add_row(*row)
        row = [f"  {name.upper()} in bounds (window)"]
        for c in cases:
            frac = (c.get(name) or {}).get("inside_fraction")
            row.append("-" if frac is None else f"{100 * frac:.0f}%")
        table.add_row(*row)
    for label, key in (
        ("runs failed", "runs_failed"),
        ("runs without estimate", "runs_without_estimate"),
        ("runs diverged", "runs_diverged"),
    ):
        table.add_row(label, *[str(c.get(key, 0)) for c in cases])
    if any(c.get("sensor") for c in cases):
        table.add_row("measurements", *[c.get("sensor") or "the scenario's sensor" for c in cases])
    if any(c.get("tuning") for c in cases):
        table.add_row("settings", *[c.get("tuning") or "the scenario's tuning" for c in cases])
    table.add_row(
        "time per run (s)",
        *[f"{c['seconds_per_run']:.3g}" if c.get("seconds_per_run") else "(stored)" for c in cases],
    )
    console.print(table)
    for c in cases:
        for line in c.get("warnings") or []:
            console.print(
                f"[bold yellow]warning ({escape(str(c.get('estimator')))}):[/] {escape(line)}",
                highlight=False,
            )
