"""Hu, Wu, Meng, Wu, Sensors 2024, Sec. 5: the Monte Carlo study at four noise levels.

Cases: angular resolution 0.1e-5, 0.5e-5, 2e-5, 5e-5 rad x estimators ekf-dpacf and
ekf-baseline, 500 runs each by default, on the built-in hu2024 scenario. Every case of one
noise level uses the same seeds, so both estimators see the same trajectories, features and
noise (common random numbers). Figures: analogues of Fig. 5 (DPACF attitude RMSE per noise
level) and Figs. 6-11 (ekf-dpacf vs ekf-baseline RMSE at 2e-5 rad).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.console import Console

from tumblenav import io
from tumblenav import plots as figures
from tumblenav.papers import case_from_campaign
from tumblenav.pipeline import campaign_curves, run_montecarlo
from tumblenav.scenario import load_scenario

NOISE_RAD = (0.1e-5, 0.5e-5, 2e-5, 5e-5)  # Hu 2024 Sec. 5 (1)
ESTIMATORS = ("ekf-dpacf", "ekf-baseline")
# The paper's setting (Hu 2024 Sec. 5): its filter noise, sigma_t^2 = 2e-6 and sigma_r^2 =
# 2.5e-5, on a torque-free truth, the inertia least squares torque-free (eq. 10). The built-in
# hu2024 carries small disturbances that its filter assumes instead (issue 18); `reproduce`
# keeps the paper's.
PAPER_SETTING = {
    "process_noise.translational_m2_s4": 2e-6,
    "process_noise.rotational_rad2_s4": 2.5e-5,
    "process_noise.disturb_truth": False,
    "estimator.tuning": {},
}
# The paper shows figures only; these are the targets at 2e-5 rad, window [150, 200] s.
TARGETS_2E5 = {
    "attitude_deg": 0.5,
    "rate_deg_s": 0.05,
    "position_m": 0.005,
    "velocity_m_s": 0.001,
    "features_m": 0.005,
    "inertia": 0.01,
}

_LABELS = {
    "attitude_deg": ("attitude RMSE [deg]", "fig6_attitude"),
    "rate_deg_s": ("rate RMSE [deg/s]", "fig7_rate"),
    "inertia": ("inertia-ratio RMSE [-]", "fig8_inertia"),
    "features_m": ("feature RMSE [m]", "fig9_features"),
    "position_m": ("position RMSE [m]", "fig10_position"),
    "velocity_m_s": ("velocity RMSE [m/s]", "fig11_velocity"),
}


def case_dir(output: Path, noise: float, estimator: str) -> Path:
    return Path(output) / f"noise_{noise:.1e}" / estimator


def reproduce(
    output: Path,
    runs: int | None = None,
    workers: int | None = None,
    console: Console | None = None,
    scheduler: str | None = None,
) -> dict[str, Any]:
    base = load_scenario("hu2024").with_updates(**PAPER_SETTING)
    runs = runs or base.montecarlo.runs
    cases = []
    for noise in NOISE_RAD:
        sc = base.with_updates(**{"sensor.noise.angular_rad": noise})
        for est in ESTIMATORS:
            s = run_montecarlo(
                sc.name,
                est,
                runs,
                case_dir(output, noise, est),
                workers,
                scheduler,
                console=console,
                scenario=sc,
            )
            case = {
                "noise_rad": noise,
                "estimator": est,
                **case_from_campaign(s),
                "paper_values": {"note": "Hu 2024 gives figures only (Figs. 5-11)"},
            }
            if noise == 2e-5 and est == "ekf-dpacf":
                case["targets"] = TARGETS_2E5
            cases.append(case)
    _figures(Path(output), runs, base.window_s)
    summary = {"paper": "hu2024", "scenario": "hu2024", "cases": cases}
    io.write_json(summary, Path(output) / "summary.json")
    return summary


def _figures(output: Path, runs: int, window) -> None:
    fig5 = {}
    for noise in NOISE_RAD:
        t, curves, cons = campaign_curves(case_dir(output, noise, "ekf-dpacf"), runs)
        if "dpacf_attitude_deg" in curves:
            fig5[f"{noise:.1e} rad RMSE"] = (t, curves["dpacf_attitude_deg"])
            fig5[f"{noise:.1e} rad median"] = (t, cons["median"]["dpacf_attitude_deg"])
    if fig5:
        figures.plot_rmse(
            fig5,
            "DPACF attitude error [deg]",
            output / "fig5_dpacf_attitude.png",
            "Hu 2024 Fig. 5 analogue: principal-frame attitude from DPACF (RMSE, median)",
        )
    per = {est: campaign_curves(case_dir(output, 2e-5, est), runs) for est in ESTIMATORS}
    for key, (label, name) in _LABELS.items():
        curves = {}
        for est, (t, c, cons) in per.items():
            if key in c:
                curves[f"{est} RMSE"] = (t, c[key])
                curves[f"{est} median"] = (t, cons["median"][key])
        if curves:
            figures.plot_rmse(
                curves,
                label.replace("RMSE", "error"),
                output / f"{name}.png",
                f"Hu 2024 {name.split('_')[0]} analogue, 2e-5 rad, {runs} runs "
                "(RMSE of eq. 45 and median)",
                window=window,
            )
