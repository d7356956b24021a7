"""Front-ends of Hu 2024 Sec. 2.1 / 3: triangulation, frame G, rates, inertia, DPACF."""

import itertools
import warnings
from functools import lru_cache

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import stats
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from tumblenav import rotations as rot
from tumblenav.frontends import (
    InertiaAccumulator,
    InertiaIdentification,
    accumulate,
    best_triplet,
    features_in_G,
    g_frame_from_points,
    identify_inertia,
    inertia_design,
    inertia_ratios,
    principal_frame,
    principal_moments,
    rate_from_attitudes,
    recover_G,
    solve,
    triangulate_parallel,
    triangulate_two_ray,
    triangulation_covariance,
    triplet_score,
)

# The setting the Hu 2024 tests below were written on (a scenario update): the paper's
# process noise on a torque-free truth, the inertia least squares torque-free, as the built-in
# hu2024 had before its truth got its disturbances (issue 18). They check behaviours and
# numbers measured there; the engine comparisons run on the built-in as shipped.
HU2024_PAPER = {
    "process_noise.rotational_rad2_s4": 2.5e-5,
    "process_noise.translational_m2_s4": 2e-6,
    "process_noise.disturb_truth": False,
    "estimator.tuning": {},
}


F_PX = 1000.0
B_M = 0.5
PP = np.array([640.0, 480.0])


def project(p_inCk, f=F_PX, pp=PP):
    """Pinhole projection with the optical axis on y: u = cu + f x/y, v = cv + f z/y."""
    p = np.asarray(p_inCk, float)
    return np.stack([pp[0] + f * p[..., 0] / p[..., 1], pp[1] + f * p[..., 2] / p[..., 1]], -1)


def stereo_pixels(p_inC, f=F_PX, b=B_M, pp=PP):
    return project(p_inC, f, pp), project(p_inC - np.array([b, 0.0, 0.0]), f, pp)


def angle_between(R1, R2):
    return float(np.linalg.norm(rot.log_map(R1 @ np.swapaxes(R2, -1, -2))))


def random_rotation(seed):
    return Rotation.random(random_state=seed).as_matrix()


# --------------------------------------------------------------------------- triangulation


def test_parallel_triangulation_inverts_projection_vectorised():
    rng = np.random.default_rng(1)
    p = np.stack(
        [rng.uniform(-2, 2, (4, 5)), rng.uniform(3, 40, (4, 5)), rng.uniform(-2, 2, (4, 5))], -1
    )
    uv_l, uv_r = stereo_pixels(p)
    out = triangulate_parallel(uv_l, uv_r, F_PX, B_M, PP)
    assert out.shape == (4, 5, 3)
    assert np.allclose(out, p, rtol=1e-12, atol=1e-12)


def test_parallel_triangulation_invalid_gives_nan_without_warnings():
    uv_l = np.array([[700.0, 500.0], [700.0, 500.0], [700.0, 500.0], [np.nan, 500.0]])
    uv_r = np.array([[700.0, 500.0], [710.0, 500.0], [650.0, np.nan], [650.0, 500.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = triangulate_parallel(uv_l, uv_r, F_PX, B_M, PP)
    # zero disparity, negative disparity -> NaN; v_r unused -> finite; NaN u_l -> NaN
    assert np.all(np.isnan(out[[0, 1, 3]]))
    assert np.all(np.isfinite(out[2]))
    assert not np.any(np.isinf(out))


def test_two_ray_equals_parallel_formula_on_parallel_rig():
    rng = np.random.default_rng(2)
    p = np.stack([rng.uniform(-2, 2, 50), rng.uniform(3, 30, 50), rng.uniform(-2, 2, 50)], -1)
    uv_l, uv_r = stereo_pixels(p)
    uv_l = uv_l + rng.normal(0, 0.5, uv_l.shape)  # noisy u; v_r := v_l keeps rays coplanar
    uv_r = uv_r + rng.normal(0, 0.5, uv_r.shape)
    uv_r[:, 1] = uv_l[:, 1]
    eye = np.eye(3)
    two = triangulate_two_ray(uv_l, uv_r, F_PX, PP, eye, np.zeros(3), eye, [B_M, 0, 0])
    par = triangulate_parallel(uv_l, uv_r, F_PX, B_M, PP)
    assert np.allclose(two, par, rtol=1e-10, atol=1e-10)


def test_two_ray_toed_in_rig_exact_geometry_and_failures():
    rng = np.random.default_rng(3)
    toe = np.deg2rad(4.0)
    # Camera frames: left yawed towards +x, right towards -x (about the rig z axis),
    # plus small arbitrary misalignments; R_CkC maps rig into camera coordinates.
    R_ClC = rot.exp_map([0.01, -0.02, -toe]).T
    R_CrC = rot.exp_map([-0.015, 0.01, toe]).T
    p_l, p_r = np.array([0.0, 0.0, 0.0]), np.array([0.8, 0.02, -0.01])
    f = (1000.0, 1100.0)
    pp = ((640.0, 480.0), (650.0, 470.0))
    p = np.stack([rng.uniform(-1, 2, 40), rng.uniform(4, 25, 40), rng.uniform(-1, 1, 40)], -1)
    uv_l = project((p - p_l) @ R_ClC.T, f[0], np.array(pp[0]))
    uv_r = project((p - p_r) @ R_CrC.T, f[1], np.array(pp[1]))
    out = triangulate_two_ray(uv_l, uv_r, f, pp, R_ClC, p_l, R_CrC, p_r)
    assert np.allclose(out, p, rtol=1e-10, atol=1e-10)

    # Point behind both cameras: its projections exist but the rays meet behind -> NaN.
    behind = np.array([0.3, -6.0, 0.2])
    ub_l = project((behind - p_l) @ R_ClC.T, f[0], np.array(pp[0]))
    ub_r = project((behind - p_r) @ R_CrC.T, f[1], np.array(pp[1]))
    # Parallel rays (parallel rig, zero disparity) -> NaN; NaN input -> NaN.
    eye = np.eye(3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        nb = triangulate_two_ray(ub_l, ub_r, f, pp, R_ClC, p_l, R_CrC, p_r)
        npar = triangulate_two_ray(
            [700, 500], [700, 500], F_PX, PP, eye, [0, 0, 0], eye, [B_M, 0, 0]
        )
        nnan = triangulate_two_ray(
            [np.nan, 500], [690, 500], F_PX, PP, eye, [0, 0, 0], eye, [B_M, 0, 0]
        )
    assert np.all(np.isnan(nb)) and np.all(np.isnan(npar)) and np.all(np.isnan(nnan))


def test_triangulation_inverts_the_sensor_model_of_tumblenav_sensors_stereo():
    """Same conventions as tumblenav.sensors.stereo (R_CkC, p_CkinC, u = cu + f x/y)."""
    stereo = pytest.importorskip("tumblenav.sensors.stereo")
    rng = np.random.default_rng(12)
    p = np.stack([rng.uniform(-1, 1, 30), rng.uniform(8, 30, 30), rng.uniform(-1, 1, 30)], -1)
    rig = stereo.chang2021_rig()  # convergent, 10 deg toe-in
    uv, _ = stereo.project(rig, p)
    L, R = rig.cameras
    out = triangulate_two_ray(
        uv[0], uv[1], (L.focal_px, R.focal_px), (L.principal_point_px, R.principal_point_px),
        L.R_CkC, L.p_CkinC, R.R_CkC, R.p_CkinC,
    )  # fmt: skip
    assert np.allclose(out, p, rtol=1e-10, atol=1e-10)
    prig = stereo.parallel_rig(1000.0, 0.5, (1280, 960))
    uv, _ = stereo.project(prig, p)
    pp = prig.left.principal_point_px
    assert np.allclose(triangulate_parallel(uv[0], uv[1], 1000.0, 0.5, pp), p, rtol=1e-12)


def test_triangulation_covariance_matches_monte_carlo():
    rng = np.random.default_rng(4)
    p = np.array([0.8, 10.0, -0.5])
    sigma = 0.3
    uv_l, uv_r = stereo_pixels(p)
    n = 40000
    noisy_l = uv_l + rng.normal(0, sigma, (n, 2))
    noisy_r = uv_r + rng.normal(0, sigma, (n, 2))
    samples = triangulate_parallel(noisy_l, noisy_r, F_PX, B_M, PP)
    mc = np.cov(samples.T)
    pred = triangulation_covariance(p, sigma, F_PX, B_M)
    assert pred.shape == (3, 3)
    # depth std sqrt(2) y^2 sigma / (f b)
    assert np.isclose(np.sqrt(pred[1, 1]), np.sqrt(2) * 100 * sigma / (F_PX * B_M))
    sd = np.sqrt(np.diag(pred))
    assert np.allclose(np.sqrt(np.diag(mc)), sd, rtol=0.03)
    corr_mc = mc / np.outer(np.sqrt(np.diag(mc)), np.sqrt(np.diag(mc)))
    corr_pred = pred / np.outer(sd, sd)
    assert np.allclose(corr_mc, corr_pred, atol=0.03)
    # vectorised: (2, 3) points and per-point sigma -> (2, 3, 3)
    assert triangulation_covariance(np.stack([p, 2 * p]), [0.3, 0.5], F_PX, B_M).shape == (2, 3, 3)


# ----------------------------------------------------------------------- photogrammetric


def test_g_frame_definition_and_rigid_invariance():
    rng = np.random.default_rng(5)
    p_B = rng.normal(size=(3, 3))  # three features in some body frame
    R_CB = np.stack([random_rotation(s) for s in range(6)])  # (6, 3, 3) over time
    o = rng.normal(size=(6, 3)) + [0, 10, 0]
    m = np.einsum("tij,kj->tki", R_CB, p_B) + o[:, None, :]
    R_GC = g_frame_from_points(m[:, 0], m[:, 1], m[:, 2])
    assert R_GC.shape == (6, 3, 3)
    assert np.allclose(R_GC @ np.swapaxes(R_GC, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R_GC), 1.0)
    p_G = features_in_G(m, R_GC, m[:, 0])
    # m1 at the origin, m2 on +x_G, m3 in the x-y plane with y > 0 (Hu 2024 eq. 6-7)
    assert np.allclose(p_G[:, 0], 0, atol=1e-12)
    assert np.allclose(p_G[:, 1, 1:], 0, atol=1e-12) and np.all(p_G[:, 1, 0] > 0)
    assert np.allclose(p_G[:, 2, 2], 0, atol=1e-12) and np.all(p_G[:, 2, 1] > 0)
    # G is target-fixed: R_GB = R_GC R_CB constant, G coordinates constant.
    assert np.allclose(R_GC @ R_CB, (R_GC @ R_CB)[0], atol=1e-12)
    assert np.allclose(p_G, p_G[0], atol=1e-12)
    # collinear -> NaN
    bad = g_frame_from_points([0, 0, 0], [1, 1, 1], [2, 2, 2])
    assert np.all(np.isnan(bad))


def test_best_triplet_prefers_wide_well_conditioned_triangle_and_respects_visibility():
    pts = np.array(
        [
            [0.0, 10.0, 0.0],
            [5.0, 10.0, 0.0],
            [10.0, 10.0, 0.05],  # nearly collinear with 0, 1
            [5.0, 10.0, 3.0],
            [np.nan, np.nan, np.nan],
        ]
    )
    # scores (smallest altitude): (0,2,3) 2.97 m > (0,1,3) 2.57 m ~ (1,2,3) > (0,1,2) ~0
    assert best_triplet(pts) == (0, 2, 3)  # m1 m2 = longest side
    assert best_triplet(pts, np.array([True, True, False, True, True])) == (0, 3, 1)
    with pytest.raises(ValueError):  # only two usable
        best_triplet(pts, np.array([True, False, False, True, True]))
    with pytest.raises(ValueError):
        best_triplet(np.array([[0, 5, 0], [1, 5, 0], [2, 5, 0.0]]))
    # random clouds: the winner maximises the score over all triplets (also with the
    # candidate pre-selection above max_candidates)
    rng = np.random.default_rng(11)
    cloud = rng.normal(size=(12, 3)) + [0, 10, 0]
    combos = list(itertools.combinations(range(12), 3))
    scores = [triplet_score(*cloud[list(c)]) for c in combos]
    assert set(best_triplet(cloud)) == set(combos[int(np.argmax(scores))])
    big = rng.normal(size=(200, 3))
    i, j, k = best_triplet(big)  # searches the 40 outermost points only
    assert triplet_score(big[i], big[j], big[k]) > 4.0  # global max 4.51, median 1.03


def test_recover_G_after_reselection_equals_original():
    rng = np.random.default_rng(6)
    p_B = rng.uniform(-1.5, 1.5, (8, 3))
    R0, R1 = random_rotation(10), random_rotation(11)
    o0, o1 = np.array([0.2, 12.0, -0.3]), np.array([-0.5, 9.0, 0.4])
    p0 = p_B @ R0.T + o0
    p1 = p_B @ R1.T + o1
    i, j, k = best_triplet(p0)
    R_GC0 = g_frame_from_points(p0[i], p0[j], p0[k])
    catalogue = features_in_G(p0, R_GC0, p0[i])
    # truth at epoch 1: the same three (now partly occluded) features define G
    R_GC1_true = g_frame_from_points(p1[i], p1[j], p1[k])
    visible = np.ones(8, bool)
    visible[[i, j]] = False  # two of the defining features are occluded
    new = best_triplet(p1, visible)
    assert not {i, j} & set(new)
    idx = np.flatnonzero(visible)
    R_GC1, origin1 = recover_G(p1[idx], catalogue, idx)
    assert np.allclose(R_GC1, R_GC1_true, atol=1e-12)
    assert np.allclose(origin1, p1[i], atol=1e-12)  # origin = occluded m1
    assert np.isclose(np.linalg.det(R_GC1), 1.0)
    # from exactly the 3 features of the new triplet only
    res3 = recover_G(p1[list(new)], catalogue[list(new)])
    assert angle_between(res3.R_GC, R_GC1_true) < 1e-12 and res3.n_features == 3
    # noisy features: small error, residual of the order of the noise
    noisy = recover_G(p1[idx] + rng.normal(0, 1e-3, (len(idx), 3)), catalogue, idx)
    assert angle_between(noisy.R_GC, R_GC1_true) < 3e-3
    assert 2e-4 < noisy.residual_rms_m < 2e-3
    with pytest.raises(ValueError):
        recover_G(p1[:2], catalogue[:2])


def constant_rate_attitudes(w_G, R0, t):
    """R_GI(t) = Exp(-w t) R0: constant rate w of G w.r.t. I, in G (dR/dt = -[w x] R)."""
    return rot.exp_map(-np.outer(t, w_G)) @ R0


@pytest.mark.parametrize("method, tol", [("geodesic", 1e-10), ("quaternion", 2e-4)])
def test_rate_constant_rotation_and_rotating_camera(method, tol):
    t = np.arange(0.0, 40.0, 0.1)
    w_G = np.array([0.12, -0.25, 0.3])  # 0.41 rad/s: > 2 pi in 40 s, quaternion sign flips
    R_GI = constant_rate_attitudes(w_G, random_rotation(20), t)
    est = rate_from_attitudes(R_GI, t, None, method=method)
    rel = np.max(np.linalg.norm(est - w_G, axis=1)) / np.linalg.norm(w_G)
    assert rel < tol
    # rotating camera: R_GC = R_GI R_IC, chaser rotation removed with R_CI
    R_CI = constant_rate_attitudes(np.array([0.0, 0.05, -0.02]), random_rotation(21), t)
    R_GC = R_GI @ np.swapaxes(R_CI, 1, 2)
    est_c = rate_from_attitudes(R_GC, t, R_CI, method=method)
    assert np.max(np.linalg.norm(est_c - w_G, axis=1)) / np.linalg.norm(w_G) < tol
    # ignoring the camera rotation would be wrong by ~the camera rate
    wrong = rate_from_attitudes(R_GC, t, None, method=method)
    assert np.max(np.linalg.norm(wrong - w_G, axis=1)) > 0.01


def test_quaternion_rate_formula_is_hamilton_form_of_hu_eq15():
    rng = np.random.default_rng(7)
    q = rot.quat_normalize(rng.normal(size=4))
    w = rng.normal(size=3)
    q_dot = rot.quat_derivative(q, w)
    qv, qw = q[:3], q[3]
    xi_h = np.vstack([rot.skew(qv) - qw * np.eye(3), qv])
    assert np.allclose(2.0 * xi_h.T @ q_dot, w, atol=1e-14)


# --------------------------------------------------------------------------- inertia

I_T = np.diag([8.0, 5.0, 4.0])


@lru_cache(maxsize=1)
def torque_free(t_end=20.0, dt=0.1, seed=30):
    """Torque-free tumbling of I_T, w0 = (0.1, 0.1, 0.1) rad/s: (t, omega_T, R_TI)."""
    q0 = rot.quat_normalize(Rotation.random(random_state=seed).as_quat())
    inv = np.linalg.inv(I_T)

    def rhs(_, y):
        w, q = y[:3], y[3:]
        return np.concatenate([-inv @ np.cross(w, I_T @ w), rot.quat_derivative(q, w)])

    t = np.arange(0.0, t_end + 1e-9, dt)
    sol = solve_ivp(rhs, (0, t_end), np.r_[0.1, 0.1, 0.1, q0], t_eval=t, rtol=1e-12, atol=1e-14)
    return t, sol.y[:3].T, rot.quat_to_matrix(sol.y[3:].T)


def tumbling_in_G(R_GT):
    t, w_T, R_TI = torque_free()
    I_G = R_GT @ I_T @ R_GT.T
    h_I = np.einsum("tji,tj->ti", R_TI, w_T @ I_T)  # R_IT I_T w_T
    assert np.allclose(h_I, h_I[0], atol=1e-10)  # conserved
    return t, w_T @ R_GT.T, R_GT @ R_TI, I_G, h_I[0]


def test_design_rows_encode_euler_momentum_equation():
    rng = np.random.default_rng(8)
    A = rng.normal(size=(3, 3))
    I = A @ A.T + 3 * np.eye(3)
    I_bar = I / I[0, 0]
    H = rng.normal(size=3)
    w = rng.normal(size=(5, 3))
    R = np.stack([random_rotation(s) for s in range(5)])
    a, b = inertia_design(w, R)
    X = np.r_[I_bar[1, 1], I_bar[2, 2], I_bar[0, 1], I_bar[0, 2], I_bar[1, 2], H]
    assert a.shape == (5, 3, 8) and b.shape == (5, 3)
    assert np.allclose(a @ X - b, w @ I_bar.T - R @ H, atol=1e-12)


def test_identify_inertia_exact_batch_and_online():
    R_GT = random_rotation(31)
    t, w_G, R_GI, I_G, h_I = tumbling_in_G(R_GT)
    est = identify_inertia(w_G, R_GI)
    assert np.max(np.abs(est.I_bar_G - I_G / I_G[0, 0])) < 1e-6
    assert np.max(np.abs(est.H_I - h_I / I_G[0, 0])) < 1e-6
    assert est.residual_rms < 1e-8 and np.isfinite(est.condition_number)
    assert est.is_physical and est.I_bar_G[0, 0] == 1.0
    # online: frame by frame normal equations give the batch result
    ident = InertiaIdentification()
    conds = []
    for k in range(len(t)):
        ident.update(w_G[k], R_GI[k])
        if k in (0, 10, 50, 200):
            conds.append(ident.estimate().condition_number)
    online = ident.estimate()
    assert np.isinf(conds[0])  # one epoch: 3 equations, 8 unknowns
    assert conds[1] > conds[2] > conds[3]  # becomes better conditioned as the rate moves
    assert np.allclose(online.I_bar_G, est.I_bar_G, atol=1e-9)
    assert np.allclose(online.H_I, est.H_I, atol=1e-9)
    assert np.isclose(online.condition_number, est.condition_number, rtol=1e-6)
    # functional form, accumulating in two batches
    st_ = accumulate(accumulate(None, w_G[:100], R_GI[:100]), w_G[100:], R_GI[100:])
    assert np.allclose(solve(st_).I_bar_G, est.I_bar_G, atol=1e-9)
    assert isinstance(st_, InertiaAccumulator) and st_.n_epochs == len(t)
    # DPACF on identified vs true inertia: same frame; it is one of the 24 candidates of R_GT
    R_hat = principal_frame(est.I_bar_G)
    R_true = principal_frame(I_G)
    assert angle_between(R_hat, R_true) < 1e-6
    S = R_GT.T @ R_true
    assert np.allclose(np.abs(S), np.eye(3), atol=1e-9)  # diag(8,5,4) is already ordered
    assert np.allclose(principal_moments(est.I_bar_G), [1.0, 5 / 8, 4 / 8], atol=1e-6)
    assert np.allclose(
        inertia_ratios(principal_moments(est.I_bar_G)),
        [(5 - 4) / 8, (4 - 8) / 5, (8 - 5) / 4],
        atol=1e-6,
    )


def test_identify_inertia_degrades_gracefully_with_rate_noise():
    R_GT = random_rotation(32)
    _, w_G, R_GI, I_G, h_I = tumbling_in_G(R_GT)
    truth = I_G / I_G[0, 0]
    rng = np.random.default_rng(9)
    errs, angs = [], []
    for sigma in (1e-5, 1e-4, 1e-3):
        est = identify_inertia(w_G + rng.normal(0, sigma, w_G.shape), R_GI)
        errs.append(np.max(np.abs(est.I_bar_G - truth)))
        angs.append(angle_between(principal_frame(est.I_bar_G), principal_frame(I_G)))
        assert 0.3 * sigma < est.residual_rms < 3 * sigma
    assert errs[0] < 1e-3 and errs[1] < 1e-2 and errs[2] < 0.1
    assert errs[0] < errs[1] < errs[2]
    assert angs[0] < 1e-3 and angs[2] < 0.1


def test_not_identifiable_reports_infinite_condition():
    # pure spin about a principal axis: the rate never moves in G
    R = np.stack([rot.exp_map([0.0, 0.0, -0.2 * k]) for k in range(50)])
    w = np.tile([0.0, 0.0, 0.2], (50, 1))
    est = identify_inertia(w, R)
    assert not np.isfinite(est.condition_number) and np.all(np.isnan(est.I_bar_G))
    assert np.isinf(identify_inertia(w[:2], R[:2]).condition_number)


def test_pipeline_pixels_to_principal_frame_with_occlusion_and_rotating_chaser():
    """pixels -> eq. 1 -> G (eq. 6-7, kept through occlusion) -> rate (eq. 15) -> LS -> DPACF."""
    t, w_T, R_TI = torque_free()
    rng = np.random.default_rng(10)
    p_T = rng.uniform(-1.0, 1.0, (6, 3))  # features in the principal frame
    R_CI = constant_rate_attitudes(np.array([0.01, -0.02, 0.005]), random_rotation(40), t)
    R_CT = R_CI @ np.swapaxes(R_TI, 1, 2)
    centre = np.array([0.3, 12.0, -0.2]) + np.outer(t, [0.01, -0.05, 0.0])
    p_inC = np.einsum("tij,kj->tki", R_CT, p_T) + centre[:, None, :]
    uv_l, uv_r = stereo_pixels(p_inC)
    m = triangulate_parallel(uv_l, uv_r, F_PX, B_M, PP)
    i, j, k = best_triplet(m[0])
    R_GC0 = g_frame_from_points(m[0, i], m[0, j], m[0, k])
    catalogue = features_in_G(m[0], R_GC0, m[0, i])
    R_GC = np.empty((len(t), 3, 3))
    for n in range(len(t)):
        vis = np.ones(6, bool)
        if 50 <= n < 120:
            vis[[i, k]] = False  # two defining features occluded for 7 s
        idx = np.flatnonzero(vis)
        R_GC[n] = recover_G(m[n, idx], catalogue, idx).R_GC
    R_GT_true = R_GC0 @ R_CT[0]
    w_G = rate_from_attitudes(R_GC, t, R_CI)
    w_G_true = w_T @ R_GT_true.T
    assert np.max(np.abs(w_G - w_G_true)) < 1e-5
    est = identify_inertia(w_G, R_GC @ R_CI)
    I_G = R_GT_true @ I_T @ R_GT_true.T
    assert np.max(np.abs(est.I_bar_G - I_G / I_G[0, 0])) < 2e-4  # measured 4.8e-5
    assert angle_between(principal_frame(est.I_bar_G), principal_frame(I_G)) < 2e-4


# ------------------------------------------------------------------ DPACF properties

SIGNED_PERMS = [
    P
    for perm in itertools.permutations(range(3))
    for signs in itertools.product((1.0, -1.0), repeat=3)
    if np.isclose(np.linalg.det(P := np.eye(3)[:, list(perm)] * np.array(signs)), 1.0)
]

quat4 = arrays(np.float64, 4, elements=st.floats(-1.0, 1.0)).filter(
    lambda q: np.linalg.norm(q) > 0.1
)
moments = st.tuples(st.floats(1.0, 10.0), st.floats(0.1, 0.8), st.floats(0.1, 0.8)).map(
    lambda m: np.array([m[0] * (1 + m[1]) * (1 + m[2]), m[0] * (1 + m[1]), m[0]])
)


def _dpacf_reference(R_GT0):
    """Expected DPACF frame of R_GT0 diag(l1 > l2 > l3) R_GT0^T, computed independently.

    r1: first component (x, then y, z for the degenerate r1_x = 0) positive; r2: largest
    magnitude component positive; r3 = r1 x r2.
    """
    r1, r2 = R_GT0[:, 0].copy(), R_GT0[:, 1].copy()
    r1 *= np.sign(r1[np.flatnonzero(np.abs(r1) > 1e-6)[0]])
    r2 *= np.sign(r2[np.argmax(np.abs(r2))])
    return np.column_stack([r1, r2, np.cross(r1, r2)])


def _decisive(R_GT0, margin, allow_zero_r1=False):
    """The sign rules are at least ``margin`` away from their switching sets.

    r1_x clearly non-zero (or, with ``allow_zero_r1``, every r1 component either clearly
    non-zero or zero to round-off: axis-aligned draws, which exercise the documented
    fallback); r2's two largest magnitudes not tied.
    """
    r1, r2 = np.abs(R_GT0[:, 0]), R_GT0[:, 1]
    if allow_zero_r1:
        r1_ok = np.all((r1 > margin) | (r1 < 1e-13))
    else:
        r1_ok = r1[0] > margin
    top2 = np.sort(np.abs(r2))[-2:]
    return bool(r1_ok and top2[1] - top2[0] > margin)


def test_signed_permutations_are_the_24_proper_candidates():
    assert len(SIGNED_PERMS) == 24
    assert len({tuple(P.ravel()) for P in SIGNED_PERMS}) == 24


@given(moments, quat4)
def test_principal_frame_is_unique_among_24_candidates(lam, q):
    assume(lam[0] < lam[1] + lam[2])  # triangle inequality of a rigid body
    R_GT0 = rot.quat_to_matrix(q)
    assume(_decisive(R_GT0, 1e-6, allow_zero_r1=True))
    expected = _dpacf_reference(R_GT0)
    for P in SIGNED_PERMS:
        R = R_GT0 @ P
        I_T_cand = P.T @ np.diag(lam) @ P
        out = principal_frame(R @ I_T_cand @ R.T)
        assert np.allclose(out, expected, atol=1e-9)
    I_G = R_GT0 @ np.diag(lam) @ R_GT0.T
    out = principal_frame(I_G)
    assert np.isclose(np.linalg.det(out), 1.0) and np.allclose(out.T @ out, np.eye(3))
    D = out.T @ I_G @ out
    assert np.allclose(D, np.diag(lam), atol=1e-9 * lam[0])  # x_T largest, z_T smallest
    assert out[np.flatnonzero(np.abs(out[:, 0]) > 1e-6)[0], 0] > 0
    assert out[np.argmax(np.abs(out[:, 1])), 1] > 0
    assert np.allclose(principal_frame(3.7e-2 * I_G), out, atol=1e-9)  # scale-free
    assert np.allclose(principal_moments(I_G), lam / lam[0])


@given(moments, quat4, arrays(np.float64, 6, elements=st.floats(-1.0, 1.0)))
def test_principal_frame_is_continuous_away_from_switching_sets(lam, q, d):
    assume(lam[0] < lam[1] + lam[2])
    R_GT0 = rot.quat_to_matrix(q)
    assume(_decisive(R_GT0, 0.05))
    I_G = R_GT0 @ np.diag(lam) @ R_GT0.T
    eps = 1e-6 * lam[0]
    dI = eps * np.array([[d[0], d[3], d[4]], [d[3], d[1], d[5]], [d[4], d[5], d[2]]])
    change = angle_between(principal_frame(I_G + dI), principal_frame(I_G))
    gap = min(lam[0] - lam[1], lam[1] - lam[2])
    assert change <= 10 * np.linalg.norm(dI) / gap + 1e-12


def test_principal_frame_degenerate_first_component_and_stacks():
    # Axis-aligned inertia: r1 = +-y_G exactly, the paper's rule (r1_x > 0) is undefined;
    # the fallback makes the first significant component positive -> deterministic.
    out = principal_frame(np.diag([4.0, 8.0, 5.0]))
    assert np.allclose(out, [[0, 0, 1], [1, 0, 0], [0, 1, 0]])
    stack = np.stack([np.diag([4.0, 8.0, 5.0]), np.diag([8.0, 5.0, 4.0])])
    assert np.allclose(principal_frame(stack)[1], np.eye(3))
    with pytest.raises(ValueError):
        principal_frame(np.full((3, 3), np.nan))


def test_branch_probabilities_match_sampling_near_the_sign_rules():
    """``branch_probabilities`` (first order) against the frequency with which a frame error
    u ~ N(0, C) makes the true inertia's DPACF the half turn about x_T, y_T or z_T. Frames
    are drawn at random, with 1-sigma 0.5-3 deg, and kept when some probability is > 2%
    (i.e. near a rule's boundary); tolerance 0.03 absolute (sampling: 4000 draws). With
    more than 400 flips by one rule while the other rarely flips, also the mean and
    covariance of u given that flip (``branch_statistics``) against the sample's."""
    from tumblenav.frontends.inertia import branch_probabilities, branch_statistics

    rng = np.random.default_rng(11)
    lam = np.array([8.0, 5.0, 4.0])
    checked = 0
    while checked < 12:
        Rg = rot.quat_to_matrix(rng.normal(size=4))
        R = principal_frame(Rg @ np.diag(lam) @ Rg.T)
        A = rng.normal(size=(3, 3)) * np.radians(rng.uniform(0.5, 3.0))
        C = A @ A.T
        p = branch_probabilities(R, C)
        if p.max() < 0.02:
            continue
        u = rng.multivariate_normal(np.zeros(3), C, size=4000)
        Rt = R[None] @ rot.exp_map(-u)
        Rtrue = principal_frame(Rt @ np.diag(lam) @ np.swapaxes(Rt, -1, -2))
        s = np.sign(np.diagonal(np.swapaxes(R, -1, -2)[None] @ Rtrue, axis1=-2, axis2=-1))
        freq = [
            np.mean((s[:, 0] > 0) & (s[:, 1] < 0)),
            np.mean((s[:, 0] < 0) & (s[:, 1] > 0)),
            np.mean((s[:, 0] < 0) & (s[:, 1] < 0)),
        ]
        assert np.allclose(p, freq, atol=0.03), (p, freq)
        # given a single rule's flip, u is a truncated normal: its mean and covariance
        _, mu, S = branch_statistics(R, C)
        sig = np.sqrt(np.diag(C)).max()
        for a, mask in enumerate([(s[:, 0] > 0) & (s[:, 1] < 0), (s[:, 0] < 0) & (s[:, 1] > 0)]):
            if mask.sum() > 400 and p[1 - a] < 0.01 and p[2] < 0.005:  # one rule dominates
                np.testing.assert_allclose(mu[a], u[mask].mean(0), atol=0.12 * sig)
                np.testing.assert_allclose(S[a], np.cov(u[mask].T), atol=0.25 * sig**2)
        checked += 1
    # far from every boundary, and without a frame
    assert np.allclose(branch_probabilities(np.eye(3), 1e-6 * np.eye(3)), 0.0)
    # the joint flip of both rules: Owen's-T bivariate normal CDF against scipy's
    from scipy import stats

    from tumblenav.frontends.inertia import _bivariate_normal_cdf

    for h, k, r in rng.uniform([-2.5, -2.5, -0.95], [0.0, 0.0, 0.95], size=(8, 3)):
        ref = stats.multivariate_normal([0, 0], [[1, r], [r, 1]]).cdf([h, k])
        assert abs(_bivariate_normal_cdf(np.array(h), np.array(k), np.array(r)) - ref) < 1e-6
    assert np.all(branch_probabilities(np.full((3, 3), np.nan), np.eye(3)) == 0.0)


# ------------------------------------------- compiled loops of the stereo-points front end


def _hu_measurements(n_runs, seed, **updates):
    from tumblenav.campaign.store import run_seed
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate

    s = (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(duration_s=40.0, steady_state_window_s=[30.0, 40.0], **updates)
    )
    return [simulate(s, run_seed(seed, k))[1] for k in range(n_runs)]


@given(seed=st.integers(0, 2**32 - 1), noise=st.sampled_from([0.0, 1e-3, 0.1, 10.0]))
def test_kabsch_rotation_equals_the_svd_solution(seed, noise):
    """Horn's quaternion method (compiled) against the SVD with the reflection guard, for
    rigid point sets with noise up to pure noise (reflections included), and the collinear
    case (second singular value 0)."""
    from tumblenav.frontends import _points_kernel

    rng = np.random.default_rng(seed)
    g = rng.normal(size=(50, 6, 3))
    R_true = Rotation.random(50, random_state=rng.integers(2**31)).as_matrix()
    p = g @ np.swapaxes(R_true, -1, -2) + noise * rng.normal(size=g.shape)
    gc, pc = g - g.mean(1, keepdims=True), p - p.mean(1, keepdims=True)
    H = np.swapaxes(gc, -1, -2) @ pc
    R, ratio = _points_kernel.kabsch_rotation(H)
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.tile(np.eye(3), (50, 1, 1))
    D[:, 2, 2] = d
    np.testing.assert_allclose(R, np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2), atol=1e-9)
    np.testing.assert_allclose(ratio, S[:, 1] / S[:, 0], atol=1e-12)
    line = np.outer(np.arange(6.0), [1.0, 2.0, 0.5])[None]  # collinear points
    lc = line - line.mean(1, keepdims=True)
    assert _points_kernel.kabsch_rotation(np.swapaxes(lc, -1, -2) @ lc)[1][0] < 1e-9


def test_compiled_triangulation_equals_numpy():
    """Points, covariances (in C and L), masks and skip counts of the compiled parallel-rig
    loop equal :func:`stereo_points.triangulate` and its rotation into L, including features
    seen in one camera only and non-positive disparities."""
    from tumblenav.frontends import _points_kernel, stereo_points

    meas = _hu_measurements(2, 3)
    uv = np.stack([m.uv for m in meas]).astype(float)
    obs = np.stack([m.observed for m in meas])
    uv[0, 5, 1, 2, 0] = uv[0, 5, 0, 2, 0] + 1.0  # negative disparity
    uv[1, 7, 1, 0, 0] = uv[1, 7, 0, 0, 0]  # zero disparity
    obs[0, 9, 1, 3] = False  # left camera only
    uv[1, 11, 0, 4, 1] = np.nan  # NaN pixel
    for k, m in enumerate(meas):
        m.uv[...] = uv[k]
        m.observed[...] = obs[k]
    p_C, cov_C, usable, skipped = stereo_points.triangulate(meas)
    R_LC = np.ascontiguousarray(
        np.swapaxes(rot.quat_to_matrix(np.stack([m.q_CL for m in meas])), -1, -2)
    )
    rig = meas[0].rig
    out = _points_kernel.triangulate_parallel_rotated(
        uv, obs, rig.left.focal_px, rig.baseline_m, *rig.left.principal_point_px,
        meas[0].noise_px, R_LC,
    )  # fmt: skip
    pc, cc, pl, cl, uc, one_cam, bad = out
    assert np.array_equal(uc, usable) and (~usable).sum() >= 4
    assert np.array_equal(one_cam, skipped["one_camera_only"])
    assert np.array_equal(bad, skipped["bad_triangulation"]) and bad.sum() >= 3
    assert np.allclose(pc[usable], p_C[usable], rtol=1e-14, atol=0)
    assert np.allclose(cc[usable], cov_C[usable], rtol=1e-12, atol=0)
    assert np.allclose(pl[usable], (R_LC[:, :, None] @ p_C[..., None])[..., 0][usable], atol=1e-12)
    cov_L = R_LC[:, :, None] @ cov_C @ np.swapaxes(R_LC, -1, -2)[:, :, None]
    assert np.allclose(cl[usable], cov_L[usable], rtol=1e-10, atol=1e-20)
    assert np.all(np.isnan(pl[~usable]))


def _rates_reference(q, valid, h, dt):
    """The numpy version the compiled rate fit replaced (symmetric slope of log q(k+j) q(k)^*)."""
    B, n = valid.shape
    num = np.zeros((B, n, 3))
    good = valid.copy()
    for j in range(1, h + 1):
        for s in (+1, -1):
            shifted = np.roll(q, -s * j, axis=1)
            vshift = np.roll(valid, -s * j, axis=1)
            if s > 0:
                vshift[:, n - j :] = False
            else:
                vshift[:, :j] = False
            num += s * j * rot.log_quat(rot.quat_multiply(shifted, rot.quat_conjugate(q)))
            good &= vshift
    omega = -num / (dt * 2.0 * sum(j * j for j in range(1, h + 1)))
    return np.where(good[..., None], omega, np.nan)


@given(seed=st.integers(0, 2**32 - 1), h=st.integers(1, 6))
def test_compiled_rate_fit_equals_numpy(seed, h):
    from tumblenav.frontends import _points_kernel

    rng = np.random.default_rng(seed)
    B, n = 2, 40
    w = rng.normal(scale=0.3, size=(B, 1, 3))
    t = np.arange(n) * 0.1
    q = rot.quat_multiply(
        rot.exp_quat(-w * t[None, :, None]), rot.quat_normalize(rng.normal(size=(B, 1, 4)))
    )
    q = rot.quat_normalize(rot.boxplus(q, rng.normal(scale=1e-3, size=(B, n, 3))))
    valid = rng.random((B, n)) > 0.1
    q = np.where(valid[..., None], q, rot.IDENTITY)
    om, om3 = _points_kernel.rate_fit(q, valid, h, 0.1)
    ref = _rates_reference(q, valid, h, 0.1)
    assert np.array_equal(np.isfinite(om), np.isfinite(ref))
    assert np.allclose(om[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-12, atol=1e-14)
    assert np.array_equal(np.isfinite(om3), np.isfinite(ref) & (h >= 2))


@pytest.mark.parametrize("h", [2, 5, 10])
def test_cubic_rate_fit_removes_the_third_order_bias(h):
    """About a fixed axis the rotation vector is the angle: with angle(t) = w t + c t^3 the
    line's slope is biased by c * sum(c_j j^3) dt^2 (stereo_points._fit_factors), the cubic
    fit's slope is w exactly."""
    from tumblenav.frontends import _points_kernel
    from tumblenav.frontends.stereo_points import _fit_factors

    dt, w, c = 0.1, 0.3, 0.02
    axis = np.array([0.6, 0.0, 0.8])
    t = np.arange(60) * dt
    ang = w * (t - 3.0) + c * (t - 3.0) ** 3
    q = rot.exp_quat(-ang[None, :, None] * axis)  # R_GI(t) = exp(-angle [axis x])
    om, om3 = _points_kernel.rate_fit(q, np.ones((1, 60), bool), h, dt)
    k = 30  # t = 3: the rate there is w
    _, _, bias = _fit_factors(h)
    assert np.allclose(om3[0, k], w * axis, atol=1e-9)
    assert np.allclose(om[0, k], (w + c * bias * dt**2) * axis, atol=1e-9)


@given(seed=st.integers(0, 2**32 - 1), delay=st.integers(0, 7), every=st.integers(1, 6))
def test_compiled_normal_equations_equal_cumulative_sums(seed, delay, every):
    from tumblenav.frontends import _points_kernel

    rng = np.random.default_rng(seed)
    B, n = 2, 30
    a, b = rng.normal(size=(B, n, 3, 8)), rng.normal(size=(B, n, 3))
    ok = rng.random((B, n)) > 0.2
    w = np.where(ok, rng.random((B, n)), 0.0)
    sel = np.unique((np.arange(n) // every) * every)
    N, r, bb, cnt = _points_kernel.normal_equations_at(a, b, w, ok, delay, sel)
    aT = np.swapaxes(a, -1, -2)
    sums = [
        np.cumsum(w[..., None, None] * (aT @ a), axis=1),
        np.cumsum(w[..., None] * (aT @ b[..., None])[..., 0], axis=1),
        np.cumsum(w * np.sum(b * b, axis=-1), axis=1),
        np.cumsum(ok, axis=1),
    ]
    for got, full in zip((N, r, bb, cnt), sums, strict=True):
        idx = sel - delay
        ref = np.where(
            (idx >= 0).reshape((1, -1) + (1,) * (full.ndim - 2)),
            full[:, np.maximum(idx, 0)],
            0,
        )
        assert np.allclose(got, ref, rtol=1e-12, atol=1e-12)


@given(seed=st.integers(0, 2**32 - 1))
def test_compiled_matrix_to_quat_equals_rotations(seed):
    """Shepperd conversion, including rotations near a half turn about each axis."""
    from tumblenav.frontends import _points_kernel

    rng = np.random.default_rng(seed)
    R = Rotation.random(64, random_state=seed).as_matrix()
    axes = rng.normal(size=(6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    half = rot.exp_map(axes * (np.pi - rng.uniform(0, 1e-3, size=(6, 1))))
    R = np.concatenate([R, half, np.eye(3)[None]])
    q = _points_kernel.matrix_to_quat(np.ascontiguousarray(R))
    ref = rot.matrix_to_quat(R)
    assert np.all(q[:, 3] >= 0)
    assert np.allclose(np.abs(np.sum(q * ref, axis=1)), 1.0, atol=1e-12)
    assert np.allclose(rot.quat_to_matrix(q), R, atol=1e-12)


def test_front_end_batch_is_per_run():
    """A run's front-end result does not depend on the batch it is processed in (the
    compiled loops run per run; the numpy parts are vectorised)."""
    from tumblenav.frontends import stereo_points

    meas = _hu_measurements(3, 5, **{"sensor.noise.angular_rad": 2e-5})
    s = stereo_points.FrontEndSettings(min_ls_epochs=50)
    batch = stereo_points.process(meas, s)
    alone = stereo_points.process(meas[1:2], s)
    for name in ("p_L", "cov_L", "R_GI", "omega_G", "q_TI", "cov_TI"):
        a, b = getattr(batch, name)[1], getattr(alone, name)[0]
        assert np.array_equal(np.isfinite(a), np.isfinite(b)), name
        assert np.allclose(a[np.isfinite(b)], b[np.isfinite(b)], rtol=1e-10, atol=1e-14), name


def _stereo_like_points(rng, M, K, rng_m, sigma_rad, baseline_m=1.0):
    """M rigid sets of K points (a 3 m target) at ``rng_m`` along y (the optical axis of
    the parallel rig) with the stereo error shape: ``rng sigma`` wide, ``sqrt(2) rng^2 sigma
    / b`` deep; returns template g, points p, their covariances, R_CG and o (truth)."""
    g = rng.uniform(-1.5, 1.5, size=(M, K, 3))
    R = Rotation.random(M, random_state=rng.integers(2**31)).as_matrix()
    o = np.array([0.0, rng_m, 0.0]) + rng.normal(size=(M, 3))
    lat, dep = rng_m * sigma_rad, np.sqrt(2.0) * rng_m**2 * sigma_rad / baseline_m
    C = np.diag([lat**2, dep**2, lat**2])
    cov = np.broadcast_to(C, (M, K, 3, 3)).copy()
    p = g @ np.swapaxes(R, -1, -2) + o[:, None] + rng.normal(size=(M, K, 3)) @ np.sqrt(C)
    return g, p, cov, R, o


@pytest.mark.parametrize("rng_m", [17.0, 190.0])
def test_full_covariance_alignment_is_consistent_and_beats_kabsch(rng_m):
    """The G attitude fitted in the points' metric (``align_rigid`` through
    ``weighted_kabsch``): over 400 alignments of six points with the stereo error shape at
    2e-5 rad, its NEES (3 dof) is inside the chi-square bounds of 400 draws, and its
    median error is far below the isotropic Kabsch fit's (at 190 m: about 0.2 against
    20 deg)."""
    from tumblenav.evaluation.metrics import chi2_bounds
    from tumblenav.frontends.stereo_points import weighted_kabsch

    rng = np.random.default_rng(5)
    M = 400
    g, p, cov, R, o = _stereo_like_points(rng, M, 6, rng_m, 2e-5)
    w = np.ones((M, 6)) / np.trace(cov, axis1=-2, axis2=-1)

    def errors(R_GC):  # rotation vector of R_CG_est R_CG^T (the C-frame error)
        E = np.swapaxes(R_GC, -1, -2) @ np.swapaxes(R, -1, -2)
        return Rotation.from_matrix(E).as_rotvec()

    R_k, _, _, ok_k = weighted_kabsch(p, g, w)
    R_f, o_f, cov_G, ok = weighted_kabsch(p, g, w, cov)
    assert ok.all() and ok_k.all()
    e = errors(R_f)
    cov_C = np.swapaxes(R_f, -1, -2) @ cov_G @ R_f  # back to C (R_f is R_GC)
    nees = np.einsum("mi,mij,mj->m", e, np.linalg.inv(cov_C), e)
    lo, hi = chi2_bounds(3, M)
    assert lo <= np.mean(nees) / 3 <= hi, np.mean(nees) / 3
    med_f = np.median(np.linalg.norm(e, axis=1))
    med_k = np.median(np.linalg.norm(errors(R_k), axis=1))
    assert med_f < med_k / (20.0 if rng_m > 100 else 3.0), (med_f, med_k)
    assert np.median(np.linalg.norm(o_f - o, axis=1)) < np.sqrt(cov[0, 0, 1, 1])


def test_alignment_states_the_points_own_noise_apart_from_the_templates_errors():
    """``weighted_kabsch``'s ``noise``: the share of the G attitude's covariance from the
    points' own noise (the sandwich ``A^-1 B A^-1``). One template error held fixed and 2000
    draws of the points' noise: the fits scatter about the template's bias with that
    covariance (NEES of the centred errors inside the chi-square bounds), while the whole
    covariance, which also states the template's errors, is larger; with no template error
    stated both are the same."""
    from tumblenav.evaluation.metrics import chi2_bounds
    from tumblenav.frontends.stereo_points import weighted_kabsch

    rng = np.random.default_rng(1)
    M, K = 2000, 6
    g1, p1, cov1, R1, o1 = _stereo_like_points(rng, 1, K, 17.0, 2e-5)
    lat2 = (17.0 * 2e-5) ** 2
    T = np.broadcast_to(8.0 * lat2 * np.eye(3), (M, K, 3, 3)).copy()  # template's, in G
    g_err = g1[0] + rng.normal(size=(K, 3)) * np.sqrt(8.0 * lat2)  # one template error
    C = cov1[0, 0]
    p = (g1[0] @ R1[0].T + o1[0]) + rng.normal(size=(M, K, 3)) @ np.sqrt(C)
    g = np.broadcast_to(g_err, (M, K, 3)).copy()
    cov = np.broadcast_to(C, (M, K, 3, 3)).copy()
    w = np.ones((M, K)) / np.trace(C)
    noise: dict = {}
    R_f, _, cov_G, ok = weighted_kabsch(p, g, w, cov, T, noise=noise)
    assert ok.all()
    e = Rotation.from_matrix(np.swapaxes(R_f, -1, -2) @ R1[0].T).as_rotvec()  # in C
    e = e - e.mean(axis=0)  # the template's bias, common to every draw
    cov_n = np.swapaxes(R_f, -1, -2) @ noise["cov_G"] @ R_f  # back to C
    nees = np.einsum("mi,mij,mj->m", e, np.linalg.inv(cov_n), e)
    lo, hi = chi2_bounds(3, M)
    assert lo <= np.mean(nees) / 3 <= hi, np.mean(nees) / 3
    # the whole covariance states the template's errors too
    assert np.all(np.linalg.eigvalsh(cov_G - noise["cov_G"]) > 0)
    assert np.trace(cov_G[0]) > 2.0 * np.trace(noise["cov_G"][0])
    # no template error stated: the two are the same
    noise0: dict = {}
    _, _, cov_G0, _ = weighted_kabsch(p[:50], g[:50], w[:50], cov[:50], noise=noise0)
    assert np.allclose(noise0["cov_G"], cov_G0, rtol=1e-4, atol=0)


def test_alignment_warm_start_and_its_fallback():
    """A run of epochs: each fit starts from the previous one; an epoch whose points are
    inconsistent with any rigid fit (one point 1 m off at 1 mm noise) fails the chi-square
    gate and keeps the Kabsch fit with its information-form covariance, and the next
    epoch starts from its own Kabsch fit; fewer than three points or collinear points give
    no alignment."""
    from tumblenav.frontends import _points_kernel

    rng = np.random.default_rng(2)
    n, K = 6, 5
    g = rng.uniform(-1.5, 1.5, size=(K, 3))
    R = Rotation.from_rotvec(np.outer(np.arange(n) * 0.02, [0.3, 0.5, 0.8])).as_matrix()
    o = np.array([0.0, 10.0, 0.0])
    p = g @ np.swapaxes(R, -1, -2) + o + 1e-3 * rng.normal(size=(n, K, 3))
    p[2, 0] += [1.0, 0.0, 0.0]  # epoch 2: an outlier
    p[4, 2:] = np.nan  # epoch 4: two points left
    cov = np.broadcast_to(1e-6 * np.eye(3), (n, K, 3, 3)).copy()
    w = np.ones((n, K))
    gg = np.broadcast_to(g, (n, K, 3)).copy()
    Ro, oo, ct, ok, refined, _ = _points_kernel.align_rigid(
        p, gg, cov, np.zeros((1, K, 3, 3)), w, 4, n
    )
    assert ok.tolist() == [True, True, True, True, False, True]
    assert refined.tolist() == [True, True, False, True, False, True]
    for k in (0, 1, 3, 5):
        assert np.allclose(Ro[k], R[k], atol=5e-3)
    # the gate's fallback is the Kabsch fit (Horn) with the information-form covariance
    H, pc, gc, info, _, _ = _points_kernel.kabsch_moments(p[2:3], gg[2:3], w[2:3])
    Rk, _ = _points_kernel.kabsch_rotation(H)
    assert np.allclose(Ro[2], Rk[0]) and np.allclose(ct[2], np.linalg.inv(info[0]), rtol=1e-6)
    line = np.outer(np.arange(K, dtype=float), [1.0, 2.0, 0.5])
    assert not _points_kernel.align_rigid(
        line[None] + o, line[None], cov[:1], np.zeros((1, K, 3, 3)), w[:1], 4, 1
    )[3][0]


def test_rate_covariance_follows_the_attitudes_covariance_across_its_window():
    """``rates_and_covariance`` where G's covariance steps up (a change of the visible
    features: hu_selfocc run 96 at 94.5 s, 20-fold): the rates of the epochs whose window
    reaches past the step are as uncertain as its attitudes make them, each weighted by its
    coefficient squared. Over 400 runs the full covariance's NEES/dof at those epochs is
    inside its chi-square bounds (114 with the centre's covariance taken for the
    whole window), and ``rates_noise_cov`` is the same sum."""
    from tumblenav.evaluation.metrics import chi2_bounds
    from tumblenav.frontends.stereo_points import rates_and_covariance, rates_noise_cov

    dt, h, n, B = 0.1, 5, 60, 400
    t = np.arange(n) * dt
    axis = np.array([0.0, 0.6, 0.8])
    R_GI = Rotation.from_rotvec(-(0.2 * t)[:, None] * axis).as_matrix()
    sig = np.where(np.arange(n) < 30, 1e-3, 2e-2)  # the step at epoch 30
    rng = np.random.default_rng(8)
    psi = sig[None, :, None] * rng.normal(size=(B, n, 3))
    noisy = Rotation.from_rotvec(psi.reshape(-1, 3)).as_matrix().reshape(B, n, 3, 3) @ R_GI
    cov_G = np.broadcast_to((sig**2)[:, None, None] * np.eye(3), (B, n, 3, 3)).copy()
    fit: dict = {}
    om, cov_fit, cov = rates_and_covariance(noisy, cov_G, dt, h, unbiased=True, details=fit)
    k = np.arange(30 - h, 30)  # windows reaching past the step, centres before it
    e = om[:, k] - 0.2 * axis
    nees = np.einsum("bki,bkij,bkj->bk", e, np.linalg.inv(cov[:, k]), e) / 3
    lo, hi = chi2_bounds(3, B * len(k))
    assert lo <= nees.mean() <= hi, nees.mean()
    assert nees.mean(axis=0).max() < 1.3  # at each of those epochs, not only on average
    assert np.allclose(rates_noise_cov(cov_G, fit["cubic"], dt, h)[:, k], cov_fit[:, k])


def test_rate_fit_choice_follows_the_bias():
    """``rates_and_covariance``: with precise attitudes the third-order bias of the line
    dominates and the cubic fit is used; with noisy attitudes the line is used; the fit's
    covariance is the chosen fit's, and the full covariance (with the centre attitude's
    part, which grows with the rate) holds the errors (NEES/dof within 0.5-2)."""
    from tumblenav.frontends.stereo_points import _fit_factors, rates_and_covariance

    dt, h, n = 0.1, 10, 200
    t = np.arange(n) * dt
    axis = np.array([0.0, 0.6, 0.8])
    ang = 0.2 * t + 0.01 * t**2 + 0.001 * t**3  # about a fixed axis
    rate = 0.2 + 0.02 * t + 0.003 * t**2
    R_GI = Rotation.from_rotvec(-ang[:, None] * axis).as_matrix()[None]
    rng = np.random.default_rng(4)
    fl, fc, bias = _fit_factors(h)
    for sig, expect_cubic in ((1e-6, True), (2e-2, False)):
        noisy = Rotation.from_rotvec(sig * rng.normal(size=(n, 3))).as_matrix()[None] @ R_GI
        cov_G = np.broadcast_to(sig**2 * np.eye(3), (1, n, 3, 3))
        om, cov_fit, cov = rates_and_covariance(noisy, cov_G, dt, h)
        k = np.arange(110, n - h)
        var = np.trace(cov_fit[0, k], axis1=-2, axis2=-1) / 3 / (sig**2 / dt**2)
        if expect_cubic:
            assert np.allclose(var, fc)
        else:  # the line's, plus the bias's estimated mean square (noisy, at most a few fl)
            assert np.all((var >= fl * (1 - 1e-9)) & (var < fc))
        e = om[0, k] - rate[k, None] * axis
        nees = np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov[0, k]), e) / 3
        assert 0.5 < nees.mean() < 2.0, (sig, nees.mean())
    # the line's bias against its noise: 6.6e-4 against 3.6e-7 and 7.2e-3 rad/s
    assert 1e-6 * np.sqrt(fl) / dt < bias * 0.001 * dt**2 < 2e-2 * np.sqrt(fl) / dt
    # unbiased (the rows the least squares accumulates after the last refinement): the
    # cubic fit wherever it exists, per run, even where the line would be chosen
    sig = 2e-2
    noisy = Rotation.from_rotvec(sig * rng.normal(size=(2, n, 3))).as_matrix() @ R_GI
    cov_G = np.broadcast_to(sig**2 * np.eye(3), (2, n, 3, 3))
    auto = rates_and_covariance(noisy, cov_G, dt, h)
    mixed = rates_and_covariance(noisy, cov_G, dt, h, unbiased=np.array([True, False]))
    k = np.arange(110, n - h)
    var = np.trace(mixed[1][0, k], axis1=-2, axis2=-1) / 3 / (sig**2 / dt**2)
    assert np.allclose(var, fc)
    for a_, m_ in zip(auto, mixed, strict=True):
        np.testing.assert_array_equal(a_[1], m_[1])
    e = mixed[0][0, k] - rate[k, None] * axis  # no bias: mean error within its noise
    assert np.all(np.abs(e.mean(0)) < 4 * np.sqrt(fc) * sig / dt / np.sqrt(len(k) / (2 * h)))


def test_refinement_schedule_is_causal_and_refines():
    """Several refinements (the default 8, 10 and 30 s after G): the G attitudes before
    each refinement are those without it (the template as known then), the least squares'
    solutions before the first are those of the one-sighting template, and each version of
    the template is closer to the true shape than the one before (2e-5 rad; measured over
    20 runs: 7.0, 0.28 (8 s), then 0.04 mm (30 s),
    `python benchmarks/hu2024_refinement_checks.py schedule`)."""
    from tumblenav.campaign.store import run_seed
    from tumblenav.estimators import ekf_dpacf as hu
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate

    s = (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(duration_s=50.0, steady_state_window_s=[40.0, 50.0])
    )
    sims = [simulate(s, run_seed(5, k)) for k in range(3)]
    meas = [m for _, m in sims]
    scheds = {"none": 0.0, "8": [8.0], "8,10": [8.0, 10.0], "8,10,30": [8.0, 10.0, 30.0]}
    fe = {key: hu.frontend(meas, hu.parse_tuning({"template_refine_s": v}))
          for key, v in scheds.items()}  # fmt: skip
    full = fe["8,10,30"]
    hist = full.template_history
    assert len(hist) == 4
    ks = [k_v for k_v, _ in hist[1:]]
    for b, (truth, _) in enumerate(sims):
        k1, k2, k3 = (int(k[b]) for k in ks)
        assert k1 < k2 < k3 < len(full.t)
        same = np.testing.assert_array_equal
        same(full.R_GI[b, :k1], fe["none"].R_GI[b, :k1])
        same(full.R_GI[b, :k2], fe["8"].R_GI[b, :k2])
        same(full.R_GI[b, :k3], fe["8,10"].R_GI[b, :k3])
        np.testing.assert_allclose(full.R_GT[b, :k1], fe["none"].R_GT[b, :k1], rtol=1e-7,
                                   atol=1e-9)  # fmt: skip
        for k in (k1 - 1, k1, k2, k3 - 1, k3):
            v = sum(k >= kk for kk in (k1, k2, k3))
            same(full.template_at(k)[b], hist[v][1][b])
        errs = []
        for v, (_, tmpl) in enumerate(hist):
            kn = full.known_at[b, (k1, k2, k3, k3)[v] - 1]
            g, f = tmpl[b][kn], truth.features_T[kn]
            U, _, Vt = np.linalg.svd((f - f.mean(0)).T @ (g - g.mean(0)))
            R = Vt.T @ np.diag([1, 1, np.linalg.det(Vt.T @ U.T)]) @ U.T
            errs.append(np.sqrt(np.mean(np.sum((g - g.mean(0) - (f - f.mean(0)) @ R.T) ** 2, 1))))
        assert errs[1] < 0.3 * errs[0] and errs[3] < errs[1], errs


@given(seed=st.integers(0, 2**32 - 1))
def test_compiled_whitening_equals_numpy(seed):
    """``whiten_rows``: the rows of eq. 11-12 times ``L^-1`` with ``L L^T = C``, as numpy's
    Cholesky and triangular solve; epochs not ok are zeroed."""
    from tumblenav.frontends import _points_kernel

    rng = np.random.default_rng(seed)
    B, n = 2, 7
    a, b = rng.normal(size=(B, n, 3, 8)), rng.normal(size=(B, n, 3))
    X = rng.normal(size=(B, n, 3, 3))
    C0 = X @ np.swapaxes(X, -1, -2) + 0.1 * np.eye(3)
    ok = rng.random((B, n)) > 0.2
    C = C0 + 1e-12 * np.trace(C0, axis1=-2, axis2=-1)[..., None, None] * np.eye(3)
    L = np.linalg.cholesky(C)
    ra, rb = np.linalg.solve(L, a), np.linalg.solve(L, b[..., None])[..., 0]
    aa, bb, okk = a.copy(), b.copy(), ok.copy()
    _points_kernel.whiten_rows(aa, bb, C0, okk)
    assert np.array_equal(okk, ok)
    assert np.allclose(aa[ok], ra[ok], atol=1e-10) and np.allclose(bb[ok], rb[ok], atol=1e-10)
    assert not aa[~ok].any() and not bb[~ok].any()


def test_refined_template_steadies_g_and_is_causal():
    """The template refitted to all views of its first 30 s (stereo_points._refine_template):
    at a constant 17 m, 2e-5 rad, the G attitude's error about its mean (the G frame's
    offset, which the principal frame absorbs) after the refinement is several times smaller
    than with the one-sighting template (0.11-0.18 deg -> 0.013-0.023 deg over 8 runs,
    `python benchmarks/hu2024_refinement_checks.py template`); before it, G attitudes, the rates they fully determine and the least squares'
    solutions are unchanged (causal)."""
    from tumblenav import rotations as rot
    from tumblenav.campaign.store import run_seed
    from tumblenav.estimators import ekf_dpacf as hu
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate

    s = (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(
            duration_s=45.0,
            steady_state_window_s=[40.0, 45.0],
            **{"target.v0_L_m_s": [0.0, 0.0, 0.0]},
        )
    )
    sims = [simulate(s, run_seed(3, k)) for k in range(4)]
    meas = [m for _, m in sims]
    fe = {v: hu.frontend(meas, hu.parse_tuning({"template_refine_s": v})) for v in (0.0, 30.0)}
    h = hu.parse_tuning({}).frontend.rate_half_window
    for b, (truth, _) in enumerate(sims):
        first = int(np.argmax(fe[0.0].known_at[b].any(axis=1)))
        k_ref = -(-(first + 300) // 10) * 10  # at a least-squares solution (every 10)
        assert k_ref < len(fe[0.0].t) - 50
        same = np.testing.assert_array_equal
        same(fe[0.0].R_GI[b, :k_ref], fe[30.0].R_GI[b, :k_ref])
        same(fe[0.0].omega_G[b, : k_ref - h], fe[30.0].omega_G[b, : k_ref - h])

        # the least squares' solutions before k_ref, and what follows from them (to the
        # rounding of the sums' correction, old rows minus refined rows, 5e-11 measured)
        def close(x, y):
            np.testing.assert_allclose(x, y, rtol=1e-7, atol=1e-9)

        close(fe[0.0].R_GT[b, :k_ref], fe[30.0].R_GT[b, :k_ref])
        close(fe[0.0].cov_ratios[b, :k_ref], fe[30.0].cov_ratios[b, :k_ref])
        close(fe[0.0].q_TI[b, :k_ref], fe[30.0].q_TI[b, :k_ref])
        assert not np.array_equal(fe[0.0].R_GT[b, k_ref:], fe[30.0].R_GT[b, k_ref:])
        # the template as known at each epoch: the first one before k_ref
        same(fe[30.0].template_at(k_ref - 1)[b], fe[0.0].template_G[b])
        same(fe[30.0].template_at(k_ref)[b], fe[30.0].template_G[b])
        spread = []
        for f in fe.values():
            kn = f.known[b]
            g, ft = f.template_G[b][kn], truth.features_T[kn]
            U, _, Vt = np.linalg.svd((ft - ft.mean(0)).T @ (g - g.mean(0)))
            R_GT = Vt.T @ np.diag([1, 1, np.linalg.det(Vt.T @ U.T)]) @ U.T
            ks = np.arange(k_ref, len(f.t))
            ks = ks[np.all(np.isfinite(f.R_GI[b, ks]), axis=(-1, -2))]
            R_true = R_GT @ rot.quat_to_matrix(truth.q_TI[ks])
            e = rot.log_map(f.R_GI[b, ks] @ np.swapaxes(R_true, -1, -2))
            spread.append(np.sqrt(np.mean(np.sum((e - e.mean(0)) ** 2, axis=1))))
        assert spread[1] < 0.4 * spread[0]


def test_joint_normal_equations_kernel_matches_numpy():
    """The compiled sums of stereo_points.joint_features against their numpy form."""
    from tumblenav import rotations as rot
    from tumblenav.frontends import _points_kernel

    rng = np.random.default_rng(17)
    m, N, K, nf = 7, 4, 9, 3
    Phi = rng.normal(size=(m, 3, K))
    R = rot.exp_map(rng.normal(size=(m, 3)))
    p = rng.normal(size=(m, N, 3))
    A0 = rng.normal(size=(m, N, 3, 3))
    cov = A0 @ np.swapaxes(A0, -1, -2) + 0.1 * np.eye(3)
    B0 = rng.normal(size=(m, 3, 3)) * 0.01
    cov_G = B0 @ np.swapaxes(B0, -1, -2)
    col = rng.integers(-1, nf, size=(m, N))
    f = rng.normal(size=(nf, 3))
    Nm, rhs, bb, cnt = _points_kernel.joint_normal_equations(Phi, R, p, cov, cov_G, col, f, nf)
    dim = K + 3 * nf
    N_ref, r_ref, bb_ref = np.zeros((dim, dim)), np.zeros(dim), 0.0
    for j, i in zip(*np.nonzero(col >= 0), strict=True):
        c = col[j, i]
        A = np.zeros((3, dim))
        A[:, :K] = Phi[j]
        A[:, K + 3 * c : K + 3 * c + 3] = R[j]
        lever = R[j] @ rot.skew(f[c])
        W = np.linalg.inv(cov[j, i] + lever @ cov_G[j] @ lever.T)
        N_ref += A.T @ W @ A
        r_ref += A.T @ W @ p[j, i]
        bb_ref += p[j, i] @ W @ p[j, i]
    assert cnt == np.sum(col >= 0)
    np.testing.assert_allclose(Nm, N_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(rhs, r_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(bb, bb_ref, rtol=1e-10)


def test_refinement_is_per_run_in_a_batch():
    """A run whose G is defined too late for the template's refinement (here: features
    unseen for the first 10 s of a 35-s run) gets, inside a batch of refined runs, exactly
    what it gets alone (no refinement): the front end's batch is per run."""
    import dataclasses

    from tumblenav.campaign.store import run_seed
    from tumblenav.estimators import ekf_dpacf as hu
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate

    s = (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(duration_s=35.0, steady_state_window_s=[30.0, 35.0])
    )
    meas = [simulate(s, run_seed(4, k))[1] for k in range(3)]
    late = meas[0].observed.copy()
    late[:100] = False
    uv = np.where(late[..., None], meas[0].uv, np.nan)
    meas[0] = dataclasses.replace(meas[0], observed=late, uv=uv)
    tun = hu.parse_tuning({})
    both = hu.frontend(meas, tun)
    alone = hu.frontend(meas[:1], tun)
    refined = hu.frontend(meas[1:], tun)
    assert np.argmax(both.known_at[0].any(axis=1)) >= 100  # G only after 10 s
    for key in ("R_GI", "omega_G", "R_GT", "q_TI", "cov_frame", "template_G"):
        np.testing.assert_allclose(getattr(both, key)[0], getattr(alone, key)[0],
                                   rtol=1e-7, atol=1e-9, err_msg=key)  # fmt: skip
        np.testing.assert_allclose(getattr(both, key)[1:], getattr(refined, key),
                                   rtol=1e-7, atol=1e-9, err_msg=key)  # fmt: skip


def test_refinement_leaves_no_gap_when_g_starts_off_the_solution_grid():
    """G defined at epoch 13 (not a least-squares solution epoch): each switch (the default
    refinements, 8, 10 and 30 s after G) is rounded up to the next solution, and no epoch
    loses its G attitude or rate on the way."""
    import dataclasses

    from tumblenav.campaign.store import run_seed
    from tumblenav.estimators import ekf_dpacf as hu
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate

    s = (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(duration_s=45.0, steady_state_window_s=[40.0, 45.0])
    )
    m = simulate(s, run_seed(4, 0))[1]
    late = m.observed.copy()
    late[:13] = False
    m = dataclasses.replace(m, observed=late, uv=np.where(late[..., None], m.uv, np.nan))
    fe0 = hu.frontend([m], hu.parse_tuning({"template_refine_s": 0}))
    fe = hu.frontend([m], hu.parse_tuning({}))
    assert np.argmax(fe.known_at[0].any(axis=1)) == 13
    np.testing.assert_array_equal(
        np.all(np.isfinite(fe0.R_GI[0]), axis=(-1, -2)),
        np.all(np.isfinite(fe.R_GI[0]), axis=(-1, -2)),
    )
    np.testing.assert_array_equal(np.isfinite(fe0.omega_G[0]), np.isfinite(fe.omega_G[0]))
    np.testing.assert_array_equal(fe0.R_GI[0, :100], fe.R_GI[0, :100])  # first k_ref = 100
    assert not np.allclose(fe0.R_GI[0, 100:120], fe.R_GI[0, 100:120])
    np.testing.assert_array_equal(fe.template_history[1][0], [100])
    np.testing.assert_array_equal(fe.template_history[2][0], [120])
    np.testing.assert_array_equal(fe.template_history[3][0], [320])


def _synthetic_frames(q_truth, q_model, rate_noise, B=40, sig=2e-4, seed=1):
    """Frame NEES/dof at 100 s and 200 s of the inertia least squares on a synthetic rigid
    body (inertia 300, 250, 120, slow tumble) whose G attitudes carry white errors of
    ``sig`` rad and whose truth carries the isotropic torque ``q_truth``."""
    from tumblenav import rotations as rot
    from tumblenav.dynamics.disturbances import disturbed_attitude
    from tumblenav.frontends.stereo_points import (
        FrontEndSettings,
        identify_and_dpacf,
        rates_and_covariance,
    )

    rng = np.random.default_rng(seed)
    dt, h = 0.1, 10
    t = np.arange(0.0, 200.0 + 1e-9, dt)
    n = len(t)
    q = rng.standard_normal(4)
    R_GT = rot.quat_to_matrix(q / np.linalg.norm(q))
    R_GI = np.empty((B, n, 3, 3))
    for b in range(B):
        q0 = rng.standard_normal(4)
        qs, _ = disturbed_attitude(
            q0 / np.linalg.norm(q0), [0.02, 0.03, 0.04], [300.0, 250.0, 120.0], t, q_truth, rng
        )
        psi = sig * rng.standard_normal((n, 3))
        R_GI[b] = rot.exp_map(psi) @ (R_GT @ rot.quat_to_matrix(qs))
    cov_G = np.broadcast_to(sig**2 * np.eye(3), (B, n, 3, 3)).copy()
    fit: dict = {}
    om, cf, cw = rates_and_covariance(R_GI, cov_G, dt, h, unbiased=True, details=fit)
    s = FrontEndSettings(q_r=q_model, min_ls_epochs=50, max_dpacf_sigma_rad=1.0,
                         rate_noise=rate_noise)  # fmt: skip
    var_w = np.trace(cw, axis1=-2, axis2=-1) / 3
    R_est, _, _, _, cov_phi, _, _ = identify_and_dpacf(
        om, var_w, R_GI, cov_G, s, delay=h, cov_w=cf, fit=fit, dt=dt
    )
    out = []
    for k in (n // 2, n - 1):
        v = []
        for b in range(B):
            turns = ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])
            e = min((rot.log_map(R_GT.T @ R_est[b, k] @ np.diag(d)) for d in turns),
                    key=np.linalg.norm)  # fmt: skip
            v.append(e @ np.linalg.solve(cov_phi[b, k], e) / 3)
        out.append(float(np.mean(v)))
    return out


def test_errors_in_variables_take_the_rates_zero_mean_noise():
    """The inertia least squares' bias compensation (``gls``'s ``Nc``, ``rc``) takes the
    regressors' noise from ``cov_w_noise`` (``rates.rates_noise_cov``: the points' own noise
    through the rate fit), not from the whitening, which also states the template's errors
    (on hu_selfocc run 173 that compensation removed more than all of the information along
    one direction and the moments jumped to (1, 0.19, -0.10)): the compensation scales with
    it, the sums do not; and for attitudes whose whole covariance is their own noise,
    ``rates_noise_cov`` is the rate fit's covariance."""
    from tumblenav.frontends import stereo_points
    from tumblenav.frontends.stereo_points import inertia_ls, rates

    n, dt, h = 80, 0.5, 4
    s = stereo_points.FrontEndSettings(rate_half_window=h)
    t = np.arange(n) * dt
    om = np.stack([0.1 + 0.02 * np.sin(0.3 * t), 0.05 * np.cos(0.2 * t), 0.03 + 0 * t], -1)[None]
    R = Rotation.random(n, random_state=4).as_matrix()[None]
    A = np.array([[1.0, 0.3, -0.2], [0.0, 1.2, 0.4], [0.0, 0.0, 0.7]])
    cov_w = np.broadcast_to(A @ A.T * 1e-6, (1, n, 3, 3)).copy()  # correlated axes
    cov_G = np.broadcast_to(1e-6 * np.eye(3), (1, n, 3, 3)).copy()
    var_w = np.trace(cov_w, axis1=-2, axis2=-1) / 3
    sel = np.array([n - 1])
    sums = []
    for cn in (None, cov_w, 3.0 * cov_w):
        rows = inertia_ls._gls_rows(om, var_w, R, cov_w, cov_G, None, s, dt, cn)
        sums.append(inertia_ls._version_sums(rows, om, R, s, dt, 0, sel))
    N0, Nc0, rc0 = sums[0][0], sums[0][6], sums[0][7]
    assert np.abs(Nc0).max() > 0 and np.abs(rc0).max() > 0
    assert np.allclose(sums[1][6], Nc0) and np.allclose(sums[1][7], rc0)  # the default
    assert np.allclose(sums[2][6], 3.0 * Nc0) and np.allclose(sums[2][7], 3.0 * rc0)
    assert np.array_equal(sums[2][0], N0) and np.array_equal(sums[2][1], sums[0][1])
    # rates_noise_cov: the fit's covariance where the attitudes' noise is all there is
    q = rot.exp_quat(np.cumsum(np.broadcast_to([0.02, 0.01, -0.01], (n, 3)), 0))
    R_GI = rot.quat_to_matrix(q)[None]
    fit: dict = {}
    _, cov_fit, _ = rates.rates_and_covariance(R_GI, cov_G, dt, h, unbiased=True, details=fit)
    got = rates.rates_noise_cov(cov_G, fit["cubic"], dt, h)
    ok = np.all(np.isfinite(cov_fit), axis=(-1, -2))
    assert ok.sum() == n - 2 * h and fit["cubic"][ok].all()
    assert np.allclose(got[ok], cov_fit[ok], rtol=1e-12)


def test_inertia_least_squares_covariance_against_monte_carlo():
    """stereo_points.gls: the DPACF frame's covariance from the least squares' noise model
    against a Monte Carlo of 40 synthetic runs (seeded). With white G attitude errors the
    moving-sum correlation model ('white_attitudes') is right: frame NEES/dof ~1 (measured
    1.2-1.9 torque-free, 0.85-1.2 under the torque). Under a truth torque of 1e-8 rad^2/s^3
    the momentum's random walk makes it right, and without it the frame is over-confident
    by orders of magnitude (measured 6e3-6e4: the previous engineer's 12.7 on hu_big12 had
    the 2h+1 allowance). 'independent' rows (the default, for the real G attitude errors'
    slowly varying part) are conservative here."""
    free = _synthetic_frames(0.0, 0.0, "white_attitudes")
    assert all(0.5 < x < 2.5 for x in free), free
    torque = _synthetic_frames(1e-8, 1e-8, "white_attitudes")
    assert all(0.5 < x < 2.0 for x in torque), torque
    blind = _synthetic_frames(1e-8, 0.0, "white_attitudes")
    assert min(blind) > 100.0, blind
    indep = _synthetic_frames(1e-8, 1e-8, "independent")
    assert all(x < 2.0 for x in indep), indep


def _joint_trials(trials, seed, psi_sigma, q_force):
    """Synthetic joint fits (stereo_points.joint_features): six features in +-1.5 m tumbling
    (0.1 rad/s of precession, 0.07 rad/s of spin), 20 s at 10 Hz, 20 m away, points 8 mm deep and 0.4 mm wide; the measured
    attitudes off by a slowly varying error (a constant and a 30-s sinusoid of
    ``psi_sigma`` each, plus white 1e-4 rad: a template's error turned into attitude by the
    changing view) and the mass centre pushed by a white force of density ``q_force``
    (double integrator). Yields the truth and the fits as (with cov_dev, fixed attitudes),
    (with cov_dev, free attitudes), (without cov_dev, free)."""
    from tumblenav.frontends import stereo_points

    rng = np.random.default_rng(seed)
    m, N, dt = 200, 6, 0.1
    t = np.arange(m) * dt
    Phi = np.concatenate([np.broadcast_to(np.eye(3), (m, 3, 3)), t[:, None, None] * np.eye(3)], 2)
    lo, hi = np.minimum.outer(t, t), np.maximum.outer(t, t)
    Qd = q_force * (lo**2 * hi / 2 - lo**3 / 6)
    cov_dev = np.einsum("jk,ab->jakb", Qd, np.eye(3))
    L = np.linalg.cholesky(Qd + 1e-30 * np.eye(m))
    for _ in range(trials):
        f = rng.uniform(-1.5, 1.5, size=(N, 3))
        f -= f.mean(0) * 0.5  # the mass centre away from the features' centroid
        ax1, ax2 = rng.normal(size=(2, 3))
        ax1, ax2 = ax1 / np.linalg.norm(ax1), ax2 / np.linalg.norm(ax2)
        R0 = rot.quat_to_matrix(rot.quat_normalize(rng.normal(size=4)))
        # a tumble: precession about an inertial axis and a spin about a body axis
        R = rot.exp_map(0.1 * t[:, None] * ax1) @ R0 @ rot.exp_map(0.07 * t[:, None] * ax2)
        a = np.array([20.0, 1.0, -2.0]) + rng.normal(size=3)
        a = np.concatenate([a, rng.normal(size=3) * 0.01])
        r = Phi @ a + (L @ rng.normal(size=(m, 3)))
        los = a[:3] / np.linalg.norm(a[:3])
        B_ = np.linalg.svd(np.eye(3) - np.outer(los, los))[0][:, :2]
        ci = 0.008**2 * np.outer(los, los) + 4e-4**2 * B_ @ B_.T
        cov = np.broadcast_to(ci, (m, N, 3, 3)).copy()
        p = r[:, None, :] + np.einsum("jab,ib->jia", R, f)
        p += rng.multivariate_normal(np.zeros(3), ci, size=(m, N))
        psi = rng.normal(size=3) * psi_sigma + np.outer(
            np.sin(2 * np.pi * t / 30 + rng.uniform(0, 6.3)), rng.normal(size=3) * psi_sigma
        )
        psi += rng.normal(size=(m, 3)) * 1e-4
        R_meas = R @ rot.exp_map(psi)
        cov_G = np.broadcast_to((1.5 * psi_sigma**2 + 1e-8) * np.eye(3), (m, 3, 3)).copy()
        use = np.ones((m, N), dtype=bool)
        f0 = f + rng.normal(size=f.shape) * 0.005
        fits = [
            stereo_points.joint_features(Phi, R_meas, p, cov, cov_G, use, f0, cov_dev=cov_dev),
            stereo_points.joint_features(
                Phi, R_meas, p, cov, cov_G, use, f0, cov_dev=cov_dev, free_attitudes=True
            ),
            stereo_points.joint_features(Phi, R_meas, p, cov, cov_G, use, f0, free_attitudes=True),
        ]
        yield f, fits


def _shape_and_shift_nees(f, fit):
    """NEES/dof of the fitted features' shape (their rotation and shift about the truth's
    projected out) and of their common shift."""
    _, fe, C, idx = fit
    e = (fe - f[idx]).ravel()
    n = len(idx)
    A = np.zeros((3 * n, 6))
    for i in range(n):
        A[3 * i : 3 * i + 3, :3] = -rot.skew(f[idx][i])
        A[3 * i : 3 * i + 3, 3:] = np.eye(3)
    Rm = np.eye(3 * n) - A @ np.linalg.pinv(A)
    shape = e @ Rm @ np.linalg.pinv(Rm @ C @ Rm, rcond=1e-10) @ Rm @ e / (3 * n - 6)
    S = np.kron(np.ones((1, n)) / n, np.eye(3))
    es = S @ e
    return shape, es @ np.linalg.solve(S @ C @ S.T, es) / 3


def test_joint_features_with_free_attitudes_is_honest_under_correlated_attitude_errors():
    """Issue 18: the measured G attitudes carry their template's error, fixed in G and so
    correlated from epoch to epoch; the joint fit that takes them as measured with
    independent errors reports the features' shape too small (NEES/dof 5.0 over 40 seeded
    synthetic runs, 1.06 without the attitude errors), the fit with every epoch's attitude
    an unknown (``free_attitudes``) reports it honestly (1.11). Under a white force on the
    mass centre (1e-9 m^2/s^3) the covariance with the force's deviation from the Hill
    motion (``cov_dev``) covers the features' common shift (NEES/dof 1.16), without it the
    shift is over-confident (55)."""
    fixed, free, shift_dev, shift_none, shape_free = [], [], [], [], []
    for f, (a, b, c) in _joint_trials(40, 18, 3e-4, 1e-9):
        fixed.append(_shape_and_shift_nees(f, a)[0])
        s_b, h_b = _shape_and_shift_nees(f, b)
        free.append(s_b)
        shift_dev.append(h_b)
        shift_none.append(_shape_and_shift_nees(f, c)[1])
        shape_free.append(_shape_and_shift_nees(f, c)[0])
    assert np.mean(fixed) > 3.0
    assert 0.7 < np.mean(free) < 1.5
    assert 0.7 < np.mean(shape_free) < 1.5
    assert 0.7 < np.mean(shift_dev) < 1.6
    assert np.mean(shift_none) > 10.0


def test_residual_scale_inflates_only_beyond_what_the_model_allows():
    """``inertia_ls._residual_scale``: the residuals' ratio to what the noise model expects
    scales the covariance only beyond its 95 % quantile under the model; that quantile is
    near 1 where the rows' own noise dominates (many degrees of freedom), about 2 where the
    momentum's random walk does over three axes (7.5) and 2.7 over one (2.5); the gate is
    always sqrt(max(ratio, 1))."""
    from tumblenav.frontends.stereo_points.inertia_ls import WALK_DOF_PER_AXIS, _residual_scale

    ratio = np.array([0.5, 1.2, 1.6, 2.5, 5.0])
    expect = np.ones_like(ratio)
    rows = np.full_like(ratio, 30_000.0)
    white, gate = _residual_scale(ratio, expect, np.zeros_like(ratio), rows, 21)
    np.testing.assert_allclose(white, [1.0, 1.2, 1.6, 2.5, 5.0])
    np.testing.assert_allclose(gate, np.sqrt([1.0, 1.2, 1.6, 2.5, 5.0]))
    walk, _ = _residual_scale(ratio, expect, expect, rows, 21, 3.0)
    q95 = stats.chi2.ppf(0.95, 3 * WALK_DOF_PER_AXIS) / (3 * WALK_DOF_PER_AXIS)
    assert 1.9 < q95 < 2.0
    np.testing.assert_allclose(walk, [1.0, 1.0, 1.0, 2.5, 5.0])
    one_axis, _ = _residual_scale(ratio, expect, expect, rows, 21, 1.0)
    np.testing.assert_allclose(one_axis, [1.0, 1.0, 1.0, 1.0, 5.0])


def test_walk_dof_is_that_of_a_brownian_motion_less_its_mean():
    """WALK_DOF_PER_AXIS: the squared norm of a Brownian motion less its mean over the window has
    (sum 1/(pi k)^2)^2 / sum 1/(pi k)^4 = 2.5 degrees of freedom per axis (2 E^2 / Var),
    against 4000 seeded simulated walks of 2000 steps."""
    from tumblenav.frontends.stereo_points.inertia_ls import WALK_DOF_PER_AXIS

    rng = np.random.default_rng(7)
    W = np.cumsum(rng.standard_normal((4000, 2000)), axis=1)
    s = np.sum((W - W.mean(axis=1, keepdims=True)) ** 2, axis=1)
    dof = 2 * s.mean() ** 2 / s.var()
    assert abs(dof - WALK_DOF_PER_AXIS) < 0.15, dof
