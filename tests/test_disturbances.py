"""The truth's random disturbances (tumblenav.dynamics.disturbances): torque-free limit, the
spectral densities the filters' Q assume, determinism, and the scenario switch."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from tumblenav import dynamics
from tumblenav.dynamics.disturbances import (
    angular_acceleration_psd,
    disturbed_attitude,
    translational_disturbance,
)
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate


@pytest.mark.parametrize(
    "inertia",
    [np.array([8.0, 5.0, 4.0]), np.array([[8.0, 0.3, -0.2], [0.3, 5.0, 0.1], [-0.2, 0.1, 4.0]])],
)
def test_zero_density_is_the_torque_free_motion(inertia):
    t = np.arange(0.0, 200.0 + 1e-9, 0.1)
    q0, w0 = np.array([0.1, -0.2, 0.3, 0.9]), np.array([0.1, 0.1, 0.1])
    q_ref, w_ref = dynamics.propagate_attitude(q0, w0, inertia, t)
    q, w = disturbed_attitude(q0, w0, inertia, t, 0.0, np.random.default_rng(0))
    # same rotation (sign-insensitive) and rate; RK4 on 2 mrad sub-steps: ~1e-9 over 200 s
    assert np.max(1.0 - np.abs(np.sum(q * q_ref, axis=1))) < 1e-12
    assert np.max(np.abs(w - w_ref)) < 1e-9


def test_angular_acceleration_density_is_hu_eq22():
    # Hu 2024 eq. 22: J = diag(1, Ix/Iy, Ix/Iz) with x the largest moment; density q_r J^2
    S = angular_acceleration_psd([8.0, 5.0, 4.0], 2.5e-5)
    np.testing.assert_allclose(S, 2.5e-5 * np.diag([1.0, (8 / 5) ** 2, 2.0**2]), rtol=1e-14)
    # any labelling: the largest moment's axis gets q_r itself
    S = angular_acceleration_psd([4.0, 5.0, 8.0], 1.0)
    np.testing.assert_allclose(np.diag(S), [4.0, (8 / 5) ** 2, 1.0], rtol=1e-14)


def test_rate_random_walk_has_the_stated_density():
    # a body at rest: the rate after T is a random walk of covariance S T (Euler's coupling
    # is second order in the small rates); 600 seeded runs, each variance within its 99.9 %
    # chi-square interval
    inertia, q_r, T = np.array([8.0, 5.0, 4.0]), 1e-6, 20.0
    t = np.arange(0.0, T + 1e-9, 1.0)
    R = 600
    end = np.array(
        [
            disturbed_attitude(
                [0, 0, 0, 1.0], np.zeros(3), inertia, t, q_r, np.random.default_rng(s)
            )[1][-1]
            for s in range(R)
        ]
    )
    expected = np.diag(angular_acceleration_psd(inertia, q_r)) * T
    ratio = np.mean(end**2, axis=0) / expected
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], R) / R
    assert np.all((ratio > lo) & (ratio < hi)), ratio


def test_translational_disturbance_matches_the_cw_model():
    # no orbit (n = 0): a double integrator, cov(v) = q T, cov(r) = q T^3 / 3, cov(r, v) = q T^2/2
    q, T, R = 1e-4, 10.0, 2000
    t = np.arange(0.0, T + 1e-9, 0.5)
    rng = np.random.default_rng(3)
    x = np.array(
        [
            np.concatenate([a[-1] for a in translational_disturbance(0.0, t, q, rng)])
            for _ in range(R)
        ]
    )
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], R) / R
    ratio_v = np.mean(x[:, 3:] ** 2, axis=0) / (q * T)
    ratio_r = np.mean(x[:, :3] ** 2, axis=0) / (q * T**3 / 3)
    assert np.all((ratio_v > lo) & (ratio_v < hi)), ratio_v
    assert np.all((ratio_r > lo) & (ratio_r < hi)), ratio_r
    corr = np.mean(x[:, 0] * x[:, 3]) / (q * T**2 / 2)
    assert abs(corr - 1.0) < 0.15
    # with an orbit the response starts at zero and stays finite
    dr, dv = translational_disturbance(1.1e-3, t, q, np.random.default_rng(0))
    assert np.all(dr[0] == 0) and np.all(dv[0] == 0) and np.all(np.isfinite(dr))


def test_scenario_switch_and_determinism():
    from tumblenav.papers.hu2024 import PAPER_SETTING  # a torque-free truth, Q = 2.5e-5

    base = (
        load_scenario("hu2024")
        .with_updates(**PAPER_SETTING)
        .model_copy(update={"duration_s": 20.0})
    )
    truth_off, _ = simulate(base, seed=5)
    pn = base.process_noise.model_copy(update={"disturb_truth": True})
    on = base.model_copy(update={"process_noise": pn})
    truth_a, meas_a = simulate(on, seed=5)
    truth_b, meas_b = simulate(on, seed=5)
    truth_c, _ = simulate(on, seed=6)
    np.testing.assert_array_equal(truth_a.omega_TI_T, truth_b.omega_TI_T)
    np.testing.assert_array_equal(truth_a.r_L, truth_b.r_L)
    assert not np.array_equal(truth_a.omega_TI_T, truth_c.omega_TI_T)
    # features are drawn from their own stream: the same with and without disturbances
    np.testing.assert_array_equal(truth_a.features_T, truth_off.features_T)
    # the disturbance is of the size the densities state: rate walk ~ sqrt(q_r J^2 t)
    dw = truth_a.omega_TI_T[-1] - truth_off.omega_TI_T[-1]
    sig = np.sqrt(np.diag(angular_acceleration_psd(base.target.inertia_matrix, 2.5e-5)) * 20.0)
    assert np.all(np.abs(dw) < 6 * sig) and np.any(np.abs(dw) > 0.05 * sig)
    dv = truth_a.v_L[-1] - truth_off.v_L[-1]
    assert np.all(np.abs(dv) < 6 * np.sqrt(2e-6 * 20.0)) and np.any(dv != 0)
