"""Kabir 2025 UKF (``ukf``) and its multiplicative variant (``ukf-mult``): the k1, k2 Euler
equations against the rigid-body truth (its fast quaternion algebra is tested in
tests/test_rotations.py), the covariance map against a numerical Jacobian, tuning errors, and short seeded runs on the
kabir2025 scenario (convergence, NEES, occlusion, pseudo-measurements, gate, batch).
"""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tumblenav import dynamics
from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.errors import InputError
from tumblenav.estimators import base
from tumblenav.estimators import ukf as U
from tumblenav.evaluation import alignment, metrics
from tumblenav.papers import kabir2025 as K
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate
from tumblenav.testing import KABIR_TORQUE_FREE, numerical_jacobian

quat = (
    arrays(np.float64, 4, elements=st.floats(-1.0, 1.0))
    .filter(lambda q: np.linalg.norm(q) > 0.1)
    .map(lambda q: q / np.linalg.norm(q))
)
vec3 = arrays(np.float64, 3, elements=st.floats(-1.0, 1.0))
moments = arrays(np.float64, 3, elements=st.floats(1.0, 10.0))
U3 = np.array([2 / 3, 1 / 3, 2 / 3])  # Kabir 2025 Sec. 3: omega0 = 2 pi f_T U3


def kabir(f_T=0.075, duration=400.0, occlusion=None, **tuning):
    """kabir2025 at tumbling frequency f_T with the paper's tuning for it (Sec. 3.2) and its
    truth-based assumptions (known mass centre, the paper's start, as the recipe makes them;
    ``init="triangulated"`` keeps the measurement-only start). Keys of ``start`` in
    ``tuning`` (rate_factor, q_offset_wxyz, feature_offset_m) shape the paper's start."""
    start = {
        k: tuning.pop(k)
        for k in ("rate_factor", "q_offset_wxyz", "feature_offset_m")
        if k in tuning
    }
    s = (
        load_scenario("kabir2025")
        .with_updates(**KABIR_TORQUE_FREE)
        .with_updates(
            duration_s=duration,
            **{
                "target.omega0_T_rad_s": list(2 * np.pi * f_T * U3),
                "occlusion.loss_from_s": occlusion,
                "estimator.tuning": {**U.paper_tuning(f_T), **tuning},
            },
        )
    )
    if tuning.get("init") == "triangulated":
        return s.with_updates(
            **{"estimator.tuning": {**s.estimator.tuning, **K.known_mass_centre(s)}}
        )
    return K.with_paper_assumptions(s, **start)


# 10 % of the paper's initial errors (Sec. 3.2) with P0 standard deviations scaled alike
NEAR = {
    "rate_factor": 1.075,
    "feature_offset_m": 0.07,
    "q_offset_wxyz": list(
        rot.to_scalar_first(rot.exp_quat(0.1 * rot.log_quat([0.1386, 0.1386, 0.1386, 0.9707])))
    ),
    "p0_omega_var": 0.1225e-2,
    "p0_quat_var": 0.04e-2,
    "p0_feature_var": 2.25e-2,
}


# --- model -------------------------------------------------------------------------------


@given(vec3, moments)
def test_euler_k_form_equals_the_rigid_body_equations(w, I):
    # Kabir 2025 eq. 7-8 with k1 = log(I1/I2), k2 = log(I3/I2)
    k = np.array([np.log(I[0] / I[1]), np.log(I[2] / I[1])])
    np.testing.assert_allclose(
        U.euler_rhs_k(w, k), dynamics.euler_rhs(w, I), rtol=1e-12, atol=1e-15
    )


def test_rk4_propagation_follows_the_torque_free_truth():
    I = np.array([90.0, 100.0, 112.0])
    k = np.array([np.log(0.9), np.log(1.12)])
    w0 = 2 * np.pi * 0.075 * U3
    q0 = rot.exp_quat([0.3, -0.2, 0.1])
    t = np.arange(0.0, 100.0 + 1e-9, 0.1)
    q_true, w_true = dynamics.propagate_attitude(q0, w0, I, t)
    w, q = w0, q0
    for _ in range(len(t) - 1):
        w, q = U.propagate_rotation(w, q, k, 0.1)
    np.testing.assert_allclose(w, w_true[-1], atol=1e-10)
    assert rot.quat_angle(rot.quat_multiply(q, rot.quat_conjugate(q_true[-1]))) < 1e-6


def sigma_like_states(seed: int, n: int = 49, spread: float = 1.0) -> np.ndarray:
    """(2, n, 24) states around Kabir's 0.075 Hz tumble (five features), non-unit quaternions
    as the additive UKF's sigma points have; ``spread`` scales the rate's scatter (large:
    several RK4 substeps)."""
    rng = np.random.default_rng(seed)
    x = np.empty((2, n, 24))
    x[..., 0:3] = 2 * np.pi * 0.075 * U3 * (1 + spread * 0.3 * rng.normal(size=(2, n, 3)))
    x[..., 3:7] = rot.exp_quat([0.3, -0.2, 0.1]) + 0.05 * rng.normal(size=(2, n, 4))
    x[..., 7:9] = [np.log(0.9), np.log(1.12)] + 0.1 * rng.normal(size=(2, n, 2))
    x[..., 9:] = rng.uniform(-1.5, 1.5, size=(2, n, 15))
    return x


@pytest.mark.parametrize("seed, spread, dt", [(0, 1.0, 1.0), (1, 30.0, 1.0), (2, 1.0, -0.5)])
def test_compiled_propagation_equals_the_numpy_reference(seed, spread, dt):
    # the filter's sigma points go through the compiled loop (kabir2025/kernels.py): the same
    # substeps and RK4 as propagate_rotation, to rounding
    x = sigma_like_states(seed, spread=spread)
    x[1, 3] = np.nan  # a diverged run's sigma point: NaN, ignored by the substep count
    from tumblenav.estimators.kabir2025.model import propagate_rotation_compiled

    ref = U.propagate_rotation(x[..., 0:3], x[..., 3:7], x[..., 7:9], dt)
    out = propagate_rotation_compiled(x[..., 0:3], x[..., 3:7], x[..., 7:9], dt)
    for a, b in zip(out, ref, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("seed, spread", [(0, 1.0), (1, 30.0)])
def test_compiled_stencil_model_equals_the_numpy_reference(seed, spread):
    # Kabir 2025 eq. 22-23 with eq. 27's stencil flow, compiled (the filter's update) and numpy
    from tumblenav.estimators.kabir2025 import observations as O

    x = sigma_like_states(seed, spread=spread)
    rng = np.random.default_rng(seed)
    R_CI = rot.quat_to_matrix(rot.exp_quat(rng.normal(size=3)))
    rho0, v0, cx = np.array([0.2, 10.0, -0.3]), np.array([1e-3, -2e-3, 5e-4]), [-0.25, 0.25]
    ref = O.stencil_measurement_model(x, R_CI, rho0, v0, np.array(cx), 1.0)
    out = O.stencil_measurement_model_compiled(x, R_CI, rho0, v0, np.array(cx), 1.0)
    assert out.shape == ref.shape == (2, 49, 5, 9)
    scale = np.abs(ref).max(axis=(0, 1, 2))  # per component: projections, flows
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-13 * scale.max())
    np.testing.assert_allclose(out[..., 5:], ref[..., 5:], rtol=0, atol=1e-12 * scale[5:].max())


@given(quat, arrays(np.float64, 14, elements=st.floats(-1.0, 1.0)), vec3)
def test_state_boxplus_matches_the_layout(q, v, dth):
    lay = U.layout(3)
    x = np.concatenate([v[:3], q, v[3:]])
    dx = np.concatenate([v[:3] * 0.1, dth, v[3:] * 0.2])
    np.testing.assert_allclose(U._boxplus(x, dx), lay.boxplus(x, dx), atol=1e-14)


@given(quat)
def test_quaternion_covariance_map_is_the_jacobian_of_boxminus(q):
    J = numerical_jacobian(lambda s: rot.boxminus(s / np.linalg.norm(s), q), q)
    np.testing.assert_allclose(U.quat_cov_map(q), J, atol=1e-8)


def test_measurement_model_at_the_truth_reproduces_noise_free_measurements():
    s = kabir(duration=30.0, **{"flow_edges": "paper"}).with_updates(
        **{"sensor.noise.angular_rad": 0.0}
    )
    truth, meas = simulate(s, 3)
    tun = U.parse_tuning({**s.estimator.tuning, "sigma_p_rad": 1e-5})
    z, R = U.stereo_measurements(meas, tun)
    g = U.geometry(s, meas.t, meas)
    h = U.measurement_model(
        alignment.kabir_truth_state_of(truth), g.R_CI, g.rho0_C, g.rho0_dot_C, g.centres_x
    )
    np.testing.assert_allclose(z[..., :5], h[..., :5], atol=1e-12)
    # flow by Kabir 2025 eq. 27 at 1 Hz: ~1e-4 rad/s truncation inside (0.075 Hz tumbling)
    np.testing.assert_allclose(z[2:-2, :, 5:], h[2:-2, :, 5:], atol=2e-3)
    np.testing.assert_allclose(R[0, 0], [1e-10] * 5 + [5e-4**2] * 4)


def test_truth_state_uses_k2_log_I3_over_I2():
    truth, _ = simulate(kabir(duration=5.0), 1)
    x = alignment.kabir_truth_state_of(truth)
    np.testing.assert_allclose(x[0, 7:9], [np.log(90 / 100), np.log(112 / 100)])
    assert x.shape == (len(truth.t), 9 + 15)


# --- tuning and input errors ---------------------------------------------------------------


def test_paper_tuning_per_frequency_and_bad_input():
    # Kabir 2025 Sec. 3.2
    assert U.paper_tuning(0.175) == {
        "q_omega_var": 2.5e-5,
        "q_quat_var": 4e-6,
        "sigma_flow_rad_s": 1e-3,
        # the paper's Q of k and features and its observation model, now explicit (issue 18:
        # the defaults follow the scenario)
        "q_k_var": 3.6e-5,
        "q_feature_var": 1e-6,
        "flow_model": "instantaneous",
        "use_disparity": True,
        "update_chart": "body",  # the paper's filter updates in its own chart
        "relabel_axes": False,  # ... and keeps the start's labelling of the principal axes
    }
    assert K.tumbling_frequency_hz(kabir(0.125)) == pytest.approx(0.125)
    with pytest.raises(InputError, match="0.1 Hz"):
        U.paper_tuning(0.1)
    with pytest.raises(InputError, match="estimator.tuning.alpah: unknown key"):
        U.parse_tuning({"alpah": 0.1})
    with pytest.raises(InputError, match="estimator.tuning.p0_k_var"):
        U.parse_tuning({"p0_k_var": -1.0})
    with pytest.raises(InputError, match="inertially fixed chaser"):
        U.geometry(load_scenario("hu2024"), np.zeros(2))


def test_projection_noise_defaults_are_named_rules():
    """The tuning shows the rules it applies ('sensor', 'sigma_p'); null (the former default)
    means the rule too; a number overrides it."""
    tun = U.KabirTuning()
    assert (tun.sigma_p_rad, tun.sigma_d_rad) == ("sensor", "sigma_p")
    assert U.parse_tuning({"sigma_p_rad": None, "sigma_d_rad": None}) == tun
    meas = dataclasses.make_dataclass("M", ["noise_px", "rig"])(
        0.5, dataclasses.make_dataclass("Rig", ["left"])(
            dataclasses.make_dataclass("Cam", ["focal_px"])(1000.0)
        )
    )  # fmt: skip
    assert U.projection_sigmas(tun, meas) == (5e-4, 5e-4)
    assert U.projection_sigmas(U.parse_tuning({"sigma_d_rad": 2e-4}), meas) == (5e-4, 2e-4)
    assert U.projection_sigmas(U.parse_tuning({"sigma_p_rad": 1e-5}), meas) == (1e-5, 1e-5)
    for bad in (0.0, -1e-5, "senor", True):
        with pytest.raises(InputError, match="estimator.tuning.sigma_p_rad: .*'sensor'"):
            U.parse_tuning({"sigma_p_rad": bad})
    with pytest.raises(InputError, match="sigma_p_rad"):
        U.projection_sigmas(tun, dataclasses.replace(meas, noise_px=0.0))


def test_registered_with_needs_and_description():
    for name in ("ukf", "ukf-mult"):
        est = base.get(name)
        assert est.name == name and "stereo" in est.needs and "Kabir 2025" in est.description
    assert {"ukf", "ukf-mult"} <= set(base.available())


# --- runs on the kabir2025 scenario ---------------------------------------------------------


@pytest.fixture(scope="module")
def near_run():
    s = kabir(**NEAR)
    truth, meas = simulate(s, run_seed(4, 0))
    out = {}
    for variant in ("additive", "mult"):
        est = U.KabirUKF(variant)
        h = est.run(s, meas, np.random.default_rng(0))
        out[variant] = (h, metrics.run_errors(h, alignment.truth_state(truth, h)))
    return s, truth, meas, out


@pytest.mark.parametrize("variant", ["additive", "mult"])
def test_converges_and_is_consistent_from_a_near_start(near_run, variant):
    # kabir2025 at f_T = 0.075 Hz, no occlusion, paper tuning, 10 % of the paper's initial
    # errors: 400 s (2.7 polhode periods). Observed: 0.3-0.4 deg, 0.17-0.2 deg/s, NEES/dof 0.8.
    s, _, _, out = near_run
    h, r = out[variant]
    e = {k: v[-1] for k, v in r.errors.items()}
    assert e["attitude_deg"] < 1.0
    assert e["rate_deg_s"] < 0.5
    assert e["inertia"] < 0.03
    assert e["features_m"] < 0.03
    nees = metrics.consistency(r.nees[None], r.nees_dof, r.t, s.window_s)
    assert 0.4 < nees["mean"] < 2.5
    assert h.skipped["no_measurement_epochs"] == 0 and h.skipped["diverged"] == 0
    # flows are dropped where eq. 27 is below 4th order: 2 epochs at each end
    np.testing.assert_array_equal(h.nis_dof[[0, 1, -2, -1]], 25)
    assert np.all(h.nis_dof[2:-2] == 45)


def test_variants_agree(near_run):
    _, _, _, out = near_run
    qa, qm = out["additive"][0].block("attitude"), out["mult"][0].block("attitude")
    assert np.degrees(metrics.attitude_error_rad(qa[-1], qm[-1])) < 0.3


def test_ukf_converges_from_the_papers_initial_guess():
    # Kabir 2025 Sec. 3.2's guess (omega x 1.75, 27.8 deg, k = 0, features + 0.7 m), f_T =
    # 0.075 Hz: the filter soon claims sub-degree attitude while 28 deg off (the frame is fixed
    # by the dynamics only, through strongly nonlinear terms) and converges over a few polhode
    # periods (147 s); observed 0.60-0.67 deg and 0.24-0.33 deg/s at 1000 s on four seeds.
    s = kabir(duration=1000.0)
    truth, meas = simulate(s, run_seed(0, 0))
    est = U.KabirUKF("additive")
    h = est.run(s, meas, np.random.default_rng(0))
    r = metrics.run_errors(h, alignment.truth_state(truth, h))
    assert r.errors["attitude_deg"][0] > 20.0
    assert r.errors["attitude_deg"][-1] < 1.0
    assert r.errors["rate_deg_s"][-1] < 0.5
    assert r.errors["features_m"][-1] < 0.03


def test_occlusion_predicts_only_and_counts_skips():
    # the filter's own covariance (covariance_report: filter); the reported one below
    s = kabir(duration=300.0, occlusion=200.0, covariance_report="filter", **NEAR)
    truth, meas = simulate(s, run_seed(4, 0))
    s_a = s.with_updates(
        **{"estimator.tuning": {**s.estimator.tuning, "covariance_report": "actual"}}
    )
    for variant in ("additive", "mult"):
        h = U.KabirUKF(variant).run(s, meas, np.random.default_rng(0))
        occluded = h.t >= 200.0
        assert h.skipped["no_measurement_epochs"] == occluded.sum() == 101  # 200..300 s
        assert h.skipped["unobserved_feature_epochs"] == 5 * 101
        assert np.all(h.nis_dof[occluded] == 0) and np.isnan(h.nis[occluded]).all()
        # prediction only: the rotational block's volume grows (a torque-free rigid body's
        # flow keeps volume, Q adds to it; its trace may dip as the spread turns with the
        # polhode), and nothing updates the rigid parameters, so no process noise on them
        o = 7 if variant == "additive" else 6
        logdet = np.linalg.slogdet(h.P[occluded][:, :o, :o])[1]
        assert np.all(np.diff(logdet) > 0)
        rigid = h.P[occluded][:, o:, o:]
        np.testing.assert_allclose(rigid, np.broadcast_to(rigid[0], rigid.shape), atol=1e-15)
        # k and features stay (to the round-off of the weighted sigma-point mean)
        np.testing.assert_allclose(h.x[occluded, 7:], np.tile(h.x[200, 7:], (101, 1)), atol=1e-12)
        # reported at the actual error's covariance: the same estimate, and the rigid
        # parameters' covariance stays through the coast (kabir2025.mismatch.report_actual)
        a = U.KabirUKF(variant).run(s_a, meas, np.random.default_rng(0))
        np.testing.assert_array_equal(a.x, h.x)
        rigid_a = a.P[occluded][:, 6:, 6:]
        np.testing.assert_allclose(
            rigid_a, np.broadcast_to(rigid_a[0], rigid_a.shape), rtol=1e-9, atol=1e-15
        )
        assert np.all(np.linalg.eigvalsh(a.P[occluded]) > 0)


def test_run_ukf_takes_pseudo_measurements_with_their_own_variances(near_run):
    s, truth, meas, out = near_run
    tun = U.parse_tuning(s.estimator.tuning)
    z, R = U.stereo_measurements(meas, tun)
    g = U.geometry(s, meas.t, meas)
    h = U.run_ukf(s, meas.t, z, R, "additive", tun, g)
    np.testing.assert_array_equal(h.x, out["additive"][0].x)  # = the estimator's run
    # no v_L (the GP of Kabir 2025 Sec. 2.3 predicts [u_R, v_R, u_L] only), inflated variances
    z2 = z.copy()
    z2[..., 3] = np.nan
    h2 = U.run_ukf(s, meas.t, z2, 4.0 * R, "mult", tun, g)
    assert np.all(h2.nis_dof[2:-2] == 40)
    assert np.nanmean(h2.nis[100:] / h2.nis_dof[100:]) < np.nanmean(h.nis[100:] / h.nis_dof[100:])
    r2 = metrics.run_errors(h2, alignment.kabir_truth_state_of(truth))
    assert r2.errors["attitude_deg"][-1] < 1.0
    with pytest.raises(ValueError, match="shape"):
        U.run_ukf(s, meas.t, z[:, :, :8], R, "additive", tun, g)


def test_gate_rejects_an_outlier_and_counts_it(near_run):
    s, _, meas, _ = near_run
    s = s.with_updates(duration_s=120.0)
    meas = dataclasses.replace(
        meas,
        t=meas.t[:121],
        uv=meas.uv[:121].copy(),
        observed=meas.observed[:121],
        q_CL=meas.q_CL[:121],
        q_LI=meas.q_LI[:121],
    )
    meas.uv[60, 0, 2, 0] += 30.0  # 30 px on u of the left camera, feature 2
    plain = U.KabirUKF("additive").run(s, meas, None)
    assert plain.skipped["gated_out"] == 0
    gated_s = s.with_updates(
        **{"estimator.tuning": {**s.estimator.tuning, "gate_probability": 0.9999}}
    )
    gated = U.KabirUKF("additive").run(gated_s, meas, None)
    # the outlier spoils u_L and the disparity at epoch 60 and the flow at epochs 58-62
    assert 1 <= gated.skipped["gated_out"] <= 5
    assert gated.nis_dof[60] == 45 - 9
    assert gated.nis[60] < plain.nis[60]


def test_triangulated_start_needs_no_truth():
    s = kabir(duration=60.0, init="triangulated")
    truth, meas = simulate(s, run_seed(2, 0))
    tun = U.parse_tuning(s.estimator.tuning)
    z, _ = U.stereo_measurements(meas, tun)
    x0, P0 = U.initial_state(s, meas.t, z, U.geometry(s, meas.t, meas), tun, "mult")
    assert P0.shape == (23, 23)
    # kabir2025 starts at q0 = identity, the triangulated start's frame: compare directly
    xt = alignment.kabir_truth_state_of(truth)[0]
    # rate: 2nd-order one-sided flow at 1 Hz, ~(omega dt)^2 / 3 = 7 % at 0.47 rad/s
    np.testing.assert_allclose(x0[0:3], xt[0:3], rtol=0.1)
    np.testing.assert_allclose(x0[9:], xt[9:], atol=0.02)  # m, 1e-5 rad at 10 m depth


def test_run_batch_equals_single_runs():
    s = kabir(duration=100.0, **NEAR)
    sims = [simulate(s, run_seed(9, k)) for k in range(2)]
    est = U.KabirUKF("mult")
    res = est.run_batch(s, [m for _, m in sims], [None, None])
    for (truth, meas), hb in zip(sims, res, strict=True):
        h = est.run(s, meas, None)
        single = metrics.run_errors(h, alignment.truth_state(truth, h))
        r = metrics.run_errors(hb, alignment.truth_state(truth, hb))
        for k, v in single.errors.items():
            np.testing.assert_allclose(r.errors[k], v, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r.nees, single.nees, rtol=1e-6)
        assert hb.skipped == h.skipped


@pytest.mark.parametrize("estimator", ["ukf", "ukf-mult", "ukf-gp"])
@pytest.mark.parametrize(
    ("scenario", "message"),
    [("yu2019", "needs a stereo rig"), ("chang2021", "inertially fixed chaser")],
)
def test_scenarios_the_method_does_not_cover_are_refused_first(estimator, scenario, message):
    # Kabir 2025 Sec. 2.1 (parallel stereo rig, chaser without orbit): the reason comes before
    # any tuning key of the other paper's scenario is read
    sc = load_scenario(scenario)
    with pytest.raises(InputError, match=message):
        base.get(estimator).run(sc, None, np.random.default_rng(0))


@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), variant=st.sampled_from(["ukf", "ukf-mult"]))
def test_batched_engine_equals_the_reference_fold_on_runs_drawn_at_random(seed, variant):
    """The batched engine (run_batch, campaigns) and the reference fold of UKFSteps (run)
    give the same states, covariances, NIS and skip counts on runs drawn at random."""
    s = kabir(duration=150.0, **NEAR)
    sims = [simulate(s, run_seed(seed, k)) for k in range(2)]
    est = base.get(variant)
    batch = est.run_batch(s, [m for _, m in sims], [None, None])
    for (_, meas), hb in zip(sims, batch, strict=True):
        h = est.run(s, meas, None)
        for a, b in ((h.x, hb.x), (h.P, hb.P), (h.nis, hb.nis)):
            assert np.array_equal(np.isfinite(a), np.isfinite(b))
            fin = np.isfinite(a)
            np.testing.assert_allclose(a[fin], b[fin], rtol=1e-8, atol=1e-12)
        assert h.skipped == hb.skipped


def test_the_papers_filter_keeps_its_start_labelling_at_0025_hz():
    """Regression (eleventh session): from the paper's start (k = 0, the rate 1.75x) at
    0.025 Hz the moments' estimates cross while k is learnt; tumblenav's relabelling to
    ascending moments then hopped run 16 of `reproduce kabir2025`'s Benchmark between
    symmetric frames (attitude in the window 156 deg in its branch, the table's RMSE 13.7 ->
    59.6 deg). The paper's tuning keeps the start's labelling: the run stays nominal, as before
    issue 18 (26 deg in the window; 45.8 deg the worst of the 20 runs)."""
    sc = K.scenario_for(0.025).with_updates(**{"occlusion.loss_from_s": None})
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, 16))
    h = U.KabirUKF("additive").run(sc, meas, np.random.default_rng(0))
    a = alignment.align(truth, h)
    assert a.branch == metrics.NOMINAL
    err = metrics.run_errors(h, a.x).errors["attitude_deg"]
    assert np.sqrt(np.nanmean(err[h.t >= 1500.0] ** 2)) < 45.0
    relabelled = sc.with_updates(
        **{"estimator.tuning": {**sc.estimator.tuning, "relabel_axes": True}}
    )
    h2 = U.KabirUKF("additive").run(relabelled, meas, np.random.default_rng(0))
    assert alignment.align(truth, h2).branch != metrics.NOMINAL  # why the paper's is kept
