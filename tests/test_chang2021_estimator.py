"""ekf-pose (Chang 2021 Sec. 2): Jacobians against finite differences (the eq. 23 factor),
the measurement functions against the truth, the start, the frame alignment and robustness."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tumblenav import rotations as rot
from tumblenav.estimators.base import get
from tumblenav.estimators.chang2021 import model as M
from tumblenav.estimators.chang2021.measurements import feature_tracks, pose_fix, rate_eq29
from tumblenav.estimators.context import context_from_scenario
from tumblenav.evaluation.alignment import truth_state
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate
from tumblenav.testing import numerical_jacobian


def _scenario(duration=40.0, **upd):
    """chang2021_close on point tracks, its process noise the 1e-10 ekf-pose assumed as
    constants before its Q followed the scenario's process_noise (the built-in states Hu
    2024's, 2e-6 m^2/s^3: a random force that leaves the mass centre along the rotation axis
    unobservable within these runs)."""
    sc = load_scenario("chang2021_close")
    if getattr(sc.sensor, "images", None) is not None:
        sc = sc.with_updates(**{"sensor.images": None})
    pn = {"process_noise.translational_m2_s4": 1e-10, "process_noise.rotational_rad2_s4": 1e-10}
    return sc.with_updates(duration_s=duration, steady_state_window_s=[0.0, duration], **(pn | upd))


def _flow_jacobian(x, inertia, n, h=1e-4):
    """d(dx_dot)/d(dx) by central differences of the flow over +-h, through boxplus/boxminus."""

    def f(dt):
        return numerical_jacobian(
            lambda y: M.propagate_mean(y, dt, inertia, n),
            x,
            M.LAYOUT.boxplus,
            M.LAYOUT.boxminus,
            eps=1e-6,
            dim=M.DIM,
        )

    return (f(h) - f(-h)) / (2 * h)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), sphere=st.booleans())
def test_error_jacobian_matches_finite_differences(seed, sphere):
    rng = np.random.default_rng(seed)
    x = np.zeros(M.LAYOUT.nominal_dim)
    x[M.X_ATT] = rot.quat_normalize(rng.normal(size=4))
    x[M.X_RATE] = rng.normal(size=3) * 0.1
    x[M.X_POS] = rng.normal(size=3) * 10
    x[M.X_VEL] = rng.normal(size=3) * 0.01
    x[M.X_OFF] = rng.normal(size=3) * 0.3
    inertia = np.eye(3) if sphere else np.diag(rng.uniform(50, 150, 3))
    n = 0.05  # a large orbit rate so that the eq. 23 block is well above round-off
    F = M.error_jacobian(x, inertia, n)
    Fn = _flow_jacobian(x, inertia, n)
    assert np.allclose(F, Fn, atol=2e-6 * max(1.0, np.abs(F).max()))


def test_eq23_printed_factor_is_twice_the_left_error_one():
    """Chang 2021 eq. 23 as printed is 2x tumblenav's (left error) F_wq, i.e. -2x in the
    paper's own eq. 9 error (da = -dtheta); the finite differences decide (module docstring)."""
    rng = np.random.default_rng(7)
    x = np.zeros(M.LAYOUT.nominal_dim)
    x[M.X_ATT] = rot.quat_normalize(rng.normal(size=4))
    x[M.X_RATE] = [0.04, -0.06, 0.05]
    inertia = np.diag([120.0, 100.0, 80.0])
    n = 0.05
    Fn = _flow_jacobian(x, inertia, n)[M.E_RATE, M.E_ATT]
    a = rot.quat_to_matrix(x[M.X_ATT]) @ M.omega_LI_L(n)
    w = x[M.X_RATE]
    wti = w + a
    Ii = np.linalg.inv(inertia)
    printed = 2 * Ii @ (-rot.skew(inertia @ wti) + rot.skew(wti) @ inertia) @ rot.skew(
        a
    ) - 2 * rot.skew(w) @ rot.skew(a)
    assert np.allclose(Fn, 0.5 * printed, atol=1e-7)
    assert not np.allclose(Fn, printed, atol=1e-5)


def test_feature_positions_and_velocities_are_consistent_with_their_covariances():
    sc = _scenario(20.0)
    truth, meas = simulate(sc, 3)
    tr = feature_tracks(meas)
    e = (tr.p - truth.features_L)[tr.ok_p]
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(tr.P[tr.ok_p]), e)
    assert 0.9 < nees.mean() / 3 < 1.1
    dt = np.diff(truth.t)[0]
    fl = truth.features_L
    v_true = np.full_like(fl, np.nan)
    v_true[1:] = (fl[1:] - fl[:-1]) / dt  # the interval eq. 26's differenced pixels span
    e = (tr.v - v_true)[tr.ok_v]
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(tr.V[tr.ok_v]), e)
    assert 0.9 < nees.mean() / 3 < 1.1
    assert np.abs(e.mean(axis=0)).max() < 5 * e.std(axis=0).max() / np.sqrt(len(e))


def test_feature_tracks_of_sparse_sightings_are_those_of_the_full_run():
    """feature_tracks works on the observed (epoch, feature) entries only (image front ends
    create thousands of track IDs, ~3 % of them seen at a time): hiding 70 % of a run's
    sightings at random leaves every remaining entry's position, covariance and velocity as
    the full run gives them (a velocity where both of its epochs remain), and the hidden ones
    unobserved, NaN, the identity for V."""
    from dataclasses import replace

    sc = _scenario(10.0)
    _, meas = simulate(sc, 2)
    full = feature_tracks(meas)
    rng = np.random.default_rng(11)
    keep = rng.random(meas.observed.shape[::2]) < 0.3  # (n, N)
    obs = meas.observed & keep[:, None, :]
    uv = np.where(obs[..., None], meas.uv, np.nan)
    sp = feature_tracks(replace(meas, uv=uv, observed=obs))
    assert sp.ok_p.sum() > 100 and sp.ok_v.sum() > 20
    assert np.array_equal(sp.ok_p, full.ok_p & keep)
    assert np.array_equal(sp.ok_v, full.ok_v & keep & np.vstack([keep[:1], keep[:-1]]))
    for a, b, ok in ((sp.p, full.p, sp.ok_p), (sp.P, full.P, sp.ok_p), (sp.v, full.v, sp.ok_v)):
        assert np.allclose(a[ok], b[ok], rtol=1e-12, atol=0.0)
    assert np.all(np.isnan(sp.p[~sp.ok_p])) and np.all(np.isnan(sp.v[~sp.ok_v]))
    assert np.allclose(sp.V[~sp.ok_v], np.eye(3))
    # unobserved: the covariance of a point 10 m down the rig's y axis, turned into L
    R_CL = rot.quat_to_matrix(meas.q_CL)  # (n, 3, 3)
    fill = np.einsum("tji,jk,tkl->til", R_CL, _fill_covariance(meas), R_CL)
    hidden = np.argwhere(~sp.ok_p)
    assert np.allclose(sp.P[hidden[:, 0], hidden[:, 1]], fill[hidden[:, 0]], rtol=1e-12, atol=0)


def _fill_covariance(meas):
    from tumblenav.estimators.chang2021.measurements import _covariance_C, pixel_variance

    P, ok = _covariance_C(np.array([0.0, 10.0, 0.0]), meas.rig, pixel_variance(meas))
    assert ok
    return P


def test_eq29_recovers_a_rigid_rotation():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(10, 3))
    w = np.array([0.03, -0.05, 0.02])
    omega, C = rate_eq29(d, np.cross(w, d), np.tile(np.eye(3) * 1e-6, (10, 1, 1)))
    assert np.allclose(omega, w, atol=1e-12)
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])  # collinear: rotation about it unknown
    assert rate_eq29(line, np.cross(w, line), np.tile(np.eye(3), (5, 1, 1))) is None


def test_pose_fix_refuses_collinear_points_and_drops_an_outlier():
    rng = np.random.default_rng(4)
    s = rng.normal(size=(30, 3))
    R = rot.exp_map(np.array([0.3, -0.2, 0.5]))  # R_ThatL
    rho = (s @ R) + np.array([1.0, 9.0, 2.0])  # rho = c + R_LThat s
    S = np.tile(np.eye(3) * 1e-6, (30, 1, 1))
    rho_bad = rho.copy()
    rho_bad[3] += [0.5, 0.0, 0.0]
    fix = pose_fix(rho_bad, S, s, S)
    assert fix is not None and fix.outliers == 1 and not fix.used[3]
    assert np.allclose(rot.quat_to_matrix(fix.q_ThatL), R, atol=1e-6)
    line = np.outer(np.linspace(-1, 1, 10), [1.0, 0.5, 0.2])
    assert pose_fix(line, S[:10], line, S[:10]) is None
    assert pose_fix(rho[:2], S[:2], s[:2], S[:2]) is None


def test_alignment_defines_the_frame_at_its_epoch():
    sc = _scenario(30.0, **{"estimator.tuning": {"init_frames": 20}})
    truth, meas = simulate(sc, 1)
    h = get("ekf-pose").run(context_from_scenario(sc), meas, np.random.default_rng(1))
    assert h.info["convention"] == "chang2021"
    k0 = h.info["frame_epoch"]
    xt = truth_state(truth, h)
    assert np.allclose(xt[k0, M.X_ATT], rot.IDENTITY, atol=1e-12)  # R_ThatL(k0) = I
    assert np.allclose(xt[:, M.X_POS], truth.r_L)
    # the start (truth-free) is within a few of its own sigmas in attitude and rate
    k = h.info["start_epoch"]
    dx = h.layout.boxminus(xt[k], h.x[k])
    P = h.P[k]
    for blk in ("attitude", "rate"):
        s = h.layout.err(blk)
        d2 = dx[s] @ np.linalg.solve(P[s, s], dx[s])
        assert d2 < 40.0  # chi2(3) 0.99999 is 25.9; a loose bound on a single start


@pytest.mark.parametrize("case", ["black", "two_features", "collinear", "all_lost"])
def test_robust_to_missing_and_degenerate_frames(case):
    sc = _scenario(30.0, **{"estimator.tuning": {"init_frames": 20}})
    truth, meas = simulate(sc, 2)
    uv, obs = meas.uv.copy(), meas.observed.copy()
    bad = slice(60, 80)
    if case == "black":
        obs[bad] = False
    elif case == "two_features":
        keep = np.zeros(obs.shape[-1], bool)
        keep[np.flatnonzero(obs[60].all(0))[:2]] = True
        obs[bad] &= keep
    elif case == "collinear":  # only the features on one line through the target
        from tumblenav.sensors import project

        f_C = truth.features_C
        line = f_C[bad, :1] + np.linspace(0, 1, obs.shape[-1])[None, :, None] * (
            f_C[bad, 1:2] - f_C[bad, :1]
        )
        uv_line, vis = project(meas.rig, line)
        uv[bad] = uv_line
        obs[bad] = vis
    elif case == "all_lost":
        obs[60:] = False
    uv = np.where(obs[..., None], uv, np.nan)
    from dataclasses import replace

    m2 = replace(meas, uv=uv, observed=obs)
    h = get("ekf-pose").run(context_from_scenario(sc), m2, np.random.default_rng(2))
    started = np.flatnonzero(np.all(np.isfinite(h.x), axis=1))
    assert len(started) and started[-1] == len(h.t) - 1  # estimates to the end, no NaN
    assert np.all(np.isfinite(h.P[started]))
    skipped = sum(h.skipped[r] for r in ("no_features", "too_few_features", "degenerate_geometry"))
    assert skipped >= (20 if case != "all_lost" else 90)


# ---- map: state (features in the state) -------------------------------------------------


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_state_map_jacobians_match_finite_differences(seed):
    """rho = r + R_LThat s (left error) and its inverse s = R_ThatL (rho - r), FD-checked."""
    from tumblenav.estimators.chang2021 import slam as S

    rng = np.random.default_rng(seed)
    x = np.zeros(13)
    x[0:4] = rot.quat_normalize(rng.normal(size=4))
    x[4:] = rng.normal(size=9)
    s = rng.normal(size=(4, 3))
    rho = rng.normal(size=(4, 3)) + [0.0, 8.0, 0.0]
    Hp, Hs = S.measurement_jacobian(x[0:4], s)
    J, Jr = S.augmentation_jacobian(x[0:4], (rho - x[7:10]) @ rot.quat_to_matrix(x[0:4]).T)
    lay = S.LAYOUT_POSE
    for i in range(4):
        h = lambda y, i=i: y[7:10] + rot.quat_to_matrix(y[0:4]).T @ s[i]  # noqa: E731
        Hn = numerical_jacobian(h, x, lay.boxplus, lambda a, b: a - b, eps=1e-6, dim=12)
        assert np.allclose(Hp[i], Hn, atol=1e-6)
        Hsn = numerical_jacobian(
            lambda v: x[7:10] + rot.quat_to_matrix(x[0:4]).T @ v, s[i], eps=1e-6
        )
        assert np.allclose(Hs, Hsn, atol=1e-6)
        g = lambda y, i=i: rot.quat_to_matrix(y[0:4]) @ (rho[i] - y[7:10])  # noqa: E731
        Jn = numerical_jacobian(g, x, lay.boxplus, lambda a, b: a - b, eps=1e-6, dim=12)
        assert np.allclose(J[i], Jn, atol=1e-6)
        Jrn = numerical_jacobian(lambda v: rot.quat_to_matrix(x[0:4]) @ (v - x[7:10]), rho[i])
        assert np.allclose(Jr, Jrn, atol=1e-6)


def test_state_map_augmentation_is_the_linearised_joint_covariance():
    """Augmenting then marginalising gives back P; the new block is J P J^T + R Sigma R^T
    with cross-covariance J P (checked by sampling the nonlinear map)."""
    from tumblenav.estimators.chang2021 import slam as S

    rng = np.random.default_rng(5)
    x = np.zeros(13)
    x[0:4] = rot.quat_normalize(rng.normal(size=4))
    x[7:10] = [0.5, 9.0, -0.3]
    na = S.NA  # the pose (12) and the inertia parameters (5) come before the features
    A = rng.normal(size=(na, na)) * 1e-3
    P = A @ A.T + 1e-6 * np.eye(na)
    rho = x[7:10] + rng.normal(size=(2, 3))
    Sig = np.tile(np.diag([1e-5, 4e-4, 1e-5]), (2, 1, 1))
    s_map, Pa = S.augment(x, P, np.zeros((0, 3)), rho, Sig)
    assert Pa.shape == (na + 6, na + 6) and np.allclose(Pa[:na, :na], P)
    assert np.all(np.linalg.eigvalsh(Pa) > 0)
    P2, _ = S._keep(Pa, s_map, np.array([False, True]))
    keep = np.r_[0:na, na + 3 : na + 6]
    assert np.allclose(P2, Pa[np.ix_(keep, keep)])
    n = 20000  # Monte Carlo of s = R_ThatL (rho - r) over the pose and rho errors
    dx = rng.multivariate_normal(np.zeros(na), P, n)
    xs = S.LAYOUT_POSE.boxplus(np.broadcast_to(x, (n, 13)), dx[:, :12])
    R = rot.quat_to_matrix(xs[:, 0:4])
    r0 = rho[0] + rng.multivariate_normal(np.zeros(3), Sig[0], n)
    s0 = np.einsum("nij,nj->ni", R, r0 - xs[:, 7:10])
    C = np.cov(np.hstack([dx, s0]).T)
    ref = Pa[np.ix_(np.r_[0 : na + 3], np.r_[0 : na + 3])]
    assert np.allclose(C, ref, atol=0.05 * np.abs(ref).max())


def test_state_map_mass_centre_converges_with_a_sane_nees():
    """A seeded 70 s run on point tracks: the mass centre (0.3-0.7 m off at the start) ends
    within a few cm, within its covariance; map 'registered' (Chang as printed) stays off."""
    sc = _scenario(70.0, **{"estimator.tuning": {"init_frames": 50}})
    truth, meas = simulate(sc, 11)
    h = get("ekf-pose").run(context_from_scenario(sc), meas, np.random.default_rng(11))
    assert h.info["map"] == "state" and not h.info["diverged"]
    dx = h.layout.boxminus(truth_state(truth, h), h.x)
    late = h.t >= 55.0
    e_pos = dx[late][:, h.layout.err("position")]
    assert np.sqrt((e_pos**2).mean(axis=0)).max() < 0.05
    nees = np.einsum("ni,nij,nj->n", dx[late], np.linalg.inv(h.P[late]), dx[late]) / 12
    assert nees.mean() < 8.0  # chi2(12)/12: 1; the FEJ filter measured ~2-3 here
    nis = h.nis[late] / h.nis_dof[late]
    assert 0.7 < np.nanmean(nis) < 1.5
    sc2 = sc.with_updates(**{"estimator.tuning": {"init_frames": 50, "map": "registered"}})
    h2 = get("ekf-pose").run(context_from_scenario(sc2), meas, np.random.default_rng(11))
    dx2 = h2.layout.boxminus(truth_state(truth, h2), h2.x)
    e2 = dx2[late][:, h2.layout.err("position")]
    assert np.sqrt((e2**2).mean(axis=0)).max() > 2 * np.sqrt((e_pos**2).mean(axis=0)).max()


def test_state_map_says_diverged_when_the_data_stop_fitting():
    """A belief whose attitude is knocked 30 deg off mid-run: the prediction explains none of
    the map's features, no update is made on them, and after divergence_epochs wild epochs
    the step says diverged (the fold then stops the run)."""
    from dataclasses import replace

    from tumblenav.estimators.chang2021.slam import StateSteps
    from tumblenav.estimators.chang2021.tuning import PoseTuning

    sc = _scenario(40.0)
    _, meas = simulate(sc, 4)
    tun = PoseTuning(init_frames=20, divergence_epochs=5)
    steps = StateSteps(meas=meas, tun=tun, n_orbit=sc.chaser.orbit.mean_motion_rad_s)
    b, _ = steps.initialise(19)
    assert b is not None
    for k in range(20, 60):
        b, info = steps.update(steps.predict(b, float(meas.t[k])), k, False)
        assert not info.diverged
    b = replace(b, x=b.layout.boxplus(b.x, np.r_[np.radians([30.0, 0.0, 0.0]), np.zeros(9)]))
    wild = []
    for k in range(60, 70):
        b, info = steps.update(steps.predict(b, float(meas.t[k])), k, False)
        wild.append(info.skipped.get("wild_epoch", 0))
        if info.diverged:
            break
    assert info.diverged and k == 64 and wild == [1] * 5


def test_increment_check_passes_the_truth_and_fails_a_wrong_rate():
    """The independent divergence check (q-method increment of the raw tracks between two
    epochs vs the filter's): the true attitudes pass its gate at every lag; attitudes that
    rotate 2 deg/s too fast are flagged after 5 s (10 deg against the q-method's spread and a
    1 deg floor)."""
    from scipy.stats import chi2

    from tumblenav.estimators.chang2021.slam import increment_check

    sc = _scenario(40.0)
    truth, meas = simulate(sc, 5)
    tr = feature_tracks(meas)
    R_TL = np.swapaxes(truth.R_LT, -1, -2)
    q_TL = np.array([rot.matrix_to_quat(R) for R in R_TL])
    P = np.tile(1e-8 * np.eye(3), (len(q_TL), 1, 1))
    gate = chi2.ppf(0.9999, 3)
    d2 = [
        increment_check(tr, a, a + lag, q_TL[a], P[a], q_TL[a + lag], P[a + lag], 0.0)
        for lag in (5, 25)
        for a in range(10, 150, 7)
    ]
    assert all(d is not None and d < gate for d in d2)
    bad = rot.quat_multiply(rot.exp_quat(np.radians([10.0, 0.0, 0.0])), q_TL[125])  # 2 deg/s
    d_bad = increment_check(tr, 100, 125, q_TL[100], P[100], bad, P[125], np.radians(1.0))
    assert d_bad is not None and d_bad > 2 * gate


def test_state_map_divergence_check_says_diverged():
    """The wiring of the increment check in the filter: an untouched run fails no check; the
    same run with the last check epoch's attitude knocked 10 deg (as if the filter had since
    turned 10 deg more than the target) fails the next check and, with check_fails 1, says
    diverged there (the wild-epoch stop off: divergence_epochs huge)."""
    from dataclasses import replace

    from tumblenav.estimators.chang2021.slam import StateSteps
    from tumblenav.estimators.chang2021.tuning import PoseTuning

    sc = _scenario(40.0)
    _, meas = simulate(sc, 4)
    tun = PoseTuning(init_frames=20, divergence_epochs=10_000, check_lag_frames=10, check_fails=1)
    steps = StateSteps(meas=meas, tun=tun, n_orbit=sc.chaser.orbit.mean_motion_rad_s)
    b, _ = steps.initialise(19)
    assert b is not None
    fails = 0
    for k in range(20, 80):
        b, info = steps.update(steps.predict(b, float(meas.t[k])), k, False)
        fails += info.skipped.get("failed_checks", 0)
        assert not info.diverged
        if k == 39:
            b40 = b
    assert fails == 0 and b40.memo.check[0] == 39
    ka, qa, Pa = b40.memo.check
    qa = rot.quat_multiply(rot.exp_quat(np.radians([0.0, 10.0, 0.0])), qa)
    b = replace(b40, memo=replace(b40.memo, check=(ka, qa, Pa)))
    for k in range(40, 80):
        b, info = steps.update(steps.predict(b, float(meas.t[k])), k, False)
        if info.diverged:
            break
    assert info.diverged and info.skipped.get("failed_checks") == 1 and k == 49


def test_says_when_one_epochs_features_cannot_fix_the_attitude():
    """At Chang's printed 59 m (the built-in chang2021, on point tracks) one epoch's features
    fix the attitude to ~17 deg about the axes across the line of sight (~1 m of depth noise
    per feature on a 2 m target): the run says so in info['warnings'] (the filter's covariance
    cannot cover the drift there and the divergence check cannot see it); at ~10 m
    (chang2021_close) it is ~0.5 deg and the run says nothing. Both checked against the value
    at the frame epoch, and the value against a Monte Carlo of the depth noise below."""
    from tumblenav.estimators.chang2021.qmethod import epoch_attitude_sigma

    est = get("ekf-pose")
    sig = {}
    for name in ("chang2021", "chang2021_close"):
        sc = load_scenario(name).with_updates(
            **{"sensor.images": None, "duration_s": 24.0, "steady_state_window_s": [0.0, 24.0]}
        )
        _, meas = simulate(sc, 3)
        hist = est.run(context_from_scenario(sc), meas, np.random.default_rng(3))
        sig[name] = hist.info["epoch_attitude_sigma_deg"]
        tr = feature_tracks(meas)
        k = hist.info["frame_epoch"]
        one = np.degrees(epoch_attitude_sigma(tr.p[k, tr.ok_p[k]], tr.P[k, tr.ok_p[k]]))
        assert 0.5 * one < sig[name] < 2.0 * one  # the window's median near its first epoch's
        warned = any("fix the attitude" in w for w in hist.info.get("warnings", []))
        assert warned == (name == "chang2021")
    assert sig["chang2021"] > 10.0 and sig["chang2021_close"] < 1.0


def test_epoch_attitude_sigma_matches_a_monte_carlo_of_depth_noise():
    """The formula against what it describes: points on a 2 m square across the line of sight
    at 50 m, each measured with 0.3 m of depth noise; a least-squares turn about the axes
    across the line of sight (the only unknowns; depth residual = (dtheta x d) . los) from
    each of 4000 draws has the spread the formula gives (within 5 %)."""
    from tumblenav.estimators.chang2021.qmethod import epoch_attitude_sigma

    rng = np.random.default_rng(11)
    d = np.column_stack([np.zeros(40), rng.uniform(-1, 1, 40), rng.uniform(-1, 1, 40)])
    p = d + np.array([50.0, 0.0, 0.0])  # line of sight along x
    P = np.tile(np.diag([0.3**2, 1e-8, 1e-8]), (40, 1, 1))
    sig = epoch_attitude_sigma(p, P)
    los = np.array([1.0, 0.0, 0.0])
    A = np.column_stack([np.cross(e, d) @ los for e in np.eye(3)[1:]])  # d(depth)/d(theta_y,z)
    noise = rng.normal(0.0, 0.3, (4000, 40))
    th = np.linalg.lstsq(A, noise.T, rcond=None)[0]  # (2, 4000)
    rms = float(np.sqrt(np.mean(th**2)))
    assert abs(rms / sig - 1.0) < 0.05


def test_noise_at_the_predicted_point_does_not_lean_to_points_measured_near():
    # One point at 20 m seen 40 000 times with 0.5 px noise (chang_range20's rig): weighting
    # each triangulated point by its covariance at the measured point (Sigma ~ depth^4) pulls
    # the weighted mean towards the camera by ~4 sigma_y^2 / y; weighted at a fixed point
    # (the filter's prediction) the mean keeps only the triangulation's own second-order bias
    # (+sigma_y^2 / y, away from the camera).
    from tumblenav.estimators.chang2021.measurements import point_covariance
    from tumblenav.frontends.triangulation import triangulate_two_ray

    sc = load_scenario("docs/results/scenarios/consistency/chang_range20.yaml").with_updates(
        duration_s=1.0, steady_state_window_s=[0.0, 1.0]
    )
    _, meas = simulate(sc, 0)
    rig = meas.rig
    cams = rig.cameras
    p_true = np.array([0.3, 20.0, -0.2])  # in C (depth along y)
    uv = []
    for c in cams:
        pk = c.R_CkC @ (p_true - c.p_CkinC)
        uv.append(c.focal_px * pk[[0, 2]] / pk[1] + np.asarray(c.principal_point_px))
    rng = np.random.default_rng(7)
    n, s = 40000, 0.5
    uvl = uv[0] + s * rng.standard_normal((n, 2))
    uvr = uv[1] + s * rng.standard_normal((n, 2))
    f = np.array([c.focal_px for c in cams])
    pp = np.array([c.principal_point_px for c in cams], float)
    p = triangulate_two_ray(
        uvl, uvr, f, pp, cams[0].R_CkC, cams[0].p_CkinC, cams[1].R_CkC, cams[1].p_CkinC
    )
    q = rot.IDENTITY  # L = C
    P_meas = point_covariance(p, q, rig, s**2)
    P_pred = point_covariance(np.tile(p_true, (n, 1)), q, rig, s**2)
    sig_y2 = float(P_pred[0, 1, 1])

    def weighted_mean(P):
        W = np.linalg.inv(P)
        return np.linalg.solve(W.sum(0), np.einsum("nij,nj->i", W, p))

    bias_meas = weighted_mean(P_meas)[1] - p_true[1]
    bias_pred = weighted_mean(P_pred)[1] - p_true[1]
    se = np.sqrt(sig_y2 / n)  # the mean's own noise
    assert bias_meas < -2.0 * sig_y2 / p_true[1] and bias_meas < -5 * se
    assert abs(bias_pred - sig_y2 / p_true[1]) < 4 * se


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-1, 1), min_size=4, max_size=4),
    st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3),
    st.lists(st.floats(-0.4, 0.4), min_size=5, max_size=5),
)
def test_euler_inertia_jacobian_against_finite_differences(q, w, j):
    from tumblenav.estimators.chang2021 import slam as S

    q = np.asarray(q) + np.array([1.5, 0.0, 0.0, 0.0])
    q = rot.quat_normalize(q)
    w, j, n = np.asarray(w), np.asarray(j), 1.1e-3
    if np.linalg.eigvalsh(S.inertia_of(j))[0] < 0.1:
        return  # not a body's inertia
    A = S.euler_inertia_jacobian(q, w, j, n)
    N = np.zeros((3, 5))
    for p in range(5):
        e = np.zeros(5)
        e[p] = 1e-6
        hi = M.rate_derivative(q, w, S.inertia_of(j + e), n)
        lo = M.rate_derivative(q, w, S.inertia_of(j - e), n)
        N[:, p] = (hi - lo) / 2e-6
    np.testing.assert_allclose(A, N, atol=1e-8 + 1e-5 * np.abs(N).max())


def test_inertia_parameters_round_trip_and_stay_a_body():
    from tumblenav.estimators.chang2021 import slam as S

    rng = np.random.default_rng(3)
    for _ in range(20):
        Rq = rot.quat_to_matrix(rot.quat_normalize(rng.normal(size=4)))
        J = Rq @ np.diag(rng.uniform(0.5, 2.0, 3)) @ Rq.T
        j = S.inertia_params(J)
        np.testing.assert_allclose(S.inertia_of(j), 3.0 * J / np.trace(J), atol=1e-12)
    # an update that pushes a moment negative is brought back to a body's
    bad = S.inertia_of(np.array([1.5, 0.2, 0.0, 0.0, 0.0]))  # moments 2.5, 1.2, -0.7
    ev = np.linalg.eigvalsh(S.inertia_of(S.inertia_params(bad)))
    assert ev.min() >= S._J_MIN * ev.mean() * (1 - 1e-6)


def test_estimated_inertia_learns_the_nutation():
    # chang_inertia (moments 150/110/90, a strong nutation), 60 s of point tracks: the
    # estimated tensor's principal ratios approach the truth's (1, 0.733, 0.6) from the sphere
    # start, and the rate's NEES is near 1 (with inertia 'sphere' the nutation is a random
    # walk to the filter: NEES/dof 0.3-0.4 on the rate)
    sc = load_scenario("docs/results/scenarios/consistency/chang_inertia.yaml").with_updates(
        duration_s=60.0, steady_state_window_s=[40.0, 60.0]
    )
    truth, meas = simulate(sc, 3)
    h = get("ekf-pose").run(context_from_scenario(sc), meas, np.random.default_rng(3))
    ratios = np.array(h.info["inertia_principal_ratios"])
    true = np.array([1.0, 110 / 150, 90 / 150])
    # measured 1, 0.875, 0.634 at 60 s (the sphere's error 0.48, the estimate's 0.145)
    assert np.linalg.norm(ratios - true) < 0.5 * np.linalg.norm(1.0 - true)
    dx = h.layout.boxminus(truth_state(truth, h), h.x)
    late = np.flatnonzero(h.t >= 40.0)
    ix = np.arange(12)[h.layout.err("rate")]
    nees = [dx[k, ix] @ np.linalg.solve(h.P[k][np.ix_(ix, ix)], dx[k, ix]) / 3 for k in late]
    assert 0.4 < np.mean(nees) < 2.5


def test_tracked_sightings_are_weighted_by_the_tracks_stated_noise():
    """A tracker that states its tracked sightings' noise apart from the first sightings'
    (``track_noise_px``, as the image front end's affine refinement does): ekf-pose updates at
    it and augments at ``noise_px``. Point tracks at 0.2 px: stated as 0.5 px throughout, the
    innovations are ~(0.2/0.5)^2 of their predicted variance; with the tracked 0.2 px stated,
    near 1 and the state consistent; ``track_noise_px`` equal to ``noise_px`` changes nothing."""
    sc = _scenario(30.0, **{"sensor.noise.pixels": 0.2, "estimator.tuning": {"init_frames": 50}})
    truth, meas = simulate(sc, 5)
    ctx = context_from_scenario(sc)

    def run(**kw):
        m = dataclasses.replace(meas, **kw)
        h = get("ekf-pose").run(ctx, m, np.random.default_rng(5))
        late = h.t >= 18.0
        dx = h.layout.boxminus(truth_state(truth, h), h.x)[late]
        nees = np.einsum("ni,nij,nj->n", dx, np.linalg.inv(h.P[late]), dx).mean() / dx.shape[1]
        return h, h.nis[late].sum() / h.nis_dof[late].sum(), nees

    h_all, nis_all, _ = run(noise_px=0.5)
    h_same, _, _ = run(noise_px=0.5, track_noise_px=0.5)
    np.testing.assert_array_equal(h_same.x, h_all.x)
    np.testing.assert_array_equal(h_same.P, h_all.P)
    _, nis_tracked, nees_tracked = run(noise_px=0.5, track_noise_px=0.2)
    assert nis_all < 0.35
    assert 0.7 < nis_tracked < 1.4
    assert nees_tracked < 2.0


def _gauge_state(seed: int):
    """A random pose (rate ~0.1 rad/s), inertia parameters, a 5-point map, and the full F (17,
    17) of ekf-pose's propagation with the inertia estimated."""
    from tumblenav.estimators.chang2021 import slam as S

    rng = np.random.default_rng(seed)
    x = np.concatenate([rot.quat_normalize(rng.normal(size=4)), 0.1 * rng.normal(size=3)])
    x = np.concatenate([x, rng.normal(size=3) * 20.0, 0.01 * rng.normal(size=3)])
    j = 0.2 * rng.uniform(-1, 1, 5)
    s = rng.uniform(-1.0, 1.0, (5, 3))
    J = S.inertia_of(j)
    x16 = np.concatenate([x, np.zeros(3)])
    F = np.zeros((S.NA, S.NA))
    F[: S.NP, : S.NP] = M.error_jacobian(x16, J, 1.1e-3)[: S.NP, : S.NP]
    F[3:6, S.NA - 5 : S.NA] = S.euler_inertia_jacobian(x[0:4], x[4:7], j, 1.1e-3)
    return x, j, s, J, F


@pytest.mark.parametrize("seed", range(4))
def test_a_rotation_of_the_body_frame_is_a_symmetry_of_the_error_dynamics(seed):
    """``F N = dN/dt`` along the gauge direction (``invariant_errors`` rests on it): the
    linearised dynamics carry a rotation of That, with the rate and inertia turned along, into
    the same rotation; and no measurement sees it (``H N = 0`` at the current map)."""
    from tumblenav.estimators.chang2021 import slam as S

    x, j, s, J, F = _gauge_state(seed)
    N = S.gauge_direction(x, j, np.zeros((0, 3)))
    Ndot = np.zeros_like(N)
    Ndot[3:6] = -rot.skew(M.rate_derivative(x[0:4], x[4:7], J, 1.1e-3))
    np.testing.assert_allclose(F @ N, Ndot, atol=1e-14)
    Hp, R_LT = S.measurement_jacobian(x[0:4], s)
    Nf = S.gauge_direction(x, j, s)
    HN = Hp @ Nf[: S.NP] + R_LT @ Nf[S.NA :].reshape(5, 3, 3)
    np.testing.assert_allclose(HN, 0.0, atol=1e-14)


@pytest.mark.parametrize("seed", range(4))
def test_a_shift_of_the_map_against_the_mass_centre_is_unseen_by_one_epoch(seed):
    """``shift_direction`` (the twentieth session's start covariance adds the fit's absorbed
    shift along it): a shift of every map point in That with the mass centre moved against
    it leaves one epoch's measurements unchanged (``H N = 0``), and its velocity column is
    the rate of change of ``-R_LThat delta`` (central differences of the attitude, 1 ms)."""
    from tumblenav.estimators.chang2021 import slam as S

    x, j, s, J, F = _gauge_state(seed)
    Ns = S.shift_direction(x, s)
    Hp, R_LT = S.measurement_jacobian(x[0:4], s)
    HN = Hp @ Ns[: S.NP] + R_LT @ Ns[S.NA :].reshape(5, 3, 3)
    np.testing.assert_allclose(HN, 0.0, atol=1e-14)
    h = 1e-3
    R_LT0 = rot.quat_to_matrix(x[0:4]).T
    dR = (R_LT0 @ rot.exp_map(x[4:7] * h) - R_LT0 @ rot.exp_map(-x[4:7] * h)) / (2 * h)
    np.testing.assert_allclose(Ns[9:12], -dR, atol=1e-8)


@pytest.mark.parametrize("seed", range(4))
def test_gauge_aligned_propagation_keeps_the_gauge_exactly(seed):
    """One 0.2 s step: ``gauge_discretise``'s ``Phi`` takes the gauge direction at the step's
    start to the one at its end to rounding; the plain ``expm(F dt)`` misses it (the leak
    that made ekf-pose's attitude confident while it drifted, by ~1e-4 here)."""
    from tumblenav.dynamics.integrators import discretise
    from tumblenav.estimators.chang2021 import slam as S

    x, j, s, J, F = _gauge_state(seed)
    dt = 0.2
    x16 = np.concatenate([x, np.zeros(3)])
    xb = M.propagate_mean(x16, dt, J, 1.1e-3)
    wdot = M.rate_derivative(x[0:4], x[4:7], J, 1.1e-3)
    Qc = np.zeros((S.NA, S.NA))
    Phi, _ = S.gauge_discretise(F, Qc, dt, (x[4:7], wdot, xb[4:7]), J)
    Na = S.gauge_direction(x, j, np.zeros((0, 3)))
    Nb = S.gauge_direction(xb, j, np.zeros((0, 3)))
    np.testing.assert_allclose(Phi @ Na, Nb, atol=1e-12)
    Phi_plain, _ = discretise(F, Qc, dt)
    assert np.abs(Phi_plain @ Na - Nb).max() > 1e-6


def test_regauge_carries_the_gauge_to_the_updated_estimate():
    """A covariance wholly along the gauge direction at the prior estimate is, after
    ``regauge`` to an updated estimate (rate, inertia, map moved), wholly along the gauge
    direction there; its other directions keep their variance."""
    from tumblenav.estimators.chang2021 import slam as S

    x, j, s, _, _ = _gauge_state(7)
    rng = np.random.default_rng(8)
    xa = x.copy()
    xa[4:7] += 0.01 * rng.normal(size=3)
    ja = j + 0.01 * rng.normal(size=5)
    sa = s + 0.05 * rng.normal(size=s.shape)
    Nb, Na = S.gauge_direction(x, j, s), S.gauge_direction(xa, ja, sa)
    P = Nb @ Nb.T
    np.testing.assert_allclose(S.regauge(P, (x, j, s), (xa, ja, sa), True), Na @ Na.T, atol=1e-12)
    # any covariance: A P A^T with A = T(after)^-1 T(before), T built in full (features too)
    G = rng.normal(size=(len(P), len(P)))
    Q = G @ G.T

    def T_full(x, j, s):
        T = np.eye(len(P))
        T[: S.NA, : S.NA] = S.gauge_transform(x[4:7], S.inertia_of(j))
        T[S.NA :, :3] = rot.skew(s).reshape(-1, 3)
        return T

    A = np.linalg.solve(T_full(xa, ja, sa), T_full(x, j, s))
    np.testing.assert_allclose(
        S.regauge(Q, (x, j, s), (xa, ja, sa), True), A @ Q @ A.T, rtol=1e-10, atol=1e-10
    )


def test_batch_trajectories_are_the_filters_propagation():
    """The batch start's compiled propagation (a stack of initial rates and inertias at once)
    is ekf-pose's own (model.propagate_mean, step by step) to rounding."""
    from tumblenav.estimators.chang2021 import batch as B
    from tumblenav.estimators.chang2021 import slam as S

    rng = np.random.default_rng(0)
    w0 = 0.1 * rng.normal(size=(3, 3))
    j = 0.2 * rng.uniform(-1, 1, (3, 5))
    t = np.cumsum(np.r_[0.0, 0.2 + 0.01 * rng.random(50)])
    R, W = B._trajectories(w0, j, t, 1.1e-3)
    for b in range(3):
        x = np.zeros(16)
        x[3], x[4:7] = 1.0, w0[b]
        for k in range(1, len(t)):
            x = M.propagate_mean(x, t[k] - t[k - 1], S.inertia_of(j[b]), 1.1e-3)
            np.testing.assert_allclose(R[b, k], rot.quat_to_matrix(x[0:4]), atol=1e-13)
            np.testing.assert_allclose(W[b, k], x[4:7], atol=1e-15)


def _synthetic_window(seed: int, n: float = 1.1e-3):
    """Tracks of a torque-free tumble (the filter's model exactly), 60 frames at 5 Hz, 25
    points in a 2 m cube at ~9 m seen over random stretches, with a depth noise 20 times the
    lateral (a long range's triangulation): tracks, times, and the truth (rate and inertia
    parameters at k0, mass centre and velocity at k0, the points)."""
    from tumblenav.dynamics.relative_orbit import cw_stm
    from tumblenav.estimators.chang2021 import batch as B
    from tumblenav.estimators.chang2021.measurements import FeatureTracks

    rng = np.random.default_rng(seed)
    K, N = 60, 25
    t = 0.2 * np.arange(K)
    w0 = np.array([0.05, -0.06, 0.04])
    j = 0.05 * rng.normal(size=5)  # drawn from the fit's prior
    rv0 = np.array([-8.0, 4.0, -3.0, 0.01, -0.005, 0.002])
    s = rng.uniform(-1.0, 1.0, (N, 3))
    R, _ = B._trajectories(w0[None], j[None], t, n)
    r = np.stack([cw_stm(n, tk)[:3] @ rv0 for tk in t])
    u = rv0[:3] / np.linalg.norm(rv0[:3])
    Sig = 0.005**2 * np.eye(3) + (0.1**2 - 0.005**2) * np.outer(u, u)
    ok = np.zeros((K, N), bool)
    for i in range(N):
        a = 0 if i < 12 else int(rng.integers(0, K - 10))
        ok[a : min(K, a + int(rng.integers(10, K + 1))), i] = True
    p = np.full((K, N, 3), np.nan)
    noise = rng.multivariate_normal(np.zeros(3), Sig, size=(K, N))
    p_true = r[:, None, :] + np.einsum("kji,nj->kni", R[0], s)
    p[ok] = (p_true + noise)[ok]
    P = np.broadcast_to(Sig, (K, N, 3, 3)).copy()
    tracks = FeatureTracks(p, P, np.full_like(p, np.nan), P.copy(), ok, np.zeros_like(ok))
    return tracks, t, (w0, j, rv0, s, R[0])


def _synthetic_batch_fit(seed: int, n: float):
    """The batch fit of :func:`_synthetic_window` ``seed`` from a rate 70 deg off the truth's
    direction and a mass centre 0.3 m off, and its end state's error (17: attitude (left, in
    That), rate, position and velocity, inertia); also
    docs/results/consistency/prototype/chang_batch_start.py's."""
    from tumblenav.dynamics.relative_orbit import cw_stm
    from tumblenav.estimators.chang2021 import batch as B

    tracks, t, (w0, j, rv0, s, R) = _synthetic_window(seed, n)
    guess = rot.exp_map(np.radians(70.0) * np.array([0.0, 0.6, 0.8])) @ w0
    fit = B.fit_window(
        tracks, t, 0, len(t) - 1, guess, rv0 + np.r_[0.3, -0.3, 0.3, 0, 0, 0], n,
        estimate_inertia=True, inertia_sigma=0.05, centre_sigma=0.5, noise_scale=1.0,
        first_noise_scale=1.0, gate_probability=0.9999, max_features=120,
    )  # fmt: skip
    assert fit is not None
    _, W = B._trajectories(w0[None], j[None], t, n)
    e = np.concatenate(
        [
            rot.log_map(R[-1] @ rot.quat_to_matrix(fit.x[0:4]).T),  # left error in That
            W[0, -1] - fit.x[4:7],
            cw_stm(n, t[-1]) @ rv0 - fit.x[7:13],
            j - fit.j,
        ]
    )
    return fit, e


def test_batch_start_recovers_a_window_within_its_covariance():
    """The batch start (slam's start_fit 'batch') on synthetic windows whose motion is the
    filter's model: from a rate 70 deg off the truth's direction and a mass centre 0.3 m off,
    the fit's end state (attitude, position, velocity, inertia: 14 dof; the rate follows) has
    a mean NEES/dof inside its 99 % chi-square interval over 6 windows, and its cost per
    residual is near 1 (the noise as stated)."""
    from scipy.stats import chi2

    n = 1.1e-3
    nees, costs = [], []
    for seed in range(6):
        fit, e = _synthetic_batch_fit(seed, n)
        # the motion is deterministic: the end attitude and rate are functions of the rate
        # and inertia at k0, so the 17 end errors span 14 dimensions (the filter adds the
        # window's process noise); the NEES is taken on attitude, position, velocity, inertia
        sel = np.r_[0:3, 6:17]
        nees.append(e[sel] @ np.linalg.solve(fit.P[np.ix_(sel, sel)], e[sel]) / 14)
        sig_w = np.sqrt(np.diag(fit.P[3:6, 3:6]))
        assert np.all(np.abs(e[3:6]) < 4 * sig_w + 1e-12)
        costs.append(fit.cost / fit.dof)
    lo, hi = chi2.ppf([0.005, 0.995], 6 * 14) / (6 * 14)
    assert lo < np.mean(nees) < hi, nees
    assert max(nees) < 3.0, nees
    assert 0.85 < np.mean(costs) < 1.15, costs


def test_batch_start_covers_its_error_at_chang_s_printed_range():
    """Chang's printed 59 m on point tracks (one epoch fixes the attitude to ~15 deg across the
    line of sight), run 2 of the montecarlo seeds: the replay start ends 4.7 / 1.4 / -6.3 deg
    off per axis at a 1-sigma of 0.10 / 0.09 / 0.12 deg; the batch start (the default) within 3
    sigma of the truth on each axis (measured -0.05 / -0.07 / 0.09 deg at 0.15 / 0.10 / 0.18,
    the window's Q included)."""
    from tumblenav.campaign.store import run_seed

    sc = load_scenario("chang2021").with_updates(
        **{"sensor.images": None, "duration_s": 24.0, "steady_state_window_s": [0.0, 24.0]}
    )
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, 2))
    h = get("ekf-pose").run(context_from_scenario(sc), meas, np.random.default_rng(0))
    k = int(h.info["start_epoch"])
    assert h.info["start_fit"] == "batch"
    dx = h.layout.boxminus(truth_state(truth, h)[k], h.x[k])
    sig = np.sqrt(np.diag(h.P[k]))
    att = h.layout.err("attitude")
    assert np.all(np.abs(dx[att]) < 3 * sig[att]), (dx[att], sig[att])


def test_batch_start_mass_centre_unbiased_at_range():
    """Chang's printed 59 m on point tracks, runs 0-3 of the montecarlo seeds: the batch start
    weights each sighting at its predicted point (noise_at 'predicted', as the updates), and
    its mass centre then lies within its covariance (position NEES/dof at the start, mean over
    the runs, measured 0.86); weighted at the measured points (noise_at 'measured', the
    eighteenth session's batch for every setting) the triangulation covariance's depth^4
    leans it towards the camera (measured 16.0 over the same runs; 8.4 at 40 m, 8 runs,
    before the nineteenth session)."""
    from tumblenav.campaign.store import run_seed

    sc = load_scenario("docs/results/scenarios/consistency/chang_points59.yaml").with_updates(
        duration_s=21.0, steady_state_window_s=[0.0, 21.0]
    )
    out = {}
    for at in ("predicted", "measured"):
        sc_at = sc.with_updates(**{"estimator.tuning": {"noise_at": at}})
        nees = []
        for run in range(4):
            truth, meas = simulate(sc_at, run_seed(sc.montecarlo.seed, run))
            h = get("ekf-pose").run(context_from_scenario(sc_at), meas, np.random.default_rng(0))
            k = int(h.info["start_epoch"])
            dx = h.layout.boxminus(truth_state(truth, h)[k], h.x[k])
            pos = h.layout.err("position")
            nees.append(dx[pos] @ np.linalg.solve(h.P[k][pos, pos], dx[pos]) / 3)
        out[at] = float(np.mean(nees))
    assert out["predicted"] < 2.0, out
    assert out["measured"] > 5.0, out


def test_replay_that_departs_from_the_batch_fit_is_refused():
    """chang_range40 (40 m, truth disturbed, the fit's window noise ratio ~30; with
    ``batch_noise_ratio`` 1, as before the twentieth session, the replay runs from the fit),
    run 3 of the montecarlo seeds: the replay ends ~3 deg off at a 1-sigma of ~0.1 deg
    (measured d^2 61 against the fit); refused, the fit with the window's Q is the first
    belief and covers its error on each axis; with the gate opened the replay's start is
    taken and does not."""
    from tumblenav.campaign.store import run_seed

    sc = load_scenario("docs/results/scenarios/consistency/chang_range40.yaml").with_updates(
        duration_s=21.0, steady_state_window_s=[0.0, 21.0]
    )
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, 3))
    covered = {}
    for gate in (0.99, 1.0 - 1e-15):
        tun = {"replay_gate_probability": gate, "batch_noise_ratio": 1.0}
        sc_g = sc.with_updates(**{"estimator.tuning": tun})
        h = get("ekf-pose").run(context_from_scenario(sc_g), meas, np.random.default_rng(0))
        k = int(h.info["start_epoch"])
        dx = h.layout.boxminus(truth_state(truth, h)[k], h.x[k])
        att = h.layout.err("attitude")
        covered[h.info["start_fit"]] = bool(
            np.all(np.abs(dx[att]) < 3 * np.sqrt(np.diag(h.P[k])[att]))
        )
    assert covered == {"batch (replay refused)": True, "batch+replay": False}, covered


def test_batch_start_refuses_a_window_it_cannot_fit():
    """Fault injection: a window whose sightings fix no rotation (every sighting at one
    point) never raises; a fit, if any, says it knows nothing of the attitude (1-sigma over
    1 rad); a window without sightings gives none (ekf-pose then starts by the replay)."""
    from tumblenav.estimators.chang2021 import batch as B

    tracks, t, (w0, j, rv0, s, R) = _synthetic_window(0)
    ok = tracks.ok_p
    p = tracks.p.copy()
    p[ok] = np.broadcast_to(p[ok].mean(axis=0), p[ok].shape)  # one point
    flat = dataclasses.replace(tracks, p=p)
    fit = B.fit_window(
        flat, t, 0, len(t) - 1, w0, rv0, 1.1e-3, estimate_inertia=True, inertia_sigma=0.05,
        centre_sigma=0.5, noise_scale=1.0, first_noise_scale=1.0, gate_probability=0.9999,
        max_features=120,
    )  # fmt: skip
    if fit is not None:  # a fit of a point: its covariance must still say so
        assert np.all(np.isfinite(fit.P))
        assert np.sqrt(np.linalg.eigvalsh(fit.P[:3, :3]).max()) > 1.0
    none = dataclasses.replace(tracks, ok_p=np.zeros_like(ok))
    assert B.fit_window(
        none, t, 0, len(t) - 1, w0, rv0, 1.1e-3, estimate_inertia=True, inertia_sigma=0.05,
        centre_sigma=0.5, noise_scale=1.0, first_noise_scale=1.0, gate_probability=0.9999,
        max_features=120,
    ) is None  # fmt: skip


def test_batch_start_belief_is_a_covariance_under_strong_process_noise():
    """The fit as the first belief (batch_noise_ratio large) on chang_paper (q_r 1e-8 over a
    20 s window): its covariance, the window's Q included, is positive definite (one Van Loan
    step over the window had given eigenvalues down to -1e-7, and the update's Cholesky
    failed)."""
    from tumblenav.campaign.store import run_seed
    from tumblenav.estimators.chang2021.slam import StateSteps
    from tumblenav.estimators.chang2021.tuning import PoseTuning

    sc = load_scenario("docs/results/scenarios/consistency/chang_paper.yaml")
    sc = sc.with_updates(duration_s=22.0, steady_state_window_s=[0.0, 22.0])
    _, meas = simulate(sc, run_seed(sc.montecarlo.seed, 0))
    pn = sc.process_noise
    steps = StateSteps(
        meas=meas,
        tun=PoseTuning(batch_noise_ratio=1e6),
        n_orbit=float(sc.chaser.orbit.mean_motion_rad_s),
        q_rot=float(pn.rotational_rad2_s4),
        q_trans=float(pn.translational_m2_s4),
    )
    b, _ = steps.initialise(steps.k0 + 99)
    assert b is not None and b.memo.start.fit == "batch"
    assert np.linalg.eigvalsh(b.P).min() > 0.0


def test_absorbed_walk_matches_simulated_walks():
    """``slam.absorbed_walk`` (the twentieth session's start covariance): the map's common
    rotation ``c`` and shift ``delta`` that a torque-free fit absorbs from the process noise's
    walk over a 20-s window, against 4000 simulated walks (Chang 2021 eq. 13 / 25 at a
    tumbling state, 1e-6 rad^2/s^3 and 1e-6 m^2/s^3, regressed as the function says: ``c``
    from the attitude on a line in time, ``delta`` from the mass centre on a line plus
    ``R_LThat(t) delta``). Whitened by the analytic covariance, the sample covariance is the
    identity within 0.12 (4000 samples: ~0.02 per element); a covariance that ignored the
    walk's correlation over time (only its end) is not."""
    from tumblenav.dynamics.integrators import discretise
    from tumblenav.estimators.chang2021.slam import NA, NP, absorbed_walk

    x = np.concatenate([rot.exp_quat(np.array([0.3, -0.2, 0.5])), [0.04, -0.06, 0.05]])
    x = np.concatenate([x, [10.0, -3.0, 2.0, 0.0, 0.01, 0.0]])
    J = np.diag([1.2, 1.0, 0.8])
    F = np.zeros((NA, NA))
    F[:NP, :NP] = M.error_jacobian(np.concatenate([x, np.zeros(3)]), J, 1.1e-3)[:NP, :NP]
    Qc = np.zeros((NA, NA))
    Qc[:NP, :NP] = M.process_noise_density(1e-6, 1e-6)[:NP, :NP]
    T, steps = 20.0, 20
    Phi1, Q1 = discretise(F, Qc, T / steps)
    walk = [np.zeros((NA, NA))]
    for _ in range(steps):
        walk.append(Phi1 @ walk[-1] @ Phi1.T + Q1)
    tt = np.linspace(0.0, T, steps + 1)
    G_rot, G_shift = absorbed_walk(x, tt, Phi1, walk)

    rng = np.random.default_rng(18)
    n_mc = 4000
    L1 = np.linalg.cholesky(Q1[:NP, :NP] + 1e-30 * np.eye(NP))
    dx = np.zeros((n_mc, steps + 1, NP))
    for i in range(steps):
        dx[:, i + 1] = dx[:, i] @ Phi1[:NP, :NP].T + rng.standard_normal((n_mc, NP)) @ L1.T
    X = np.stack([np.ones(steps + 1), tt], axis=1)
    c = np.einsum(
        "i,nik->nk", np.linalg.lstsq(X, np.eye(steps + 1), rcond=None)[0][0], dx[:, :, 0:3]
    )
    R_i = rot.quat_to_matrix(x[0:4]).T @ rot.exp_map(np.outer(tt - T, x[4:7]))
    Xs = np.concatenate(
        [np.tile(np.eye(3), (steps + 1, 1, 1)), tt[:, None, None] * np.eye(3), R_i], axis=2
    ).reshape(-1, 9)
    coef = np.linalg.lstsq(Xs, dx[:, :, 6:9].reshape(n_mc, -1).T, rcond=None)[0]
    delta = coef[6:9].T

    def whitened(G, samples):
        Li = np.linalg.inv(np.linalg.cholesky(G))
        return Li @ np.cov(samples.T) @ Li.T

    assert np.abs(whitened(G_rot, c) - np.eye(3)).max() < 0.12
    assert np.abs(whitened(G_shift, delta) - np.eye(3)).max() < 0.12
    # the end's covariance alone is no substitute (the fit averages the walk over the window)
    assert np.abs(whitened(walk[-1][0:3, 0:3], c) - np.eye(3)).max() > 0.3
    # a target that hardly turns over the window: the shift is not separable from the line,
    # and its covariance is capped at the end walk's (not 1.7e7 times it, uncapped)
    x_slow = x.copy()
    x_slow[4:7] = [1e-3, 0.0, 0.0]
    _, G_slow = absorbed_walk(x_slow, tt, Phi1, walk)
    top = np.linalg.eigvalsh(walk[-1][6:9, 6:9]).max()
    assert np.all(np.isfinite(G_slow)) and np.linalg.eigvalsh(G_slow).max() <= top * (1 + 1e-9)
