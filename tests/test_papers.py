"""Paper recipes: the comparison table `reproduce` prints, and `--runs` for yu2019."""

from __future__ import annotations

import io

import pytest
import yaml
from rich.console import Console

from tumblenav.errors import InputError
from tumblenav.papers import hu2024, kabir2025, yu2019
from tumblenav.papers.table import print_comparison
from tumblenav.scenario import load_scenario


def _render(summary: dict, width: int = 120) -> str:
    con = Console(file=io.StringIO(), width=width)
    print_comparison(summary, con)
    return con.file.getvalue()


def _nees(mean: float, lo: float = 0.48, hi: float = 1.71, dof: int = 20) -> dict:
    return {"mean": mean, "dof": dof, "bounds95": [lo, hi], "inside_fraction": 0.5}


def _yu_summary() -> dict:
    rmse = {
        "attitude_deg": 0.0441,
        "rate_deg_s": 0.000871,
        "inertia": 0.173,
        "position_m": 0.0232,
        "velocity_m_s": 1.23e-05,
        "offset_m": 0.0226,
    }
    cases = [
        {
            "estimator": "ekf-depth",
            "noise_m": noise,
            "multi_solution_fix": fix,
            "runs": 1,
            "runs_failed": 0,
            "window_s": [300.0, 400.0],
            "rmse": {k: v * scale for k, v in rmse.items()},
            "nees": _nees(nees),
            "max_attitude_jump_deg": 0.237 * scale,
            "paper_values": yu2019.PAPER_FILTER,
        }
        for (noise, fix), scale, nees in zip(
            yu2019.CASES, (1.0, 1000.0, 700.0), (0.581, 1.1e10, 2.92e3), strict=True
        )
    ]
    th = yu2019.theory(0.0)
    return {
        "paper": "yu2019",
        "table1": [
            {
                "outliers": k,
                "extracted_points": pe + 1,
                "time_ms": 0.45,
                "paper_extracted": pe,
                "paper_time_ms": pt,
            }
            for k, (pe, pt) in yu2019.TABLE1.items()
        ],
        "table2": [
            {
                "points": n,
                "centroid_cm": [0.0180, -0.0053, 6.5],
                "eigenvalues_cm2": [8.2605, 27.1377, 0.0],
                "theory_cm2": th,
                "relative_error": [0.009, 0.005, None],
                "paper_centroid_cm": list(pc),
                "paper_eigenvalues_cm2": list(pe),
            }
            for n, (pc, pe) in yu2019.TABLE2.items()
        ],
        "table3": [
            {"noise_cm": s, "centroid_cm": [0.0, 0.0, 6.4979], "paper_centroid_cm": list(pc)}
            for s, pc in yu2019.TABLE3.items()
        ],
        "table4": [
            {
                "noise_cm": s,
                "eigenvalues_cm2": [9.7706, 27.6571, 1.0092],
                "theory_cm2": yu2019.theory(s),
                "relative_error": [0.047, 0.012, 0.009],
                "paper_eigenvalues_cm2": list(pe),
            }
            for s, pe in yu2019.TABLE4.items()
        ],
        "cases": cases,
    }


def test_comparison_table_yu2019_puts_ours_next_to_the_papers():
    text = _render(_yu_summary())
    # the filter cases: ours, the paper's printed value, the ratio and the marks
    assert "noise 0.01 m, fix on" in text and "noise 0.1 m, fix on" in text
    assert "0.0441 deg" in text and "0.1 deg paper" in text and "0.441x" in text
    assert "0.0232 m" in text and "0.0032 m paper" in text and "7.25x worse" in text
    assert "1.23e-05 m/s" in text and "1e-05 m/s paper" in text
    assert "[0.48, 1.71] 95%" in text
    assert "0.581" in text and "inside" in text
    assert "2.92e+03" in text and "over-confident" in text
    # Tables 1-4: the paper's numbers and ours
    assert "1252" in text and "1253" in text and "70" in text
    assert "(8.4102, 26.7072, 0.0000)" in text and "(8.2605, 27.1377, 0.0000)" in text
    assert "(9.4664, 27.7494, 0.9765)" in text and "(9.7706, 27.6571, 1.0092)" in text
    assert "(0.0154, -0.0390, 6.5000)" in text and "(0.0000, 0.0000, 6.4979)" in text
    assert "eigenvalues [cm^2]" in text  # brackets are text, not rich markup
    assert "4.7%" in text


def _hu_summary() -> dict:
    cases = []
    for noise in hu2024.NOISE_RAD:
        for est in hu2024.ESTIMATORS:
            c = {
                "noise_rad": noise,
                "estimator": est,
                "runs": 500,
                "runs_failed": 0,
                "runs_without_estimate": 3 if est == "ekf-baseline" else 0,
                "window_s": [150.0, 200.0],
                "rmse": {
                    "attitude_deg": 0.107,
                    "rate_deg_s": 0.219,
                    "position_m": 0.0229,
                    "velocity_m_s": 0.00187,
                    "features_m": 0.00391,
                    "inertia": 0.0051,
                },
                "nees": _nees(0.561, 0.978, 1.022, 33),
                "paper_values": {"note": "Hu 2024 gives figures only (Figs. 5-11)"},
            }
            if noise == 2e-5 and est == "ekf-dpacf":
                c["targets"] = hu2024.TARGETS_2E5
            cases.append(c)
    return {"paper": "hu2024", "scenario": "hu2024", "cases": cases}


def test_comparison_table_hu2024_shows_targets_and_the_papers_note():
    text = _render(_hu_summary())
    assert "Hu 2024 gives figures only (Figs. 5-11)" in text
    assert "noise 2e-05 rad" in text and "ekf-baseline" in text and "500 runs" in text
    assert "3 without estimate" in text
    assert "0.107 deg" in text and "0.5 deg target" in text and "0.214x" in text
    assert "0.0229 m" in text and "0.005 m target" in text and "4.58x worse" in text
    assert "0.561" in text and "[0.978, 1.02] 95%" in text and "conservative" in text


def _kabir_summary() -> dict:
    cases = []
    for f in (0.025, 0.075):
        for label, est, occluded, extra in kabir2025.FILTERS:
            scale = {"ukf": 9.0, "ukf-mult": 20.0}.get(label, 1.0)
            cases.append(
                {
                    "f_T_hz": f,
                    "estimator": est,
                    "occluded": occluded,
                    "label": label,
                    **({"gp_variance": extra["gp_variance"]} if "gp_variance" in extra else {}),
                    "runs": 20,
                    "runs_failed": 0,
                    "window_s": [1500.0, 3000.0],
                    "rmse": {"attitude_deg": 0.597 * scale, "rate_deg_s": 0.252 * scale},
                    "nees": _nees(0.898, 0.875, 1.13, 23),
                    "paper_values": {"note": "Kabir 2025 Figs. 5-9 (plots only)"},
                }
            )
    gp = [
        {
            "f_T_hz": 0.025,
            "T_train_s": T,
            "T_p_s": 441.0,
            "T_train_over_T_p": T / 441.0,
            "runs": 20,
            "gp_rmse_rad": r,
            "gp_rmse_rad_max": 1.5 * r,
            "train_time_s": 1.43,
            "badly_trained": b,
            "paper_values": {"note": "Kabir 2025 Fig. 4 (box plots only)"},
        }
        for T, r, b in ((500.0, 0.128, 20), (1500.0, 3.61e-6, 0), (2000.0, 8e-6, 3))
    ]
    return {"paper": "kabir2025", "scenario": "kabir2025", "cases": cases, "gp_study": gp}


def test_comparison_table_kabir2025_compares_with_the_benchmark():
    text = _render(_kabir_summary())
    assert "Kabir 2025 Figs. 5-9 (plots only)" in text
    assert "f_T 0.025 Hz" in text and "ukf-gp-predictive" in text
    assert "occluded" in text and "no occlusion" in text
    assert "0.597 deg bench." in text and "5.37 deg" in text and "9x worse" in text
    assert "11.9 deg" in text and "20x worse" in text  # ukf-mult against ukf-mult-benchmark
    assert "0.898" in text and "[0.875, 1.13] 95%" in text and "inside" in text
    # the GP study (Fig. 4): ours, the target, and the run that misses it
    assert "3.61e-06" in text and "1.2e-05 miss" in text and "3/20" in text


@pytest.mark.parametrize("make", [_yu_summary, _hu_summary, _kabir_summary])
def test_comparison_table_fits_100_columns(make):
    text = _render(make(), width=100)
    assert max(len(line.rstrip()) for line in text.splitlines()) <= 100


def test_yu2019_builtin_uses_1cm_noise_and_the_cases_set_theirs():
    """The built-in uses 0.01 m (the paper prints 0.1 m, argued a typo); `reproduce` sets the
    noise of each case itself, so the built-in's value does not change its cases."""
    sc = load_scenario("yu2019")
    assert sc.sensor.range_noise_m == 0.01
    assert [n for n, _ in yu2019.CASES] == [0.01, 0.01, 0.1]


def test_reproduce_yu2019_honours_runs(tmp_path, monkeypatch):
    """--runs N: every filter case is N seeded runs (was 1 whatever was asked)."""
    short = load_scenario("yu2019").with_updates(duration_s=12.0)
    monkeypatch.setattr(yu2019, "base_scenario", lambda: short)
    con = Console(file=io.StringIO())
    s = yu2019.reproduce(tmp_path, runs=2, workers=1, console=con)
    assert [(c["noise_m"], c["multi_solution_fix"]) for c in s["cases"]] == list(yu2019.CASES)
    for c, (noise, fix) in zip(s["cases"], yu2019.CASES, strict=True):
        assert c["runs"] + c["runs_failed"] == 2
        if c.get("runs_without_estimate", 0) < c["runs"]:
            assert c["nees"]["bounds95"] is not None and "attitude_deg" in c["rmse"]
        else:  # Yu's printed 0.1 m noise in 12 s: ekf-depth starts only on agreeing
            # rectangles (issue 18), so it may rightly not start; the case says so
            assert noise >= 0.1 and c["runs_without_estimate"] == c["runs"]
        folder = yu2019.case_dir(tmp_path, noise, fix)
        assert len(list((folder / "runs").glob("run_*.npz"))) == c["runs"]
        stored = yaml.safe_load((folder / "scenario.yaml").read_text())
        assert stored["sensor"]["range_noise_m"] == noise  # set by the recipe, per case
    assert (tmp_path / "fig9_10_attitude.png").exists()
    assert "1 run" not in _render(s) and "2 runs" in _render(s)


def test_reproduce_yu2019_refuses_zero_runs_before_any_work(tmp_path):
    with pytest.raises(InputError, match="--runs"):
        yu2019.reproduce(tmp_path / "out", runs=0)
    assert not (tmp_path / "out").exists()


def test_chang2021_table2_and_its_contradiction_are_recorded():
    """Chang 2021 Table 2 (per axis) as printed, the RMSE it implies, and Sec. 4.2's maxima
    that contradict it (a maximum below a standard deviation)."""
    from tumblenav.papers import chang2021

    t2 = chang2021.PAPER_TABLE2
    assert t2["attitude_deg"]["std"] == [0.4482, 0.5480, 0.5298]
    assert t2["position_m"]["std"] == [0.1146, 0.1157, 0.1161]
    assert chang2021.PAPER_RMSE["position_m"] == pytest.approx(0.2003, abs=1e-3)
    for key, maximum in chang2021.PAPER_SEC42_MAX.items():
        if key != "attitude_deg":
            assert max(t2[key]["std"]) > maximum  # the contradiction the summary notes
    sc = chang2021.case_scenario("close", "table1")
    assert sc.sensor.focal_px == 2029.8 and sc.sensor.resolution_px == [1280, 1280]
    sc = chang2021.case_scenario("printed", "text")
    assert sc.sensor.focal_px == pytest.approx(1623.86, abs=0.01) and sc.sensor.images


def test_reproduce_chang2021_runs_its_cases_on_images(tmp_path):
    """A short close-range case end to end: rendered images, the image front end, ekf-pose,
    Table 2's per-axis statistics next to the paper's, the Figs. 14-19 analogues."""
    from tumblenav.papers import chang2021

    base = load_scenario("chang2021_close").with_updates(
        duration_s=8.0,
        steady_state_window_s=[6.0, 8.0],
        **{"estimator.tuning": {"init_frames": 15}},
    )
    con = Console(file=io.StringIO())
    s = chang2021.reproduce(
        tmp_path, runs=1, workers=1, console=con, cases=(("close", "text"),), bases={"close": base}
    )
    (case,) = s["cases"]
    assert case["runs"] + case["runs_failed"] == 1 and case["camera"] == "text"
    assert case["paper_table2"] == chang2021.PAPER_TABLE2 and "contradict" in s["note"]
    if case["runs"]:
        assert set(case["per_axis"]) >= {"attitude_deg", "position_m"}
        assert len(case["per_axis"]["position_m"]["std"]) == 3
        assert set(case["targets_met"]) == set(chang2021.TARGETS_CLOSE_STD)
    for fig in (
        "fig14_15_features.png",
        "fig18_feature_count.png",
        "close_text/errors_per_axis.png",
    ):
        assert (tmp_path / fig).exists(), fig
    assert "chang2021" in _render(s)


@pytest.mark.parametrize("paper", ["yu2019", "chang2021"])
def test_reproduce_passes_the_dask_scheduler_to_its_campaigns(paper, tmp_path, monkeypatch):
    """`reproduce --scheduler ADDRESS` runs the recipe's campaigns on the cluster."""
    from tumblenav import papers
    from tumblenav.campaign import runner

    seen = {}

    class Stop(Exception):
        pass

    def fake(*args, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(runner, "run_campaign", fake)
    if paper == "yu2019":  # its tables come first: skip them
        monkeypatch.setattr(yu2019, "table1", lambda: [])
        monkeypatch.setattr(yu2019, "table2", lambda: [])
        monkeypatch.setattr(yu2019, "table3_4", lambda: ([], []))
    with pytest.raises(Stop):
        papers.reproduce(paper, tmp_path, runs=1, scheduler="tcp://127.0.0.1:1")
    assert seen["scheduler"] == "tcp://127.0.0.1:1"
