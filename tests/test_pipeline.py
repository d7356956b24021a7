"""Estimation and campaigns end to end: files, summary.json contract, resume, bad input."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tumblenav import io
from tumblenav.campaign.runner import run_campaign
from tumblenav.campaign.store import CampaignStore, code_fingerprint, run_seed
from tumblenav.cli import main
from tumblenav.estimators import base as est_base
from tumblenav.estimators.ekf_dpacf import HuEKF
from tumblenav.scenario import load_scenario, scenario_to_yaml
from tumblenav.simulation import simulate

RMSE_KEYS = {"attitude_deg", "rate_deg_s", "position_m", "velocity_m_s", "inertia", "features_m"}


def short_scenario(tmp_path: Path) -> Path:
    """hu2024 shortened to 70 s (occlusion 40-50 s) so that tests stay fast."""
    s = load_scenario("hu2024").with_updates(
        duration_s=70.0,
        steady_state_window_s=[60.0, 70.0],
        occlusion={"windows": [{"start_s": 40.0, "end_s": 50.0}]},
    )
    p = tmp_path / "short.yaml"
    p.write_text(scenario_to_yaml(s))
    return p


def cli(args, capsys):
    with pytest.raises(SystemExit) as ei:
        main([str(a) for a in args])
    cap = capsys.readouterr()
    return ei.value.code, cap.out, cap.err


def test_estimate_writes_files_and_summary_contract(tmp_path, capsys):
    sc = short_scenario(tmp_path)
    out = tmp_path / "est"
    code, _, err = cli(["estimate", sc, "--estimator", "ekf-dpacf", "-o", out, "--seed", 3], capsys)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenario"] == "hu2024" and summary["estimator"] == "ekf-dpacf"
    assert summary["runs"] == 1 and summary["window_s"] == [60.0, 70.0]
    assert RMSE_KEYS <= set(summary["rmse"])
    assert {"mean", "dof", "bounds95"} <= set(summary["nees"])
    assert summary["nees"]["dof"] == 15 + 3 * 6
    # the estimate is in the right neighbourhood (short run, 2e-5 rad): degrees, not tens
    assert summary["rmse"]["attitude_deg"] < 10.0
    assert summary["rmse"]["position_m"] < 1.0
    assert (out / "estimates.nc").exists() and (out / "errors.png").exists()


def test_estimate_from_measurement_folder(tmp_path, capsys):
    sc = short_scenario(tmp_path)
    sim = tmp_path / "sim"
    assert cli(["simulate", sc, "-o", sim, "--seed", 5, "--no-plots"], capsys)[0] == 0
    code, _, err = cli(
        ["estimate", sc, "-e", "ekf-dpacf", "-o", tmp_path / "e", "--measurements", sim], capsys
    )
    assert code == 0, err
    code, _, err = cli(
        [
            "estimate",
            sc,
            "-e",
            "ekf-dpacf",
            "-o",
            tmp_path / "e2",
            "--measurements",
            tmp_path / "nothing",
        ],
        capsys,
    )
    assert code == 2 and "file not found" in err


def test_unknown_estimator_is_bad_input(tmp_path, capsys):
    code, _, err = cli(["estimate", "hu2024", "-e", "nope", "-o", tmp_path], capsys)
    assert code == 2 and "unknown estimator" in err and "Traceback" not in err


def test_estimators_lists_both(capsys):
    code, out, _ = cli(["estimators"], capsys)
    assert code == 0 and "ekf-dpacf" in out and "ekf-baseline" in out


def test_campaign_resumes_without_redoing_runs(tmp_path):
    sc = load_scenario(short_scenario(tmp_path))
    out = tmp_path / "mc"
    s1 = run_campaign(sc, "ekf-dpacf", 3, out, workers=1)
    assert s1["runs"] == 3 and s1["runs_failed"] == 0
    store = CampaignStore(out)
    stamps = {k: store.run_path(k).stat().st_mtime_ns for k in range(3)}
    s2 = run_campaign(sc, "ekf-dpacf", 4, out, workers=1)
    assert s2["runs"] == 4
    assert {k: store.run_path(k).stat().st_mtime_ns for k in range(3)} == stamps
    assert RMSE_KEYS <= set(s2["rmse"])


def test_campaign_refuses_a_folder_of_another_campaign(tmp_path, capsys):
    sc = short_scenario(tmp_path)
    out = tmp_path / "mc"
    assert (
        cli(["montecarlo", sc, "-e", "ekf-dpacf", "--runs", 1, "--workers", 1, "-o", out], capsys)[
            0
        ]
        == 0
    )
    code, _, err = cli(["montecarlo", sc, "-e", "ekf-baseline", "--runs", 1, "-o", out], capsys)
    assert code == 2 and "different campaign" in err


def test_campaign_refuses_runs_stored_by_other_code(tmp_path, capsys):
    """Resuming must not mix runs computed by another version of the code."""
    sc = short_scenario(tmp_path)
    out = tmp_path / "mc"
    args = ["montecarlo", sc, "-e", "ekf-dpacf", "--runs", 1, "--workers", 1, "-o", out]
    assert cli(args, capsys)[0] == 0
    spec = io.read_json(out / "campaign.json")
    assert spec["code_fingerprint"] == code_fingerprint()
    io.write_json({**spec, "code_fingerprint": "0.0.0+older"}, out / "campaign.json")
    code, _, err = cli([*args[:4], "--runs", 2, "-o", out], capsys)
    assert code == 2 and "other tumblenav code" in err and "0.0.0+older" in err
    assert CampaignStore(out).done() == {0}  # nothing lost


class _Flaky(HuEKF):
    """ekf-dpacf that fails on its second run (to test failure recording)."""

    def run(self, scenario, measurements, rng):
        if rng.integers(0, 2**31) % 2 == 0:
            raise RuntimeError("boom")
        return super().run(scenario, measurements, rng)

    run_batch = None


def test_failed_runs_are_recorded_and_campaign_goes_on(tmp_path, monkeypatch):
    # registered for this test only (other tests list the registry)
    monkeypatch.setitem(est_base._REGISTRY, "test-flaky", lambda: _Flaky(True))
    sc = load_scenario(short_scenario(tmp_path))
    s = run_campaign(sc, "test-flaky", 4, tmp_path / "mc", workers=1)
    assert s["runs"] + s["runs_failed"] == 4 and s["runs_failed"] >= 1
    fail = s["failed"][0]
    assert "boom" in fail["error"] and fail["base_seed"] == sc.montecarlo.seed


def test_filter_survives_bad_measurements(tmp_path):
    """NaN pixels, a feature in one camera only, negative disparity, < 3 features: the filter
    propagates through them, keeps a finite state and reports what it skipped."""
    sc = load_scenario(short_scenario(tmp_path))
    truth, meas = simulate(sc, run_seed(11, 0))
    uv, obs = meas.uv.copy(), meas.observed.copy()
    uv[100:120, :, 0, :] = np.nan  # NaN pixels (observed flag still set)
    obs[200:260, 1, 1] = False  # feature 1 seen by the left camera only
    uv[200:260, 1, 1] = np.nan
    uv[300:320, 1, 2, 0] = uv[300:320, 0, 2, 0] + 5.0  # negative disparity
    obs[500:530, :, 2:] = False  # only two features for 3 s
    uv[500:530, :, 2:] = np.nan
    bad = replace(meas, uv=uv, observed=obs)
    hist = HuEKF(True).run(sc, bad, np.random.default_rng(0))
    started = np.all(np.isfinite(hist.x), axis=1)
    assert started.any()
    first = np.argmax(started)
    assert np.all(np.isfinite(hist.x[first:])) and np.all(np.isfinite(hist.P[first:]))
    assert hist.skipped["one_camera_only"] >= 60
    assert hist.skipped["bad_triangulation"] >= 20 + 20
    assert hist.skipped["too_few_features"] >= 1


def test_campaign_on_a_dask_cluster(tmp_path):
    """--scheduler ADDRESS: the same campaign on a (local, in-process) Dask cluster."""
    distributed = pytest.importorskip("distributed")
    sc = load_scenario(short_scenario(tmp_path))
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        s = run_campaign(sc, "ekf-dpacf", 2, tmp_path / "dask", scheduler=cluster.scheduler_address)
    assert s["runs"] == 2 and s["runs_failed"] == 0
    # the same runs done locally (seeds do not depend on where runs execute); rel 1e-6 and not
    # exact because a different batch size changes BLAS summation order (measured 2e-9)
    local = run_campaign(sc, "ekf-dpacf", 2, tmp_path / "local", workers=1)
    assert local["rmse"] == pytest.approx(s["rmse"], rel=1e-6)


def test_unreachable_scheduler_is_bad_input(tmp_path, capsys):
    sc = short_scenario(tmp_path)
    code, _, err = cli(
        [
            "montecarlo",
            sc,
            "-e",
            "ekf-dpacf",
            "--runs",
            1,
            "--scheduler",
            "tcp://127.0.0.1:9",
            "-o",
            tmp_path / "x",
        ],
        capsys,
    )
    assert code == 2 and "Dask scheduler" in err


def test_reproduce_hu2024_writes_cases_and_figures(tmp_path, capsys):
    out = tmp_path / "rep"
    code, _, err = cli(["reproduce", "hu2024", "--runs", 2, "--workers", 1, "-o", out], capsys)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["paper"] == "hu2024"
    cases = summary["cases"]
    assert {(c["noise_rad"], c["estimator"]) for c in cases} == {
        (n, e) for n in (1e-6, 5e-6, 2e-5, 5e-5) for e in ("ekf-dpacf", "ekf-baseline")
    }
    for c in cases:
        assert c["runs"] + c["runs_failed"] == 2
        assert "rmse" in c and "nees" in c and "paper_values" in c
    for name in ("fig5_dpacf_attitude", "fig6_attitude", "fig10_position"):
        assert (out / f"{name}.png").exists()


def test_reproduce_unknown_paper(tmp_path, capsys):
    code, _, err = cli(["reproduce", "nope", "-o", tmp_path], capsys)
    assert code == 2 and "unknown paper" in err
