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
