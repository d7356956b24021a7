"""`tumblenav compare`: the same truth, measurements and seeds for every estimator, one table,
overlaid figures, refusals before any work, resumable."""

from __future__ import annotations

import json

import pytest

from tumblenav import io
from tumblenav.cli import main
from tumblenav.scenario import load_scenario, scenario_to_yaml


def run(args, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as ei:
        main([str(a) for a in args])
    cap = capsys.readouterr()
    return int(ei.value.code), " ".join(cap.out.split()), " ".join(cap.err.split())


@pytest.fixture()
def short(tmp_path):
    s = load_scenario("hu2024").with_updates(
        duration_s=40.0,
        steady_state_window_s=[30.0, 40.0],
        occlusion={"windows": [{"start_s": 20.0, "end_s": 25.0}]},
    )
    p = tmp_path / "short.yaml"
    p.write_text(scenario_to_yaml(s))
    return p


def test_compare_runs_every_estimator_on_the_same_runs(short, tmp_path, capsys):
    out = tmp_path / "cmp"
    args = ["compare", short, "-e", "ekf-dpacf,ekf-baseline", "--runs", 3, "--workers", 1,
            "-o", out]  # fmt: skip
    code, shown, err = run(args, capsys)
    assert code == 0, err
    s = json.loads((out / "summary.json").read_text())
    assert [c["estimator"] for c in s["cases"]] == ["ekf-dpacf", "ekf-baseline"]
    assert all(c["runs"] == 3 for c in s["cases"])
    seeds = {
        io.read_json(out / e / "campaign.json")["base_seed"] for e in ("ekf-dpacf", "ekf-baseline")
    }
    assert seeds == {s["base_seed"]}
    # the same measurements: the front end's own DPACF attitude (before any filter) is the same
    a, b = (c["rmse"]["dpacf_attitude_deg"] for c in s["cases"])
    assert a == b
    assert "ekf-dpacf" in shown and "ekf-baseline" in shown and "NEES/dof" in shown
    for f in ("rmse_attitude_deg.png", "nees.png"):
        assert (out / f).exists()
    # resumable: nothing recomputed, the same result
    code, _, err = run(args, capsys)
    assert code == 0 and "3 of 3 runs already stored" in err
    assert (
        json.loads((out / "summary.json").read_text())["cases"][0]["rmse"] == s["cases"][0]["rmse"]
    )


def test_compare_refuses_an_estimator_that_cannot_run_before_any_work(short, tmp_path, capsys):
    out = tmp_path / "cmp"
    code, _, err = run(["compare", short, "-e", "ekf-dpacf,ekf-depth", "-o", out], capsys)
    assert code == 2 and "ekf-depth" in err and "depth-clouds" in err
    assert not out.exists()
    code, _, err = run(["compare", short, "-e", "ekf-dpacf", "-o", out], capsys)
    assert code == 2 and "at least two estimators" in err


def test_an_estimator_of_another_sensor_gets_its_own_measurements_of_the_same_truth(
    tmp_path, capsys
):
    """yu2019 (depth sensor) with a stereo rig in `other_sensors`: ekf-dpacf runs on stereo
    tracks simulated from the same truth and seeds, and the table and summary say so."""
    from tumblenav.campaign.store import run_seed
    from tumblenav.simulation import simulate

    s = load_scenario("yu2019").with_updates(
        duration_s=20.0,
        steady_state_window_s=[15.0, 20.0],
        **{"target.features_T_m": {"count": 6, "low_m": -0.5, "high_m": 0.5}},
        other_sensors=[
            {"kind": "stereo", "fov_deg": 40.0, "resolution_px": [1024, 1024],
             "baseline_m": 1.0, "noise": {"angular_rad": 2e-5}}
        ],
    )  # fmt: skip
    p = tmp_path / "yu.yaml"
    p.write_text(scenario_to_yaml(s))
    out = tmp_path / "cmp"
    code, shown, err = run(
        ["compare", p, "-e", "ekf-depth,ekf-dpacf", "--runs", 2, "--workers", 1, "--no-plots",
         "-o", out], capsys,
    )  # fmt: skip
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["same_measurements"] is False
    depth, stereo = summary["cases"]
    assert "sensor" not in depth and stereo["sensor"].startswith("own stereo sensor")
    assert "own stereo sensor" in shown
    # the same truth: run 1 of each has the same target motion
    alt = s.with_updates(sensor=s.other_sensors[0].model_dump(), other_sensors=[])
    t_depth, _ = simulate(s, run_seed(s.montecarlo.seed, 1))
    t_stereo, _ = simulate(alt, run_seed(s.montecarlo.seed, 1))
    assert (t_depth.q_TI == t_stereo.q_TI).all() and (t_depth.r_L == t_stereo.r_L).all()
    assert (t_depth.features_T == t_stereo.features_T).all()
