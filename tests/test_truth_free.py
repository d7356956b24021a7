"""Estimators never see the truth: the same measurements under a scenario whose target truth
(inertia, rate, attitude, features, relative state, mass-centre offset) was changed give
identical estimates, for every registered estimator."""

from __future__ import annotations

import numpy as np
import pytest

from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import EstimatorContext, context_from_scenario
from tumblenav.papers import kabir2025 as K
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate
from tumblenav.testing import KABIR_TORQUE_FREE

OTHER_TRUTH = {
    "target.inertia_kg_m2": [55.0, 70.0, 31.0],
    "target.omega0_T_rad_s": [0.03, -0.02, 0.05],
    "target.q0_TI": (
        np.array([0.2, -0.1, 0.3, 0.927]) / np.linalg.norm([0.2, -0.1, 0.3, 0.927])
    ).tolist(),
    "target.r0_L_m": [3.0, 17.0, -2.0],
    "target.v0_L_m_s": [0.01, -0.02, 0.0],
    "target.mass_centre_offset_T_m": [0.05, -0.02, 0.01],
}


def _scenarios():
    hu = load_scenario("hu2024").with_updates(
        duration_s=40.0,
        steady_state_window_s=[30.0, 40.0],
        occlusion={"windows": [{"start_s": 20.0, "end_s": 25.0}]},
    )
    yu = load_scenario("yu2019").with_updates(duration_s=12.0, steady_state_window_s=[6.0, 12.0])
    kab = (
        load_scenario("kabir2025")
        .with_updates(**KABIR_TORQUE_FREE)
        .with_updates(
            duration_s=80.0, steady_state_window_s=[60.0, 80.0], **{"occlusion.loss_from_s": 50.0}
        )
    )
    kab = K.with_paper_assumptions(kab)  # the recipe's truth-based start, as explicit settings
    chang = load_scenario("chang2021_close").with_updates(
        duration_s=12.0,
        steady_state_window_s=[8.0, 12.0],
        **{"sensor.images": None, "estimator.tuning": {"init_frames": 20}},
    )
    return {
        "ekf-dpacf": hu,
        "ekf-baseline": hu,
        "ekf-depth": yu,
        "ukf": kab,
        "ukf-mult": kab,
        "ukf-gp": kab,
        "ekf-pose": chang,
    }


def _changed(scenario):
    """The same scenario with another target truth (the same number of features)."""
    upd = dict(OTHER_TRUTH)
    f = scenario.target.features_T_m
    if isinstance(f, list):
        rng = np.random.default_rng(1)
        upd["target.features_T_m"] = rng.uniform(-0.8, 0.8, (len(f), 3)).tolist()
    elif scenario.sensor.kind == "stereo":  # drawn at random: another draw
        upd["target.features_T_m.seed"] = 12345
    return scenario.with_updates(**upd)


def test_the_context_holds_no_target_truth():
    ctx = context_from_scenario(load_scenario("hu2024"))
    assert isinstance(ctx, EstimatorContext)
    assert not hasattr(ctx, "target")
    with pytest.raises(AttributeError):
        ctx.target  # noqa: B018


def test_every_estimator_is_covered():
    assert set(_scenarios()) == set(est_base.available())


@pytest.mark.parametrize("name", sorted(_scenarios()))
def test_same_measurements_other_truth_same_estimates(name):
    sc = _scenarios()[name]
    other = _changed(sc)
    assert other.target != sc.target
    ss = run_seed(7, 0)
    _, meas = simulate(sc, ss)
    est = est_base.get(name)
    # the same random stream for each (a SeedSequence spawns new children on each use)
    a = est.run(context_from_scenario(sc), meas, np.random.default_rng(3))
    b = est.run(context_from_scenario(other), meas, np.random.default_rng(3))
    # the scenario object itself may be passed too: the estimator keeps only its context
    c = est.run(other, meas, np.random.default_rng(3))
    assert np.isfinite(a.x).any(), "the estimator never started: the test would prove nothing"
    for h in (b, c):
        np.testing.assert_array_equal(a.x, h.x)
        np.testing.assert_array_equal(a.P, h.P)
        np.testing.assert_array_equal(a.nis, h.nis)


@pytest.mark.parametrize("name", sorted(_scenarios()))
def test_estimate_from_a_measurement_folder_without_truth(name, tmp_path, capsys):
    """`tumblenav estimate --measurements DIR` for every estimator, from a folder with no
    truth.nc: estimates.nc, the estimates with their 3-sigma bands (estimates.png) and a
    summary without an error section."""
    from tumblenav import io
    from tumblenav.cli import main
    from tumblenav.scenario import scenario_to_yaml

    sc = _scenarios()[name]
    path = tmp_path / "sc.yaml"
    path.write_text(scenario_to_yaml(sc))
    _, meas = simulate(sc, run_seed(3, 0))
    folder = tmp_path / "data"
    io.write_netcdf(meas.to_dataset(sc.name), folder / "measurements.nc")
    out = tmp_path / "est"
    args = ["estimate", str(path), "-e", name, "--measurements", str(folder), "-o", str(out)]
    with pytest.raises(SystemExit) as ei:
        main(args)
    err = capsys.readouterr().err
    assert ei.value.code == 0, err
    summary = io.read_json(out / "summary.json")
    assert "rmse" not in summary and "nees" not in summary
    assert (out / "estimates.nc").exists() and not list(out.glob("errors.png"))
    assert (out / "estimates.png").stat().st_size > 10_000
