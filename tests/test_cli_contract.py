"""The promises around the numbers: refusals before any work, one evaluation path, results
that say when they are bad, the small options a user expects (--version, --seed, --no-plots)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml
from rich.console import Console

from tumblenav import cli, evaluation, io, pipeline
from tumblenav.campaign.runner import collect, summarise
from tumblenav.campaign.store import CampaignStore, run_seed
from tumblenav.estimators import base as est_base
from tumblenav.evaluation.metrics import RunErrors
from tumblenav.scenario import builtin_text, load_scenario, scenario_to_yaml
from tumblenav.simulation import run_streams, simulate
from tumblenav.testing import KABIR_TORQUE_FREE


def run(args, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as ei:
        cli.main([str(a) for a in args])
    cap = capsys.readouterr()
    return int(ei.value.code), cap.out, " ".join(cap.err.split())


def write(tmp_path: Path, name: str, scenario) -> Path:
    p = tmp_path / f"{name}.yaml"
    p.write_text(scenario_to_yaml(scenario))
    return p


def short_hu(duration: float = 40.0):
    return load_scenario("hu2024").with_updates(
        duration_s=duration,
        steady_state_window_s=[duration - 10.0, duration],
        occlusion={"windows": [{"start_s": 20.0, "end_s": 25.0}]},
    )


def short_kabir(duration: float = 60.0):
    return (
        load_scenario("kabir2025")
        .with_updates(**KABIR_TORQUE_FREE)
        .with_updates(duration_s=duration, **{"occlusion.loss_from_s": None})
    )


# --- refuse what cannot work, before any work -------------------------------------------------


def _unrunnable(tmp_path: Path) -> list[tuple[Path, str, str]]:
    kab = load_scenario("kabir2025").with_updates(**KABIR_TORQUE_FREE)
    return [
        (
            write(
                tmp_path,
                "convergent",
                kab.with_updates(**{"sensor.rig": "convergent", "sensor.toe_in_deg": 2.0}),
            ),
            "ukf",
            "parallel stereo rig",
        ),
        (write(tmp_path, "hu", load_scenario("hu2024")), "ekf-depth", "runs on depth-clouds"),
        (write(tmp_path, "yu", load_scenario("yu2019")), "ekf-dpacf", "runs on stereo-tracks"),
        (
            write(tmp_path, "orbiting", kab.with_updates(**{"chaser.orbit": {"radius_m": 7e6}})),
            "ukf-gp",
            "inertially fixed chaser",
        ),
    ]


@pytest.mark.parametrize("command", ["montecarlo", "estimate"])
def test_an_estimator_that_cannot_run_is_refused_before_any_work(command, tmp_path, capsys):
    for scenario, estimator, why in _unrunnable(tmp_path):
        out = tmp_path / f"out_{estimator}"
        args = [command, scenario, "-e", estimator, "-o", out]
        if command == "montecarlo":
            args += ["--runs", 2, "--workers", 1]
        code, _, err = run(args, capsys)
        assert code == 2, (estimator, err)
        assert why in err and "Traceback" not in err
        assert not out.exists(), "work started before the refusal"


def test_a_repeated_option_is_refused(tmp_path, capsys):
    code, _, err = run(
        ["montecarlo", "hu2024", "-e", "ekf-dpacf", "-e", "ekf-baseline", "-o", tmp_path / "o"],
        capsys,
    )
    assert code == 2 and "given more than once" in err
    assert not (tmp_path / "o").exists()
    code, _, err = run(["estimate", "hu2024", "--seed", 1, "--seed", 2, "-o", tmp_path], capsys)
    assert code == 2 and "--seed" in err


@pytest.mark.parametrize(
    "change, words",
    [
        ({"focal_length_px": 0.0}, "focal_length_px"),
        ({"focal_length_px": -5.0}, "focal_length_px"),
        ({"baseline_m": 0.0}, "baseline"),
        ({"principal_point_px": [2000.0, 640.0]}, "outside the 1280 x 1280 px image"),
    ],
)
def test_a_calibration_that_cannot_be_right_is_one_line_exit_2(tmp_path, capsys, change, words):
    """Chang 2021 issue, bad input: fx <= 0, a zero baseline, a principal point outside the
    image: one line naming the key, exit 2, nothing written."""
    data = yaml.safe_load(builtin_text("chang2021"))
    data["sensor"].update(change)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    code, _, err = run(["estimate", p, "-o", tmp_path / "e"], capsys)
    assert code == 2 and words in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "e").exists()


# --- measurements checked against the scenario ------------------------------------------------


@pytest.fixture(scope="module")
def hu_measurements(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("sim")
    sc = short_hu()
    truth, meas = simulate(sc, run_seed(5, 0))
    io.write_netcdf(meas.to_dataset(sc.name), folder / "measurements.nc")
    return folder


def test_measurements_of_another_sensor_or_rig_are_refused(hu_measurements, tmp_path, capsys):
    # hu2024's stereo tracks under the chang2021 scenario (another rig): not relabelled
    code, _, err = run(
        [
            "estimate",
            "chang2021",
            "-e",
            "ekf-dpacf",
            "--measurements",
            hu_measurements,
            "-o",
            tmp_path / "a",
        ],
        capsys,
    )
    assert code == 2 and "another stereo rig" in err and "baseline" in err
    assert not (tmp_path / "a").exists()
    # stereo tracks under a depth scenario: a clear line, not an AttributeError
    code, _, err = run(
        ["estimate", "yu2019", "--measurements", hu_measurements, "-o", tmp_path / "b"], capsys
    )
    assert code == 2 and "holds stereo measurements" in err and "depth sensor" in err


def test_measurements_without_pixel_noise_are_refused(hu_measurements, tmp_path, capsys):
    ds = xr.open_dataset(hu_measurements / "measurements.nc").load()
    del ds.attrs["noise_px"]
    folder = tmp_path / "m"
    io.write_netcdf(ds, folder / "measurements.nc")
    sc = write(tmp_path, "short", short_hu())
    code, _, err = run(
        ["estimate", sc, "-e", "ekf-dpacf", "--measurements", folder, "-o", tmp_path / "o"],
        capsys,
    )
    assert code == 2 and "noise_px" in err


# --- one evaluation path -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "estimator, scenario",
    [("ekf-dpacf", short_hu), ("ekf-baseline", short_hu), ("ukf", short_kabir)],
)
def test_batch_and_single_run_paths_store_the_same_quantities(estimator, scenario):
    """The batched path and its per-run fallback go through the one evaluation and store the
    same fields: a campaign mixing both once broke for good on resume (KeyError
    'dpacf_attitude_deg')."""
    sc = scenario()
    est = est_base.get(estimator)
    ss = run_seed(sc.montecarlo.seed, 0)
    truth, meas = simulate(sc, ss)
    hist = est.run(sc, meas, run_streams(ss)["estimator"])
    single = evaluation.evaluate_run(hist, truth)
    p_every = evaluation.nees_every(meas.t)
    (hb,) = est.run_batch(sc, [meas], [run_streams(ss)["estimator"]], p_every=p_every)
    batch = evaluation.evaluate_run(hb, truth)
    assert sorted(single.errors) == sorted(batch.errors)
    assert sorted(hist.skipped) == sorted(hb.skipped)
    np.testing.assert_allclose(single.nees, batch.nees, rtol=1e-6)
    for key in single.errors:  # and the same values, where both are defined
        a, b = single.errors[key], batch.errors[key]
        both = np.isfinite(a) & np.isfinite(b)
        assert np.array_equal(np.isfinite(a), np.isfinite(b)), key
        np.testing.assert_allclose(a[both], b[both], rtol=1e-6, atol=1e-9, err_msg=key)


def test_the_store_reads_every_run_it_wrote_whatever_its_fields(tmp_path):
    store = CampaignStore(tmp_path / "mc")
    store.open({"scenario": "x", "estimator": "y", "base_seed": 1, "scenario_hash": "h"})
    t = np.linspace(0.0, 10.0, 11)
    for k, keys in enumerate((["attitude_deg", "dpacf_attitude_deg"], ["attitude_deg"])):
        r = RunErrors(
            t,
            {key: np.full(11, k + 1.0) for key in keys},
            np.ones(11),
            3,
            np.ones(11),
            np.full(11, 2.0),
        )
        notes = ["tuning far from the scenario", "no start"][: k + 1]  # one or two lines
        store.save_run(k, 1, r, {"warnings": notes, "skipped_gated": 4})
    _, errs, _ = collect(store, 2)
    assert set(errs) == {"attitude_deg", "dpacf_attitude_deg"}
    assert np.isnan(errs["dpacf_attitude_deg"][1]).all()
    s = summarise(store, short_hu(10.0), "ekf-dpacf", 2)
    assert s["runs"] == 2 and s["rmse"]["dpacf_attitude_deg"] == pytest.approx(1.0)
    assert store.load(1)[1]["warnings"] == ["tuning far from the scenario", "no start"]
    assert store.load(1)[1]["skipped_gated"] == 4
    assert s["estimator_warnings"] == [
        "tuning far from the scenario (2 of 2 runs)",
        "no start (1 of 2 runs)",
    ]


# --- results that say when they are bad --------------------------------------------------------


def test_a_summary_outside_its_bounds_says_so():
    summary = {
        "scenario": "s",
        "estimator": "e",
        "runs": 20,
        "window_s": [0.0, 1.0],
        "rmse": {"attitude_deg": 62.0},
        "nees": {"mean": 2.9e3, "dof": 20, "bounds95": [0.9, 1.1], "inside_fraction": 0.0},
        "nis": {"mean": 1.0, "dof": 6, "bounds95": [0.9, 1.1], "inside_fraction": 1.0},
        "runs_failed": 2,
        "runs_without_estimate": 3,
        "runs_diverged": 1,
    }
    warnings = pipeline.assess(summary)
    text = " ".join(warnings)
    assert "NEES/dof 2.9e+03 is above its 95% bounds" in text and "over-confident" in text
    assert "NIS" not in text  # inside its bounds: no word
    assert "3 of 20 runs produced no estimate" in text
    assert "1 of 20 runs diverged" in text and "2 run(s) failed" in text
    buf = Console(file=__import__("io").StringIO(), width=200)
    pipeline.print_summary({**summary, "warnings": warnings}, buf)
    shown = buf.file.getvalue()
    assert "(above bounds)" in shown and "over-confident" in shown
    assert (
        pipeline.assess(
            {
                **summary,
                "nees": {**summary["nees"], "mean": 1.0},
                "runs_failed": 0,
                "runs_without_estimate": 0,
                "runs_diverged": 0,
            }
        )
        == []
    )


def test_restarts_alarms_branches_and_the_estimators_own_warnings_are_said():
    summary = {
        "runs": 20,
        "runs_reinitialised": 3,
        "runs_nis_alarm": 2,
        "branches": {"nominal": 18, "x<->y (y,-x,z)": 2},
        "estimator_warnings": ["q_omega_var is 40x the scenario's (3 of 20 runs)"],
    }
    text = "\n".join(pipeline.assess(summary))
    assert "3 of 20 run(s) lost track and started again" in text
    assert "2 of 20 run(s) raised the lost-track alarm" in text
    assert "2 of 20 runs converged to a symmetric equivalent" in text
    assert "q_omega_var is 40x the scenario's (3 of 20 runs)" in text
    # a single run says the same from its own skipped counts
    one = pipeline.assess({"runs": 1, "skipped": {"reinitialised": 2, "nis_alarm": 0}})
    assert any("1 of 1 run(s) lost track" in w for w in one)
    assert not any("alarm" in w for w in one)


def test_estimate_writes_its_warnings_and_no_figure_with_no_plots(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(pipeline, "kernels_compiled", lambda: False)
    sc = write(tmp_path, "short", short_hu())
    out = tmp_path / "e"
    code, _, err = run(["estimate", sc, "-e", "ekf-dpacf", "--no-plots", "-o", out], capsys)
    assert code == 0, err
    assert "compiling the numerical kernels" in err
    s = json.loads((out / "summary.json").read_text())
    assert s["warnings"] == pipeline.assess(s)
    assert not list(out.glob("*.png"))


def test_montecarlo_seed_and_no_plots(tmp_path, capsys):
    sc = write(tmp_path, "short", short_hu(30.0))
    a, b = tmp_path / "a", tmp_path / "b"
    for out, seed in ((a, 11), (b, 12)):
        code, _, err = run(
            [
                "montecarlo",
                sc,
                "-e",
                "ekf-dpacf",
                "--runs",
                2,
                "--workers",
                1,
                "--seed",
                seed,
                "--no-plots",
                "-o",
                out,
            ],
            capsys,
        )
        assert code == 0, err
        assert io.read_json(out / "campaign.json")["base_seed"] == seed
        assert not list(out.glob("*.png"))
    ra, rb = (json.loads((p / "summary.json").read_text())["rmse"] for p in (a, b))
    assert ra != rb  # other seeds, other runs


def test_version(capsys):
    code, out, _ = run(["--version"], capsys)
    assert code == 0 and out.startswith("tumblenav ")


def test_an_exit_status_from_typer_is_passed_on(monkeypatch):
    """typer returns 130 (its own KeyboardInterrupt handling) instead of raising: main used to
    turn it into exit 0."""
    monkeypatch.setattr(cli, "app", lambda **kw: 130)
    with pytest.raises(SystemExit) as ei:
        cli.main(["demo"])
    assert ei.value.code == 130


def test_a_stated_prior_that_the_simulated_truth_contradicts_is_flagged(tmp_path, capsys):
    """kabir2025 with the target moved but the estimator's known mass centre left where the
    built-in says: the filter is told a wrong prior, and the summary says so."""
    sc = short_kabir(30.0).with_updates(**{"target.r0_L_m": [0.0, 12.0, 0.0]})
    path = write(tmp_path, "moved", sc)
    code, shown, err = run(
        ["estimate", path, "-e", "ukf", "--no-plots", "-o", tmp_path / "o"], capsys
    )
    assert code == 0, err
    s = io.read_json(tmp_path / "o" / "summary.json")
    assert any(
        "mass_centre_L_m" in w and "differs from the simulated truth" in w for w in s["warnings"]
    )
    assert "differs from the simulated truth" in " ".join(shown.split())
    same = write(tmp_path, "same", short_kabir(30.0))
    code, shown, err = run(
        ["estimate", same, "-e", "ukf", "--no-plots", "-o", tmp_path / "p"], capsys
    )
    assert code == 0 and "differs from the simulated truth" not in " ".join(shown.split())


def test_the_compile_message_is_not_shown_once_the_kernels_are_cached(tmp_path):
    """After a run of a compiled estimator numba's cache holds every listed kernel module, so
    the "compiling" message is not shown again (a listed module whose kernels are all inlined
    into others never gets cache files: it made the message appear every time)."""
    from tumblenav.numba_cache import KERNEL_MODULES, kernels_compiled

    sc = write(tmp_path, "short", short_hu(20.0))
    quiet = Console(file=__import__("io").StringIO())
    pipeline.run_estimate(str(sc), "ekf-dpacf", tmp_path / "e", plots=False, console=quiet)
    assert kernels_compiled(), KERNEL_MODULES
