"""Kabir 2025 observation model (Sec. 2.2.2, eq. 16-23, Appendix A) and the finite-difference
rate of eq. 27: projections against the stereo sensor, the flow matrices A_R, A_L against
finite differences of the projections along a simulated tumbling trajectory, and the order of
accuracy and NaN-gap handling of the finite differences.  Seeded throughout.
"""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from tumblenav import dynamics
from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.frontends import projections as proj
from tumblenav.sensors import convergent_rig

# Kabir 2025 Sec. 3.2: inertia, features and omega0 = 2 pi f_T [2/3, 1/3, 2/3] (f_T = 0.075 Hz)
INERTIA = np.array([90.0, 100.0, 112.0])
FEATURES_T = np.array(
    [
        [0.1302, 0.6648, 0.2264],
        [1.0343, 1.4858, 1.1352],
        [0.5122, 0.9775, 1.0898],
        [0.2252, 1.1739, 0.8723],
        [0.9440, 1.1748, 0.8409],
    ]
)
OMEGA0 = 2 * np.pi * 0.075 * np.array([2 / 3, 1 / 3, 2 / 3])


def tumbling_points(t, rho0_C, v0_C, R_CI, q0=rot.IDENTITY):
    """Features in C, the rate in C and the mass centre at times t (torque-free truth)."""
    q, w = dynamics.propagate_attitude(q0, OMEGA0, INERTIA, t)
    R_CT = R_CI @ np.swapaxes(rot.quat_to_matrix(q), -1, -2)
    c = rho0_C + np.outer(t, v0_C)
    rho = c[:, None, :] + np.einsum("tij,nj->tni", R_CT, FEATURES_T)
    return rho, np.einsum("tij,tj->ti", R_CT, w), c


def kabir_R_matrix(rho, rho0):
    """Kabir 2025 eq. 20 / A7 with its minus signs restored (x from the camera centre)."""
    x, y, z = rho
    x0, y0, z0 = rho0
    return np.array(
        [
            [x * (z - z0) / y**2, (z - z0) / y, -(y - y0) / y - x * (x - x0) / y**2],
            [(y - y0) / y + z * (z - z0) / y**2, -(x - x0) / y, -z * (x - x0) / y**2],
        ]
    )


@pytest.mark.parametrize("centres_x", [(0.0, 0.5), (-0.3, 0.2)])
def test_flow_matrices_match_finite_differences_along_a_trajectory(centres_x):
    # Kabir 2025 eq. 18-21: w_dot = A omega for a point tumbling about the known mass centre
    R_CI = rot.exp_map([0.1, -0.2, 0.05])  # any fixed rig attitude
    rho0 = np.array([0.3, 10.0, -0.4])
    h = 1e-3
    for t0 in (0.0, 7.3, 41.0):
        t = np.array([t0, t0 + h, t0 + 2 * h])
        rho, om, c = tumbling_points(t, rho0, np.zeros(3), R_CI)
        uv = proj.projection_model(rho, centres_x)  # (3, N, cam, 2)
        flow_fd = (uv[2] - uv[0]) / (2 * h)  # central difference at t0 + h
        A_R, A_L = proj.flow_matrices(rho[1], c[1], centres_x)
        np.testing.assert_allclose(A_R @ om[1], flow_fd[:, 1], atol=1e-9)
        np.testing.assert_allclose(A_L @ om[1], flow_fd[:, 0], atol=1e-9)
        # the corrected printed form (x measured from each camera's centre)
        for i in range(len(FEATURES_T)):
            for A, cx in ((A_R, centres_x[1]), (A_L, centres_x[0])):
                shift = np.array([cx, 0.0, 0.0])
                np.testing.assert_allclose(
                    A[i], kabir_R_matrix(rho[1, i] - shift, c[1] - shift), atol=1e-14
                )


def test_kabir_h_matches_projections_and_flow_with_a_moving_mass_centre():
    R_CI = np.eye(3)
    rho0, v0 = np.array([0.0, 10.0, 0.0]), np.array([0.01, -0.02, 0.005])
    h = 1e-3
    t = np.array([5.0, 5.0 + h, 5.0 + 2 * h])
    rho, om, c = tumbling_points(t, rho0, v0, R_CI)
    cx = (0.0, 0.5)
    hk = proj.kabir_h(rho[1], c[1], om[1], cx, v0)  # (N, 9)
    uv = proj.projection_model(rho, cx)
    np.testing.assert_allclose(hk[:, 0:2], uv[1, :, 1], atol=1e-15)  # right = Kabir's R
    np.testing.assert_allclose(hk[:, 2:4], uv[1, :, 0], atol=1e-15)  # left = Kabir's L
    np.testing.assert_allclose(hk[:, 4], 0.5 / rho[1, :, 1], rtol=1e-13)  # u_L - u_R = b / y
    fd = (uv[2] - uv[0]) / (2 * h)
    np.testing.assert_allclose(hk[:, 5:7], fd[:, 1], atol=1e-9)
    np.testing.assert_allclose(hk[:, 7:9], fd[:, 0], atol=1e-9)
    # batched over leading axes (sigma points) like one call per state
    stack = proj.kabir_h(rho[None, 1].repeat(3, 0), c[None, 1].repeat(3, 0), om[1][None], cx, v0)
    np.testing.assert_allclose(stack, np.broadcast_to(hk, stack.shape), atol=0)


def test_normalised_orders_kabir_R_then_L_and_matches_the_sensor():
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate
    from tumblenav.testing import KABIR_TORQUE_FREE

    s = (
        load_scenario("kabir2025")
        .with_updates(**KABIR_TORQUE_FREE)
        .with_updates(duration_s=5.0, **{"sensor.noise.angular_rad": 0.0})
    )
    truth, meas = simulate(s, 7)
    w, obs = proj.normalised(meas)
    assert w.shape == (len(meas.t), 5, 4) and obs.all()
    cx = proj.parallel_centres_x(meas.rig)
    np.testing.assert_allclose(cx, [0.0, 0.5])
    uv = proj.projection_model(truth.features_C, cx)
    np.testing.assert_allclose(w[..., 0:2], uv[..., 1, :], atol=1e-12)
    np.testing.assert_allclose(w[..., 2:4], uv[..., 0, :], atol=1e-12)
    assert np.all(w[..., 2] - w[..., 0] > 0)  # disparity u_L - u_R = b / y > 0
    # an unobserved camera gives NaN for that camera only, and no stereo pair
    observed = meas.observed.copy()
    observed[2, 1, 3] = False
    import dataclasses

    w2, obs2 = proj.normalised(dataclasses.replace(meas, observed=observed))
    assert np.isnan(w2[2, 3, 0:2]).all() and np.isfinite(w2[2, 3, 2:4]).all()
    assert not obs2[2, 3] and obs2.sum() == obs.size - 1


def test_non_parallel_rig_is_rejected():
    with pytest.raises(InputError, match="parallel"):
        proj.parallel_centres_x(convergent_rig(1000.0, 0.5, 0.1, (1000, 1000)))


# --- Kabir 2025 eq. 27 ------------------------------------------------------------------


def test_finite_difference_rate_is_exact_on_polynomials_of_its_order():
    dt = 0.5
    t = np.arange(12) * dt
    quad = 1.0 - 2.0 * t + 0.3 * t**2
    d = proj.finite_difference_rate(quad, dt)
    exact = -2.0 + 0.6 * t
    np.testing.assert_allclose(d[1:-1], exact[1:-1], atol=1e-12)  # 2nd and 4th order exact
    np.testing.assert_allclose(d[0], exact[0] + 0.3 * dt, atol=1e-12)  # forward: + c dt
    np.testing.assert_allclose(d[-1], exact[-1] - 0.3 * dt, atol=1e-12)  # backward: - c dt
    quart = t**4 - t**3
    d = proj.finite_difference_rate(quart, dt)
    np.testing.assert_allclose(d[2:-2], (4 * t**3 - 3 * t**2)[2:-2], atol=1e-10)


def test_finite_difference_rate_order_of_accuracy_on_a_sine():
    def errors(dt):
        t = np.arange(0.0, 4.0 + dt / 2, dt)
        d = proj.finite_difference_rate(np.sin(t + 0.7), dt)
        e = np.abs(d - np.cos(t + 0.7))
        return e[0], e[1], np.max(e[2:-2])

    coarse, fine = errors(0.1), errors(0.05)
    ratios = [c / f for c, f in zip(coarse, fine, strict=True)]
    assert 1.8 < ratios[0] < 2.2  # first order at the ends
    assert 3.6 < ratios[1] < 4.4  # second order at the second sample
    assert 14.0 < ratios[2] < 18.0  # fourth order inside


def test_finite_difference_rate_splits_runs_at_nan_gaps():
    dt = 2.0
    w = np.arange(16, dtype=float) ** 2  # w' = 2 k / dt per sample index k
    w[[5, 8, 10]] = np.nan  # runs: 0-4, 6-7, 9 (alone), 11-15
    d = proj.finite_difference_rate(w, dt)
    assert np.isnan(d[[5, 8, 9, 10]]).all()  # gaps, and the single-sample run
    np.testing.assert_allclose(d[6], (w[7] - w[6]) / dt)  # run of two: forward, backward
    np.testing.assert_allclose(d[7], (w[7] - w[6]) / dt)
    np.testing.assert_allclose(d[0], (w[1] - w[0]) / dt)
    np.testing.assert_allclose(d[1], (w[2] - w[0]) / (2 * dt))
    np.testing.assert_allclose(d[2], 2 * 2 / dt)  # 4th order, exact on the quadratic
    np.testing.assert_allclose(d[3], (w[4] - w[2]) / (2 * dt))
    np.testing.assert_allclose(d[4], (w[4] - w[3]) / dt)
    np.testing.assert_allclose(d[13], 2 * 13 / dt)
    order = proj.finite_difference_order(w)
    np.testing.assert_array_equal(order, [1, 2, 4, 2, 1, 0, 1, 1, 0, 0, 0, 1, 2, 4, 2, 1])


@given(st.integers(0, 2**31 - 1))
def test_finite_difference_rate_treats_every_trailing_element_alone(seed):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(30, 3, 4))
    w[rng.random(w.shape) < 0.15] = np.nan
    d = proj.finite_difference_rate(w, 0.7)
    for i in range(3):
        for j in range(4):
            np.testing.assert_array_equal(d[:, i, j], proj.finite_difference_rate(w[:, i, j], 0.7))
