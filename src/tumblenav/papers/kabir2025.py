"""Kabir & Bai, Sensors 2025, Sec. 3: the GP study (Fig. 4) and the UKF-GP study (Figs. 5-9).

GP study (Sec. 3.1): one feature at [1, 1, 1] m, f_T in {0.025, 0.075, 0.125, 0.175} Hz,
T_train in {75, ..., 3000} s, predictions for 2000 s after the training span, 20 runs each:
prediction RMSE of ``[u_R, v_R, u_L]`` (rad) and training time.  Every T_train of one f_T uses
the same runs' seeds.  A run counts as "badly trained" when its RMSE exceeds 1e-5 rad (the
issue's target).

UKF-GP study (Sec. 3.2): the built-in kabir2025 scenario (five features, paper tuning per
frequency via :func:`tumblenav.estimators.ukf.paper_tuning`), 3000 s, occlusion from 1500 s,
20 runs per frequency, for ``ukf`` (occluded), ``ukf`` without occlusion (the paper's
"Benchmark"), ``ukf-gp`` (the paper's fixed R, and beyond the paper the GP's predictive
variance in R), and ``ukf-mult`` occluded and not; RMSE over the occlusion window
[1500, 3000] s.  All cases of one frequency use the same seeds (common random numbers).
"""

from __future__ import annotations

import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import Progress

from tumblenav import io
from tumblenav import plots as figures
from tumblenav.campaign import runner
from tumblenav.campaign.store import CampaignStore
from tumblenav.dynamics import polhode_period
from tumblenav.errors import InputError
from tumblenav.estimators import ukf  # the kabir2025 package's names, re-exported
from tumblenav.estimators.kabir2025 import gp as gpm
from tumblenav.frontends import projections as proj
from tumblenav.measurements import StereoMeasurements
from tumblenav.pipeline import run_montecarlo
from tumblenav.scenario import Scenario, load_scenario
from tumblenav.sensors.stereo import project

FREQS_HZ = (0.025, 0.075, 0.125, 0.175)  # Kabir 2025 Sec. 3
T_TRAIN_S = (75.0, 100.0, 200.0, 500.0, 1000.0, 1500.0, 2000.0, 2500.0, 3000.0)  # Sec. 3.1
T_PREDICT_S = 2000.0
GP_FEATURE_M = (1.0, 1.0, 1.0)
OCCLUSION_WINDOW_S = (1500.0, 3000.0)
GOOD_RMSE_RAD = 1e-5
# (label, estimator, occluded, extra tuning)
FILTERS: tuple[tuple[str, str, bool, dict[str, Any]], ...] = (
    ("ukf", "ukf", True, {}),
    ("benchmark", "ukf", False, {}),
    # the paper's pseudo-measurements: the sensor's R, no drift term (its truth is torque-free)
    ("ukf-gp", "ukf-gp", True, {"gp_drift_in_r": False}),
    ("ukf-gp-predictive", "ukf-gp", True, {"gp_variance": "predictive", "gp_drift_in_r": False}),
    ("ukf-mult", "ukf-mult", True, {}),
    ("ukf-mult-benchmark", "ukf-mult", False, {}),
)
UNIT = np.array([2.0, 1.0, 2.0]) / 3.0  # omega0 = 2 pi f_T [2/3, 1/3, 2/3] (printed rounded)


def scenario_for(f_T_hz: float, base: Scenario | None = None) -> Scenario:
    """The kabir2025 scenario at tumbling frequency ``f_T`` with the paper's tuning and its
    truth-based start (:func:`with_paper_assumptions`)."""
    base = base or load_scenario("kabir2025")
    tuning = {**base.estimator.tuning, **ukf.paper_tuning(f_T_hz)}
    sc = base.with_updates(
        **{
            "target.omega0_T_rad_s": (2.0 * np.pi * f_T_hz * UNIT).tolist(),
            "estimator.tuning": tuning,
            "steady_state_window_s": list(OCCLUSION_WINDOW_S),
            # the paper's truth is torque-free (the built-in's quiet disturbance is ours)
            "process_noise.disturb_truth": False,
        }
    )
    return with_paper_assumptions(sc)


def tumbling_frequency_hz(scenario: Scenario) -> float:
    """``f_T = |omega0| / (2 pi)`` of the scenario's truth: Kabir 2025 Sec. 3 writes
    ``omega0 = 2 pi f_T u`` with the unit vector ``u = [2/3, 1/3, 2/3]`` (printed rounded to
    [0.67, 0.33, 0.67])."""
    return float(np.linalg.norm(scenario.target.omega0_T_rad_s) / (2.0 * np.pi))


# Kabir 2025 Sec. 3.2's initial guess relative to the truth: omega x 1.75, the attitude
# offset [0.9707, 0.1386, 0.1386, 0.1386] (scalar first: 27.8 deg about [1, 1, 1]) against its
# q0 = [1, 0, 0, 0], k = 0, every feature component + 0.7 m
PAPER_RATE_FACTOR = 1.75
PAPER_Q_OFFSET_WXYZ = (0.9707, 0.1386, 0.1386, 0.1386)
PAPER_FEATURE_OFFSET_M = 0.7


def known_mass_centre(scenario: Scenario) -> dict[str, Any]:
    """Kabir 2025 Sec. 2.1's assumption that the target's mass-centre motion is known, taken
    from the simulated truth and handed to the filter as its settings."""
    return {
        "mass_centre_L_m": list(map(float, scenario.target.r0_L_m)),
        "mass_centre_velocity_L_m_s": list(map(float, scenario.target.v0_L_m_s)),
    }


def paper_start(
    scenario: Scenario,
    rate_factor: float = PAPER_RATE_FACTOR,
    q_offset_wxyz: Any = PAPER_Q_OFFSET_WXYZ,
    feature_offset_m: float = PAPER_FEATURE_OFFSET_M,
) -> dict[str, Any]:
    """Kabir 2025 Sec. 3.2's truth-based initial guess, made here from the scenario's truth
    and handed to the filter as ``init: given`` settings: ``omega0 x rate_factor``,
    ``q = offset (x) q0``, ``k = 0``, ``p + feature_offset_m``."""
    from tumblenav import rotations as rot
    from tumblenav.simulation import draw_features

    tg = scenario.target
    off = np.asarray(q_offset_wxyz, dtype=float)
    if not np.linalg.norm(off) > 0:
        raise InputError("the paper start's attitude offset must be a nonzero quaternion")
    off = rot.quat_normalize(rot.from_scalar_first(off))
    q = rot.quat_multiply(off, rot.quat_normalize(np.asarray(tg.q0_TI, float)))
    features = draw_features(scenario, np.random.default_rng(0))[0]
    return {
        "init": "given",
        "init_omega_rad_s": (rate_factor * np.asarray(tg.omega0_T_rad_s, float)).tolist(),
        "init_q_TI": q.tolist(),
        "init_features_m": (features + feature_offset_m).tolist(),
    }


def with_paper_assumptions(scenario: Scenario, **start: Any) -> Scenario:
    """``scenario`` with Kabir 2025's truth-based assumptions in the estimator's settings:
    the known mass centre (:func:`known_mass_centre`) and the paper's start
    (:func:`paper_start`, its keyword arguments in ``start``)."""
    tuning = {
        **scenario.estimator.tuning,
        **known_mass_centre(scenario),
        **paper_start(scenario, **start),
    }
    return scenario.with_updates(**{"estimator.tuning": tuning})


# --- GP study (Fig. 4) ---------------------------------------------------------------------


def _gp_job(args: tuple[float, float, int, int]) -> dict[str, Any]:
    from tumblenav.simulation import simulate

    f_T, T_train, seed, k = args
    base = scenario_for(f_T)
    listed = base.target.features_T_m
    assert isinstance(listed, list)  # the kabir2025 scenario lists its features
    feats = [list(GP_FEATURE_M)] + [list(p) for p in listed[1:]]
    sc = base.with_updates(  # feature 0 is the study's; the scenario needs three or more
        **{
            "target.features_T_m": feats,
            "duration_s": T_train + T_PREDICT_S,
            "occlusion.loss_from_s": None,
            "steady_state_window_s": None,
        }
    )
    truth, meas = simulate(sc, np.random.SeedSequence(seed).spawn(k + 1)[k])
    assert isinstance(meas, StereoMeasurements)  # the kabir2025 scenario has a stereo rig
    w, _ = proj.normalised(meas)
    f = meas.rig.left.focal_px
    cu, cv = meas.rig.left.principal_point_px
    uv, _ = project(meas.rig, truth.features_C)  # noise-free, (n, 2, 1, 2) px
    w_true = np.stack(
        [(uv[:, 1, 0, 0] - cu) / f, (uv[:, 1, 0, 1] - cv) / f, (uv[:, 0, 0, 0] - cu) / f], axis=1
    )
    t = meas.t
    train = t <= T_train
    sigma_p = float(meas.noise_px / f)
    out: dict[str, Any] = {"f_T_hz": f_T, "T_train_s": T_train, "run": k}
    try:
        fit = gpm.fit_icm_gp(t[train], w[train, 0, :3], sensor_noise_std=sigma_p)
    except Exception as exc:  # noqa: BLE001 - recorded per run, the study goes on
        out.update(error=str(exc), gp_rmse_rad=float("nan"), train_time_s=float("nan"), ok=False)
        return out
    mean, _ = fit.predict(t[~train])
    err = mean - w_true[~train]
    out.update(
        gp_rmse_rad=float(np.sqrt(np.mean(err**2))),
        train_time_s=fit.train_time_s,
        ok=bool(fit.ok),
        reason=fit.reason,
        periods_s=fit.periods_s.tolist(),
        lengthscales=fit.lengthscales.tolist(),
    )
    return out


def gp_study(
    output: Path, runs: int, workers: int | None, console: Console | None, seed: int
) -> list[dict[str, Any]]:
    """Run (or resume: one JSON per run) the GP study; one case per (f_T, T_train)."""
    folder = Path(output) / "gp_study"
    folder.mkdir(parents=True, exist_ok=True)
    jobs, paths = [], []
    for f in FREQS_HZ:
        for T in T_TRAIN_S:
            for k in range(runs):
                p = folder / f"f{f:.3f}_T{T:.0f}_run{k:03d}.json"
                if not p.exists():
                    jobs.append((f, T, seed, k))
                    paths.append(p)
    if jobs:
        with (
            ProcessPoolExecutor(max_workers=workers) as ex,
            Progress(console=console, transient=True) as bar,
        ):
            task = bar.add_task("GP study", total=len(jobs))
            for p, result in zip(paths, ex.map(_gp_job, jobs), strict=True):
                io.write_json(result, p)
                bar.advance(task)
    cases = []
    for f in FREQS_HZ:
        Tp = _polhode(f)
        for T in T_TRAIN_S:
            res = [
                json.loads((folder / f"f{f:.3f}_T{T:.0f}_run{k:03d}.json").read_text())
                for k in range(runs)
            ]
            rmse = np.array([_num(r.get("gp_rmse_rad")) for r in res])
            tt = np.array([_num(r.get("train_time_s")) for r in res])
            cases.append(
                {
                    "f_T_hz": f,
                    "T_train_s": T,
                    "T_p_s": Tp,
                    "T_train_over_T_p": T / Tp,
                    "runs": runs,
                    "gp_rmse_rad": float(np.nanmedian(rmse)) if np.isfinite(rmse).any() else None,
                    "gp_rmse_rad_max": float(np.nanmax(rmse)) if np.isfinite(rmse).any() else None,
                    "gp_rmse_rad_runs": rmse.tolist(),
                    "train_time_s": float(np.nanmedian(tt)) if np.isfinite(tt).any() else None,
                    "train_time_s_runs": tt.tolist(),
                    "badly_trained": int(np.sum(~(rmse <= GOOD_RMSE_RAD))),
                    "flagged_not_ok": int(sum(not r.get("ok", False) for r in res)),
                    "paper_values": {"note": "Kabir 2025 Fig. 4 (box plots only)"},
                }
            )
    return cases


def _num(x: Any) -> float:
    """JSON null (a NaN written by io.write_json) back to NaN."""
    return float("nan") if x is None else float(x)


def _polhode(f_T: float) -> float:
    sc = scenario_for(f_T)
    I = np.diag(sc.target.inertia_matrix)
    return float(polhode_period(I, np.asarray(sc.target.omega0_T_rad_s)))


# --- UKF-GP study (Figs. 5-9) ----------------------------------------------------------------


def _filter_dir(output: Path, f: float, label: str) -> Path:
    return Path(output) / "ukf_gp_study" / f"f{f:.3f}" / label


def ukf_gp_study(
    output: Path,
    runs: int,
    workers: int | None,
    console: Console | None,
    scheduler: str | None = None,
) -> list[dict[str, Any]]:
    cases = []
    for f in FREQS_HZ:
        base = scenario_for(f)
        for label, est, occluded, extra in FILTERS:
            sc = base.with_updates(**{"estimator.tuning": {**base.estimator.tuning, **extra}})
            if not occluded:
                sc = sc.with_updates(**{"occlusion.loss_from_s": None})
            s = run_montecarlo(
                sc.name,
                est,
                runs,
                _filter_dir(output, f, label),
                workers,
                scheduler,
                console=console,
                scenario=sc,
            )
            cases.append(
                {
                    "f_T_hz": f,
                    "estimator": est,
                    "occluded": occluded,
                    "label": label,
                    **({"gp_variance": extra["gp_variance"]} if "gp_variance" in extra else {}),
                    "runs": s["runs"],
                    "runs_failed": s["runs_failed"],
                    "window_s": s["window_s"],
                    "rmse": s.get("rmse", {}),
                    "per_run": s.get("per_run"),
                    "nees": s.get("nees"),
                    "paper_values": {"note": "Kabir 2025 Figs. 5-9 (plots only)"},
                }
            )
    return cases


def reproduce(
    output: Path,
    runs: int | None = None,
    workers: int | None = None,
    console: Console | None = None,
    scheduler: str | None = None,
) -> dict[str, Any]:
    runs = runs or load_scenario("kabir2025").montecarlo.runs
    seed = load_scenario("kabir2025").montecarlo.seed
    gp_cases = gp_study(Path(output), runs, workers, console, seed)
    filter_cases = ukf_gp_study(Path(output), runs, workers, console, scheduler)
    _gp_figures(Path(output), gp_cases)
    _filter_figures(Path(output), runs)
    summary = {
        "paper": "kabir2025",
        "scenario": "kabir2025",
        "cases": filter_cases,
        "gp_study": gp_cases,
    }
    io.write_json(summary, Path(output) / "summary.json")
    return summary


# --- figures -------------------------------------------------------------------------------


def _gp_figures(output: Path, cases: list[dict[str, Any]]) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    width = 0.18
    for j, f in enumerate(FREQS_HZ):
        cs = [c for c in cases if c["f_T_hz"] == f]
        pos = np.arange(len(cs)) + (j - 1.5) * width
        for ax, key in zip(axes, ("gp_rmse_rad_runs", "train_time_s_runs"), strict=True):
            data = [np.asarray(c[key], float)[np.isfinite(c[key])] for c in cs]
            bp = ax.boxplot(
                data, positions=pos, widths=width * 0.9, patch_artist=True, manage_ticks=False
            )
            for b in bp["boxes"]:
                b.set_facecolor(f"C{j}")
            ax.plot([], [], color=f"C{j}", lw=6, label=f"f_T = {f} Hz")
    axes[0].axhline(GOOD_RMSE_RAD, color="k", ls=":", lw=1)
    axes[0].set_ylabel("prediction RMSE over 2000 s [rad]")
    axes[1].set_ylabel("training time [s]")
    for ax in axes:
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    axes[1].set_xticks(range(len(T_TRAIN_S)), [f"{T:.0f}" for T in T_TRAIN_S])
    axes[1].set_xlabel("T_train [s]")
    axes[0].legend(fontsize=8)
    axes[0].set_title("Kabir 2025 Fig. 4 analogue: GP prediction RMSE and training time")
    figures.save(fig, output / "fig4_gp_study.png")


def _filter_figures(output: Path, runs: int) -> None:
    import matplotlib.pyplot as plt

    from tumblenav.evaluation import metrics

    shown = ("ukf", "benchmark", "ukf-gp")
    per_run: dict[tuple[float, str], dict[str, np.ndarray]] = {}
    for n, f in enumerate(FREQS_HZ):
        curves: dict[str, dict[str, tuple]] = {"attitude_deg": {}, "rate_deg_s": {}}
        for label, *_ in FILTERS:
            folder = _filter_dir(output, f, label)
            if not folder.exists():
                continue
            t, errs, _ = runner.collect(CampaignStore(folder), runs)
            w = (t >= OCCLUSION_WINDOW_S[0]) & (t <= OCCLUSION_WINDOW_S[1])
            per_run[(f, label)] = {
                k: np.sqrt(metrics.nanmean_quiet(e[:, w] ** 2, axis=1)) for k, e in errs.items()
            }
            if label in shown:
                for key in curves:
                    if key in errs:
                        curves[key][f"{label} run 0"] = (t, errs[key][0])
                        curves[key][f"{label} RMSE"] = (t, metrics.rmse_over_runs(errs[key]))
        for key, c in curves.items():
            if c:
                figures.plot_rmse(
                    c,
                    key,
                    output / f"fig{5 + n}_{key}_f{f:.3f}.png",
                    f"Kabir 2025 Fig. {5 + n} analogue (f_T = {f} Hz): run 0 and the RMSE "
                    "over runs",
                    window=OCCLUSION_WINDOW_S,
                )
    keys = ("attitude_deg", "rate_deg_s", "inertia", "features_m")
    fig, axes = plt.subplots(1, len(keys), figsize=(16, 4))
    labels = [lab for lab, *_ in FILTERS]
    width = 0.8 / len(labels)
    for ax, key in zip(axes, keys, strict=True):
        for j, lab in enumerate(labels):
            data, pos = [], []
            for i, f in enumerate(FREQS_HZ):
                v = per_run.get((f, lab), {}).get(key)
                if v is not None and np.isfinite(v).any():
                    data.append(v[np.isfinite(v)])
                    pos.append(i + (j - (len(labels) - 1) / 2) * width)
            if data:
                bp = ax.boxplot(
                    data, positions=pos, widths=width * 0.9, patch_artist=True, manage_ticks=False
                )
                for b in bp["boxes"]:
                    b.set_facecolor(f"C{j}")
            ax.plot([], [], color=f"C{j}", lw=6, label=lab)
        ax.set_yscale("log")
        ax.set_xticks(range(len(FREQS_HZ)), [str(f) for f in FREQS_HZ])
        ax.set_xlabel("f_T [Hz]")
        ax.set_title(f"RMSE in [1500, 3000] s: {key}", fontsize=9)
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7)
    figures.save(fig, output / "fig9_rmse_boxplots.png")
