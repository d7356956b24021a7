"""Chang, Liu, Chen, Bai, Shu 2021 (Aerospace 8, 230), Sec. 3-4: ekf-pose on rendered stereo
images, the Monte Carlo of Table 2 and Figs. 14-19.

Cases: the printed scenario (``chang2021``: Sec. 3.1's closed ellipse, 59-70 m over the run) and
tumblenav's close-range variant (``chang2021_close``: the same ellipse scaled by 0.15, 8.9-10.5 m),
each with both camera presets the paper's text and Table 1 give (they contradict each other,
chang2021-notes.md sec. 1.2):

- ``text``: 1024 x 1024 px, 35 deg field of view (f = 1623.86 px, principal point 512 px);
- ``table1``: f = 2029.8 px, principal point 640 px, which is a 1280 x 1280 px image at 35 deg.

What varies between runs (the paper does not say; its renders are deterministic): the camera
noise of every image (shot, dark current and read noise, seeded per run and epoch), hence the
features found, tracked and matched, and with them the filter's start from the first frames
(tumblenav starts ekf-pose without the truth; the paper initialises from the simulation's
values, Sec. 4.2). The truth motion is the printed one in every run.

Duration and frame rate (not given): 120 s at 5 Hz (600 stereo pairs per run, 1 deg of tumble
per frame; 100 frames initialise the filter as in Sec. 4.1), chosen so that 100 runs of a case
fit in the hour the issue allows on 2 cores (docs/results/chang2021.md has the timing).

Reported per case: the campaign's RMSE, NEES and NIS, and Table 2's per-axis means and standard
deviations over runs and epochs after convergence (from 40 s; Fig. 19 converges "within 40 s")
beside the paper's (``paper_table2``), Sec. 4.1's mean errors and Sec. 4.2's claimed maxima,
which contradict Table 2 (``note``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from tumblenav import io
from tumblenav.campaign import runner
from tumblenav.campaign.store import CampaignStore, run_seed
from tumblenav.errors import InputError
from tumblenav.measurements import StereoImageMeasurements
from tumblenav.papers import case_from_campaign
from tumblenav.scenario import Scenario, load_scenario

ESTIMATOR = "ekf-pose"
RANGES = {"close": "chang2021_close", "printed": "chang2021"}
PRESETS: dict[str, dict[str, Any]] = {
    "text": {
        "sensor.resolution_px": [1024, 1024],
        "sensor.fov_deg": 35.0,
        "sensor.focal_length_px": None,
        "sensor.principal_point_px": None,
    },
    "table1": {
        "sensor.resolution_px": [1280, 1280],
        "sensor.fov_deg": None,
        "sensor.focal_length_px": 2029.8,
        "sensor.principal_point_px": [640.0, 640.0],
    },
}

# Chang 2021 Table 2 (100 runs, after convergence), per axis x, y, z
PAPER_TABLE2 = {
    "attitude_deg": {"mean": [0.0238, 8.2274e-4, 0.0094], "std": [0.4482, 0.5480, 0.5298]},
    "rate_deg_s": {"mean": [0.0222, 0.0353, 0.0030], "std": [0.5400, 0.6336, 0.2833]},
    "position_m": {"mean": [0.0033, 0.0032, 0.0090], "std": [0.1146, 0.1157, 0.1161]},
    "velocity_m_s": {
        "mean": [0.5471e-4, 9.6595e-4, 4.2910e-4],
        "std": [0.0298, 0.0308, 0.0309],
    },
}
# Sec. 4.1: mean errors after convergence; Sec. 4.2: claimed maximum deviations
PAPER_SEC41_MEAN = {
    "attitude_deg": 0.6896,
    "rate_deg_s": 0.2120,
    "position_m": 0.0316,
    "velocity_m_s": 0.0017,
}
PAPER_SEC42_MAX = {
    "attitude_deg": 1.0,
    "rate_deg_s": 0.1,
    "position_m": 0.05,
    "velocity_m_s": 0.002,
}
# the targets for the close-range variant (standard deviation per axis)
TARGETS_CLOSE_STD = {
    "attitude_deg": 0.55,
    "rate_deg_s": 0.3,
    "position_m": 0.03,
    "velocity_m_s": 0.002,
}
NOTE = (
    "Table 2's standard deviations (rate 0.28-0.63 deg/s, position 0.115 m, velocity 0.03 m/s) "
    "contradict Sec. 4.2's claimed maxima (rate < 0.1 deg/s, position < 0.05 m, velocity < "
    "0.002 m/s): a maximum cannot be below a standard deviation. We compare with Table 2 "
    "(100 runs). Table 2's attitude axes are not named (Euler sequence not given); ours are "
    "the rotation-vector error's components in the estimator's target frame."
)


def rmse_from_table(stats: dict[str, list[float]]) -> float:
    """The RMSE of the error norm a per-axis mean and standard deviation imply."""
    m, s = np.asarray(stats["mean"]), np.asarray(stats["std"])
    return float(np.sqrt(np.sum(m**2 + s**2)))


PAPER_RMSE = {k: rmse_from_table(v) for k, v in PAPER_TABLE2.items()}


def _axis_rms(stats: dict[str, list[float]]) -> np.ndarray:
    """Per-axis RMS error from a per-axis mean and standard deviation."""
    return np.sqrt(np.asarray(stats["mean"]) ** 2 + np.asarray(stats["std"]) ** 2)


def case_scenario(range_name: str, preset: str, base: Scenario | None = None) -> Scenario:
    """The scenario of one case: ``range_name`` in :data:`RANGES`, ``preset`` in :data:`PRESETS`
    (``base`` replaces the built-in, e.g. a shorter run for tests)."""
    sc = base or load_scenario(RANGES[range_name])
    return sc.with_updates(**PRESETS[preset])


def case_dir(output: Path, range_name: str, preset: str) -> Path:
    return Path(output) / f"{range_name}_{preset}"


def _components(store: CampaignStore, ks: list[int]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The runs' per-axis errors at 1 Hz: t (m,) and {quantity: (runs, m, 3)}."""
    loaded = [store.load_components(k) for k in ks]
    loaded = [(t, c) for t, c in loaded if len(t)]
    if not loaded:
        return np.zeros(0), {}
    t = loaded[0][0]
    keys = list(loaded[0][1])
    return t, {k: np.stack([c[k] for _, c in loaded if len(c[k]) == len(t)]) for k in keys}


def run_case(
    range_name: str,
    preset: str,
    output: Path,
    runs: int,
    workers: int | None = None,
    console: Console | None = None,
    base: Scenario | None = None,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """One case: a resumable campaign of ``runs`` runs of ekf-pose on rendered images, with
    Table 2's statistics and the per-axis figure (Figs. 17/19)."""
    from tumblenav import plots as figures

    sc = case_scenario(range_name, preset, base)
    folder = case_dir(output, range_name, preset)
    s = runner.run_campaign(
        sc, ESTIMATOR, runs, folder, workers=workers, scheduler=scheduler, console=console
    )
    store = CampaignStore(folder)
    ks = sorted(k for k in store.done() if k < runs)
    t, comps = _components(store, ks)
    if comps:
        figures.plot_axis_spread(
            t,
            comps,
            folder / "errors_per_axis.png",
            f"Chang 2021 Fig. 19 analogue: {range_name} range, {preset} camera, {len(ks)} runs",
            window=sc.window_s,
        )
    ours = s.get("per_axis", {})
    case: dict[str, Any] = {
        "estimator": ESTIMATOR,
        "range": range_name,
        "camera": preset,
        **case_from_campaign(s),
        "per_axis": ours,
        "paper_table2": PAPER_TABLE2,
        "paper_values": PAPER_RMSE,
        "paper_sec41_mean": PAPER_SEC41_MEAN,
        "paper_sec42_max": PAPER_SEC42_MAX,
    }
    if range_name == "close":
        case["targets_std_per_axis"] = TARGETS_CLOSE_STD
        # judged on each axis' RMS (its mean and spread together), stricter than the spread
        # alone: a biased estimate with a small spread does not meet a target
        case["targets_met"] = {
            k: bool(np.all(_axis_rms(ours[k]) <= v)) if k in ours else None
            for k, v in TARGETS_CLOSE_STD.items()
        }
    return case


def front_end_figures(
    output: Path, base: Scenario | None = None, frame_s: float = 20.0, tail_frames: int = 10
) -> list[Path]:
    """Run 0 of the close-range text case through the image front end: a frame with its tracked
    and matched features (Figs. 14-15 analogue) and the feature counts over the run."""
    from tumblenav import plots as figures
    from tumblenav.frontends.stages import image_frontend_tuning
    from tumblenav.frontends.stereo_images import ImageTracker
    from tumblenav.simulation import simulate

    sc = case_scenario("close", "text", base)
    _, meas = simulate(sc, run_seed(sc.montecarlo.seed, 0))
    if not isinstance(meas, StereoImageMeasurements):
        raise InputError(f"scenario {sc.name} does not render images (sensor.images)")
    images = getattr(sc.sensor, "images", None)
    tracker = ImageTracker(meas.rig, image_frontend_tuning(images.frontend if images else None))
    k_frame = min(int(round(frame_s * sc.rate_hz)), len(meas.t) - 1)
    history: list[dict[int, np.ndarray]] = []
    counts: dict[str, list[float]] = {"held (left and right)": [], "new": [], "tracked by LK": []}
    files = []
    for k, (left, right) in enumerate(meas.pairs()):
        fr = tracker.step(left, right)
        history.append({int(i): fr.uv[0, j] for j, i in enumerate(fr.ids)})
        st = fr.stats
        counts["held (left and right)"].append(len(fr.ids))
        counts["new"].append(getattr(st, "new", np.nan))
        counts["tracked by LK"].append(getattr(st, "tracked", np.nan))
        if k == k_frame:
            ids = list(fr.ids)
            tails = np.full((tail_frames, len(ids), 2), np.nan)
            for a, h in enumerate(history[-tail_frames:]):
                for j, i in enumerate(ids):
                    if int(i) in h:
                        tails[a, j] = h[int(i)]
            files.append(
                figures.plot_tracked_frame(
                    (left, right),
                    fr.uv,
                    tails,
                    Path(output) / "fig14_15_features.png",
                    f"Chang 2021 Figs. 14-15 analogue: t = {meas.t[k]:.1f} s, close range, "
                    "text camera (left: tracks over the last "
                    f"{tail_frames} frames; right: matched along the epipolar line)",
                )
            )
    files.append(
        figures.plot_feature_counts(
            meas.t,
            {k: np.asarray(v, float) for k, v in counts.items()},
            Path(output) / "fig18_feature_count.png",
            "Chang 2021 Fig. 18 analogue: features in the image front end (run 0, close, text)",
        )
    )
    return files


def reproduce(
    output: Path,
    runs: int | None = None,
    workers: int | None = None,
    console: Console | None = None,
    cases: tuple[tuple[str, str], ...] | None = None,
    bases: dict[str, Scenario] | None = None,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """The four cases (close and printed range, text and Table 1 camera) with ``runs`` runs each
    (default: the scenario's 100, as Table 2), the front-end figures, and summary.json."""
    if runs is not None and runs < 1:
        raise InputError("--runs must be at least 1")
    cases = cases or tuple((r, p) for r in RANGES for p in PRESETS)
    bases = bases or {}
    out = []
    for range_name, preset in cases:
        base = bases.get(range_name)
        n = runs or (base or load_scenario(RANGES[range_name])).montecarlo.runs
        out.append(run_case(range_name, preset, Path(output), n, workers, console, base, scheduler))
    summary = {
        "paper": "chang2021",
        "scenario": "chang2021 / chang2021_close",
        "note": NOTE,
        "cases": out,
    }
    if ("close", "text") in cases:
        front_end_figures(Path(output), bases.get("close"))
    io.write_json(summary, Path(output) / "summary.json")
    return summary
