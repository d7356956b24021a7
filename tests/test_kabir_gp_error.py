"""ukf-gp's model of its pseudo-measurements' error (issue 18): the consider (Schmidt) update
that leaves the rigid parameters to the training data, the prediction without their process
noise while nothing is measured, the fitted motion's extrapolation error under a random
torque (against a Monte Carlo of least-squares fits), and the GPs' disagreement measured from
the residual no rigid motion explains."""

import numpy as np
import pytest

from tumblenav import rotations as rot
from tumblenav.estimators.base import EstimateHistory
from tumblenav.estimators.kabir2025 import filter as F
from tumblenav.estimators.kabir2025 import mismatch, ukf_gp
from tumblenav.estimators.kabir2025 import model as M
from tumblenav.estimators.kabir2025 import observations as O
from tumblenav.estimators.kabir2025 import tuning as T

FEATURES = np.array(
    [[0.4, -0.6, 0.3], [-0.9, 0.5, 0.8], [0.7, 0.9, -0.5], [-0.3, -0.8, -0.9], [1.1, 0.2, 0.6]]
)
CENTRES_X = np.array([0.0, 0.5])  # a parallel rig with a 0.5 m baseline


def geometry(n):
    rho0 = np.broadcast_to([0.0, 10.0, 0.0], (n, 3)).copy()
    return M.KabirGeometry(np.eye(3), rho0, np.zeros((n, 3)), CENTRES_X)


def state(omega=(0.05, 0.1, -0.08), k=(-0.1, 0.1)):
    return np.concatenate([omega, rot.exp_quat([0.3, -0.2, 0.5]), k, FEATURES.ravel()])


def model(variant):
    tun = T.parse_tuning(
        {
            "mass_centre_L_m": [0.0, 10.0, 0.0],
            "q_omega_var": 1e-8,
            "q_quat_var": 1e-9,
            "q_k_var": 1e-6,
            "q_feature_var": 1e-6,
            "sigma_flow_rad_s": 1e-5,
            "update_chart": "body",  # a consider update stays in it: compared alike
        }
    )
    return F._UKFModel.make(24 if variant == "additive" else 23, 5, geometry(3), tun, variant)


def random_cov(d, rng, scale):
    A = rng.normal(size=(d, d)) * scale
    return A @ A.T + np.diag(scale**2)


@pytest.mark.parametrize("variant", ["additive", "mult"])
def test_consider_update_keeps_the_rigid_parameters_and_updates_the_rest_as_usual(variant):
    rng = np.random.default_rng(1)
    m = model(variant)
    d = 24 if variant == "additive" else 23
    o = 7 if variant == "additive" else 6  # first rigid component (inertia ratios, features)
    x = state()[None]
    scale = np.r_[np.full(3, 1e-3), np.full(o - 3, 1e-2), np.full(d - o, 1e-2)]
    P = random_cov(d, rng, scale)[None]
    truth = state(omega=(0.051, 0.099, -0.079))
    truth[3:7] = rot.quat_multiply(rot.exp_quat([0.01, -0.02, 0.005]), truth[3:7])
    z = O.measurement_model(truth, np.eye(3), np.array([0.0, 10.0, 0.0]), np.zeros(3), CENTRES_X)
    z = z.reshape(1, -1) + rng.normal(size=(1, 45)) * 1e-5
    R = np.full((1, 45), 1e-10)
    rows = np.ones((1, 45), dtype=bool)
    x1, P1, *_ = m.update(x, P, 1, z, R, rows)
    x2, P2, *_ = m.update(x, P, 1, z, R, rows, np.array([True]))
    # the rigid parameters keep their mean and covariance
    np.testing.assert_array_equal(x2[0, 7:], x[0, 7:])
    np.testing.assert_allclose(P2[0, o:, o:], P[0, o:, o:], rtol=1e-12, atol=0)
    # the rate and attitude, and their covariance with everything, as the optimal update's
    # (Schmidt: the suboptimal gain is only in the rigid rows)
    assert np.abs(x1[0, 7:] - x[0, 7:]).max() > 1e-4  # the usual update moves them
    np.testing.assert_allclose(x2[0, :7], x1[0, :7], rtol=0, atol=1e-12)
    np.testing.assert_allclose(P2[0, :o, :], P1[0, :o, :], rtol=1e-9, atol=1e-18)
    assert np.all(np.linalg.eigvalsh(P2[0]) > 0)


@pytest.mark.parametrize("variant", ["additive", "mult"])
def test_no_process_noise_on_the_rigid_parameters_where_nothing_updates_them(variant):
    rng = np.random.default_rng(2)
    m = model(variant)
    d = 24 if variant == "additive" else 23
    o = 7 if variant == "additive" else 6
    x = state()[None]
    P = random_cov(d, rng, np.full(d, 1e-3))[None]
    _, P1, _ = m.predict(x, P, 1.0)
    _, P2, _ = m.predict(x, P, 1.0, rigid_fixed=np.array([True]))
    # the rigid body's inertia and features do not move: the unscented transform returns
    # their covariance unchanged, with Q (1e-6) only where an update may follow
    np.testing.assert_allclose(P2[0, o:, o:], P[0, o:, o:], rtol=1e-9)
    np.testing.assert_allclose(P1[0, o:, o:] - P[0, o:, o:], m.Q[o:, o:], rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(P2[0, :o, :o], P1[0, :o, :o], rtol=1e-12)


def history(x, n):
    lay = M.layout(5)
    return EstimateHistory(
        t=np.arange(n, dtype=float),
        x=np.repeat(x[None], n, axis=0),
        P=np.repeat(np.eye(lay.dim)[None], n, axis=0),
        layout=lay,
        nis=np.full(n, np.nan),
        nis_dof=np.zeros(n, dtype=int),
    )


def test_motion_covariance_is_the_least_squares_fits_extrapolation_error():
    # a body at rest with equal moments: its attitude error is, per axis, the integral of a
    # random walk of the rate (white angular acceleration q); the GP's motion is a fit of a
    # constant rate to the attitude seen over [0, 199] s, extrapolated over [200, 299] s. A
    # Monte Carlo of that least-squares fit (the continuous walk on 20 substeps a second)
    # against the recursion of gp_motion_covariance
    q, n_train, n = 1e-12, 200, 300
    h = history(state(omega=(0.0, 0.0, 0.0), k=(0.0, 0.0)), n)
    real = np.arange(n) < n_train
    D = ukf_gp.gp_motion_covariance(h, h.t, real, ~real, q, sigma_att=1e-9)
    assert np.all(D[real] == 0.0)
    rng = np.random.default_rng(3)
    sub, runs = 20, 4000
    a = rng.normal(size=(runs, n * sub)) * np.sqrt(q * sub)  # held over 1/sub s
    w = np.cumsum(a, axis=1) / sub
    theta = (np.cumsum(w, axis=1) / sub)[:, sub - 1 :: sub]  # at t = 0, 1, ..., n - 1
    A = np.stack([np.ones(n_train), h.t[:n_train]], axis=1)
    c = np.linalg.lstsq(A, theta[:, :n_train].T, rcond=None)[0]
    err = theta - (c[0][:, None] + c[1][:, None] * h.t[None])
    for k in (n_train, n_train + 50, n - 1):
        var_mc = float(np.var(err[:, k]))  # 2.2 % sampling error on 4000 runs
        np.testing.assert_allclose(np.diag(D[k, 3:, 3:]), var_mc, rtol=0.1)
    # the rate: the fitted constant rate's error against the walk at the same epochs
    rate_err = w[:, sub - 1 :: sub] - c[1][:, None]
    np.testing.assert_allclose(np.diag(D[n - 1, :3, :3]), np.var(rate_err[:, n - 1]), rtol=0.1)
    # no disturbance: only the fit's own noise (1e-9 rad an epoch) is left
    D0 = ukf_gp.gp_motion_covariance(h, h.t, real, ~real, 0.0, 1e-9)
    assert np.abs(D0[:, 3:, 3:]).max() < 1e-17 and np.abs(D0).max() < 1e-15


def test_motion_covariance_follows_the_torques_axes():
    # q_r is the angular acceleration's density about the largest moment; about axis i it is
    # q_r (I_max / I_i)^2 (tumblenav.dynamics.disturbances): at rest the rate errors keep it
    k = (np.log(0.7), np.log(1.3))  # moments 70, 100, 130
    h = history(state(omega=(0.0, 0.0, 0.0), k=k), 300)
    real = np.arange(300) < 200
    D = ukf_gp.gp_motion_covariance(h, h.t, real, ~real, 1e-12, sigma_att=1e-9)
    ratio = np.diag(D[-1, :3, :3]) / D[-1, 2, 2]
    np.testing.assert_allclose(ratio, (1.3 / np.array([0.7, 1.0, 1.3])) ** 2, rtol=1e-6)


@pytest.mark.parametrize("sigma_b", [0.0, 3e-5])
def test_inconsistency_measures_what_no_rigid_motion_explains(sigma_b):
    # pseudo-measurements of a tumbling body turned by a common error (the GPs' motion error:
    # the filter follows it) plus independent per-feature errors of sigma_b (their own)
    rng = np.random.default_rng(4)
    n = 200
    x = state()
    h = history(x, n)
    g = geometry(n)
    off = rng.normal(size=(n, 3)) * 1e-3
    xt = np.repeat(x[None], n, axis=0)
    xt[:, 3:7] = rot.quat_multiply(rot.exp_quat(off), xt[:, 3:7])
    xt[:, :3] += rng.normal(size=(n, 3)) * 1e-4
    zp = O.measurement_model(xt, g.R_CI, g.rho0_C, g.rho0_dot_C, CENTRES_X)
    sigma_f = sigma_b * 0.3  # its flows'
    zp[..., [0, 1, 2]] += rng.normal(size=(n, 5, 3)) * sigma_b
    zp[..., [5, 6, 7]] += rng.normal(size=(n, 5, 3)) * sigma_f
    Rs = np.broadcast_to(np.r_[np.full(5, 1e-10), np.full(4, 1e-10)], zp.shape).copy()
    pseudo = np.ones(n, dtype=bool)
    s2, Db, J = ukf_gp.gp_inconsistency(h, g, zp, Rs, pseudo, window=40)
    mid = slice(20, n - 20)  # full windows
    if sigma_b == 0.0:
        # only the linearisation of a 1e-3 rad turn remains: below 1 % of 3e-5
        assert np.sqrt(s2[mid].max()) < 3e-7
        return
    np.testing.assert_allclose(np.sqrt(s2[mid, 0].mean()), sigma_b, rtol=0.05)
    np.testing.assert_allclose(np.sqrt(s2[mid, 1].mean()), sigma_f, rtol=0.05)
    # D_b: one epoch's least squares of rate and attitude with these variances
    k = n // 2
    cols = [0, 1, 2, 5, 6, 7]
    Jc = J[k][:, cols].reshape(-1, 6)
    w = np.tile(1.0 / np.r_[np.full(3, s2[k, 0]), np.full(3, s2[k, 1])], 5)
    np.testing.assert_allclose(Db[k], np.linalg.inv(Jc.T @ (Jc * w[:, None])), rtol=1e-6)


def test_measurement_jacobians_against_central_differences():
    rng = np.random.default_rng(5)
    n = 4
    h = history(state(), n)
    h.x[:] += np.r_[rng.normal(size=3) * 1e-3, np.zeros(4), rng.normal(size=17) * 1e-2]
    h.x[:, 3:7] = rot.exp_quat(rng.normal(size=(n, 3)))
    g = geometry(n)
    ks = np.arange(n)
    J = mismatch.measurement_jacobians(h.layout, g, h.x, ks)
    lay, d, eps = h.layout, h.layout.dim, 1e-5
    for j in range(d):
        dx = np.zeros((n, d))
        dx[:, j] = eps
        hp = O.measurement_model(lay.boxplus(h.x, dx), g.R_CI, g.rho0_C, g.rho0_dot_C, CENTRES_X)
        hm = O.measurement_model(lay.boxplus(h.x, -dx), g.R_CI, g.rho0_C, g.rho0_dot_C, CENTRES_X)
        num = (hp - hm) / (2 * eps)
        scale = np.abs(num).max() + 1e-12
        np.testing.assert_allclose(J[..., j], num, rtol=0, atol=1e-5 * scale)


def test_floor_congruence_maps_the_filters_covariance_onto_the_actual_one():
    rng = np.random.default_rng(6)
    Pf = random_cov(17, rng, np.full(17, 1e-4))
    Pa = random_cov(17, rng, np.full(17, 3e-5))
    S = ukf_gp.floor_congruence(Pf, Pa)
    np.testing.assert_allclose(S, S.T, rtol=0, atol=1e-12 * np.abs(S).max())
    assert np.all(np.linalg.eigvalsh(S) > 0)
    np.testing.assert_allclose(S @ Pf @ S, Pa, rtol=0, atol=1e-9 * np.abs(Pa).max())
    np.testing.assert_allclose(ukf_gp.floor_congruence(Pf, Pf), np.eye(17), atol=1e-9)


def test_rigid_floor_correction_is_the_error_covariance_of_a_filter_with_the_floor():
    # a Monte Carlo of the linearised problem: the truth's rigid parameters are constant and its
    # rate and attitude walk with the real Q; a Kalman filter with the floor on the rigid
    # parameters (Q_f) measures eq. 22-23's projections at every epoch but the last ten. Its
    # errors' covariance is P_a, its own P is P_f; P_a is below P_f (the floor is fictitious)
    # and nothing changes where nothing is measured
    rng = np.random.default_rng(7)
    n, runs = 40, 4000
    h = history(state(), n)
    lay, d = h.layout, h.layout.dim
    h.P[:] = np.nan
    P0 = np.diag(np.r_[np.full(3, 1e-8), np.full(3, 1e-6), np.full(2, 1e-6), np.full(15, 1e-6)])
    h.P[0] = P0
    g = geometry(n)
    z = np.zeros((n, 5, 9))
    z[-10:] = np.nan
    z[5, 2, :] = np.nan  # a feature not seen
    R = np.broadcast_to(np.r_[np.full(5, 1e-10), np.full(4, 1e-8)], z.shape).copy()
    tun = T.parse_tuning(
        {
            "mass_centre_L_m": [0.0, 10.0, 0.0],
            "q_omega_var": 1e-9,
            "q_quat_var": 1e-9,
            "q_k_var": 1e-9,
            "q_feature_var": 1e-9,
            "sigma_flow_rad_s": 1e-4,
        }
    )
    Pf, Pa = ukf_gp.rigid_floor_correction(h, h.t, z, R, tun, g)
    E = np.arange(d)
    dyn = np.r_[E[lay.err("rate")], E[lay.err("attitude")], E[lay.err("inertia")]]
    Fd = mismatch.step_jacobians(lay, h.x, h.t, dyn, np.arange(1, n))
    H = mismatch.measurement_jacobians(lay, g, h.x, np.arange(n))
    qa = np.r_[np.full(3, 1e-9), np.full(3, 4e-9), np.zeros(17)]
    qf = np.r_[np.full(3, 1e-9), np.full(3, 4e-9), np.full(17, 1e-9)]
    e = rng.multivariate_normal(np.zeros(d), P0, size=runs)  # (runs, d) the filter's error
    P = P0.copy()
    for k in range(1, n):
        F = np.eye(d)
        F[np.ix_(dyn, dyn)] = Fd[k - 1]
        zk = z[k].reshape(-1)
        seen = np.isfinite(zk)
        e = e @ F.T + rng.normal(size=(runs, d)) * np.sqrt(qa)
        P = F @ P @ F.T + np.diag(qf if seen.any() else qa)
        if seen.any():
            Hk = H[k].reshape(-1, d)[seen]
            Rk = R[k].reshape(-1)[seen]
            K = np.linalg.solve(Hk @ P @ Hk.T + np.diag(Rk), Hk @ P).T
            v = rng.normal(size=(runs, len(Rk))) * np.sqrt(Rk)
            e = e - (e @ Hk.T + v) @ K.T
            P = (np.eye(d) - K @ Hk) @ P
        np.testing.assert_allclose(Pf[k], P, rtol=1e-6, atol=1e-6 * np.abs(P).max())
    C = np.cov(e.T)  # at the last epoch, ten epochs after the last measurement
    sd = np.sqrt(np.diag(Pa[-1]))
    # correlation-scaled comparison: 4000 runs, sampling error ~2-5 %
    np.testing.assert_allclose(np.diag(C) / sd**2, 1.0, atol=0.1)
    np.testing.assert_allclose(C / np.outer(sd, sd), Pa[-1] / np.outer(sd, sd), atol=0.1)
    rig = np.r_[E[lay.err("inertia")], E[lay.err("features")]]
    # the floor only adds: P_a <= P_f (Loewner order), strictly on the rigid parameters
    gap = Pf[-1] - Pa[-1]
    assert np.linalg.eigvalsh(gap).min() > -1e-9 * np.abs(Pf[-1]).max()
    assert np.all(np.diag(gap)[rig] > 0.02 * np.diag(Pf[-1])[rig])
    np.testing.assert_allclose(
        Pa[-10:][:, rig[:, None], rig],
        np.broadcast_to(Pa[-10][rig[:, None], rig], (10, len(rig), len(rig))),
        rtol=1e-9,
    )


def test_pseudo_r_is_the_gps_own_error_where_it_is_a_pseudo_measurement():
    rng = np.random.default_rng(8)
    R = rng.uniform(1e-10, 2e-10, size=(6, 5, 9))
    extra = np.where(rng.uniform(size=R.shape) < 0.5, rng.uniform(1e-9, 1e-8, R.shape), 0.0)
    out = ukf_gp.pseudo_r(R, extra)
    np.testing.assert_array_equal(out[extra == 0], R[extra == 0])
    np.testing.assert_allclose(out[extra > 0], extra[extra > 0] + 0.01 * R[extra > 0])
