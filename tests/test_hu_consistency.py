"""Issue 18 for the Hu 2024 estimators: a run that loses track restarts instead of stopping,
features first seen after the start are linearised at their sighting (self-occlusion)."""

from __future__ import annotations

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import ekf_dpacf as hu
from tumblenav.estimators.hu2024.model import layout, recentre_unseen
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

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


def test_recentre_unseen_puts_the_feature_at_its_sighting():
    rng = np.random.default_rng(3)
    lay = layout(3)
    x = np.zeros(lay.nominal_dim)
    q = rot.exp_quat(rng.normal(size=3))
    x[lay.nom("attitude")] = q
    x[lay.nom("position")] = r = rng.normal(size=3) * 10
    R_LI = rot.quat_to_matrix(rot.exp_quat(rng.normal(size=3)))
    f_true = rng.normal(size=(3, 3))
    R_LT = R_LI @ rot.quat_to_matrix(q).T
    p = r + f_true @ R_LT.T
    fresh = np.array([True, False, True])
    out = recentre_unseen(x[None], R_LI[None], p[None], fresh[None], lay)[0]
    f = out[lay.nom("features")].reshape(3, 3)
    assert np.allclose(f[[0, 2]], f_true[[0, 2]], atol=1e-12)
    assert np.array_equal(f[1], np.zeros(3))  # untouched
    y, _ = hu.feature_measurement(out[None], R_LI[None], lay)
    assert np.allclose(y[0, [0, 2]], p[[0, 2]], atol=1e-12)


def _selfocc(duration: float):
    return (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(
            duration_s=duration,
            steady_state_window_s=[duration - 20.0, duration],
            **{
                "target.v0_L_m_s": [0.0, 0.0, 0.0],
                "target.features_T_m.count": 10,
                "occlusion.self_occlusion": True,
                "occlusion.windows": [],
            },
        )
    )


def test_self_occlusion_late_features_engines_agree_and_stay_on_track():
    """Self-occlusion: most features appear after the start. Both engines re-centre them
    alike; run 4 (seed 2024), which diverged at ~45 s when a late feature's first-estimates
    Jacobian stayed at the placeholder 0, now tracks with an honest covariance."""
    s = _selfocc(90.0)
    ks = [4, 7]
    sims = [simulate(s, run_seed(2024, k)) for k in ks]
    meas = [m for _, m in sims]
    a = hu.run_filter(s, meas, True, p_every=5, engine="compiled")
    b = hu.run_filter(s, meas, True, p_every=5, engine="numpy")
    assert (a["k0"] >= 0).all() and not a["diverged"].any() and not b["diverged"].any()
    assert a["reinit_epochs"] == [[], []] == b["reinit_epochs"]
    fin = np.isfinite(b["x"])
    assert np.array_equal(np.isfinite(a["x"]), fin)
    assert np.allclose(a["x"][fin], b["x"][fin], rtol=1e-6, atol=1e-6)
    hs = hu.histories(a, s)
    from tumblenav import evaluation

    _, err = evaluation.error_states(hs, [t for t, _ in sims])
    t = a["t"]
    for i in range(len(ks)):
        kk = np.flatnonzero((t >= 60.0) & (np.arange(len(t)) % 5 == 0))
        P = a["P"][i, kk // 5]
        e = err[i, kk]
        nees = np.einsum("ki,ki->k", e, np.linalg.solve(P, e[..., None])[..., 0]) / e.shape[1]
        assert np.mean(nees) < 2.0  # was 9e4 for run 4 (diverged), 0.6-1.3 for the others
        assert np.sqrt(np.mean(err[i, kk, 9:12] ** 2)) < 0.03  # position [m]


def test_baseline_restarts_after_a_long_occlusion():
    """ekf-baseline loses track when the features return after 30 s (run 2 of seed 2024
    diverged and was stopped; run 14 since the inertia least squares' covariance changed,
    stereo_points.gls, run 5 since the start gate and the unbiased early rows, issue 18:
    which run loses track is chaotic); it is now started again from the
    measurements, as at the start, and reports estimates to the end, the restart counted."""
    s = (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(
            duration_s=110.0,
            steady_state_window_s=[100.0, 110.0],
            **{"occlusion.windows": [{"start_s": 60.0, "end_s": 90.0}]},
        )
    )
    tr, m = simulate(s, run_seed(2024, 5))
    res = hu.run_filter(s, [m], False)
    assert len(res["reinit_epochs"][0]) >= 1
    assert res["t"][res["reinit_epochs"][0][0]] >= 90.0  # after the features came back
    assert not res["diverged"][0]
    assert np.isfinite(res["x"][0, -1]).all()
    h = hu.histories(res, s)[0]
    assert h.skipped["reinitialised"] == len(res["reinit_epochs"][0])
    assert h.info["reinit_times_s"][0] >= 90.0


def test_nis_alarm_flags_innovations_that_do_not_fit():
    from tumblenav.estimators.hu2024.filter import nis_alarm

    rng = np.random.default_rng(5)
    t = np.arange(2000) * 0.1
    dof = np.full(2000, 12)
    nis = rng.chisquare(12, size=2000)
    assert nis_alarm(t, nis, dof).sum() == 0  # honest innovations: no alarm
    nis[1000:1200] *= 3.0  # the filter lost track for 20 s
    a = nis_alarm(t, nis, dof)
    assert a[1050:1200].all() and not a[:1000].any() and not a[1300:].any()
    dof[:10] = 0  # no update: no window, no alarm
    assert not nis_alarm(t, np.full(2000, np.nan), np.zeros(2000)).any()


def test_start_covariance_is_positive_definite_at_1e6_rad():
    """hu2024 at 1e-6 rad (the paper's lowest noise), run 231 of seed 2024: the joint start
    holds the mass centre to centimetres and the shape to micrometres; assembled from its
    parts, its covariance had an eigenvalue at -2.6e-10 (correlation), which the precise
    updates grew until the filter broke (NIS < 0) and kept the mass centre 0.1 m off at a
    1-sigma of 1 mm (NEES/dof 3e4). init.positive_definite floors it (issue 18)."""
    from threadpoolctl import threadpool_limits

    from tumblenav.estimators.hu2024.init import positive_definite

    s = (
        load_scenario("hu2024")
        .with_updates(**HU2024_PAPER)
        .with_updates(
            **{"sensor.noise.angular_rad": 1e-6},
            duration_s=60.0,
            steady_state_window_s=[45.0, 60.0],
        )
    )
    with threadpool_limits(limits=1, user_api="blas"):  # the failing run's round-off
        tr, m = simulate(s, run_seed(2024, 231))
        res = hu.run_filter(s, [m], True, p_every=1)
    k0 = int(res["k0"][0])
    P = res["P"][0, k0]
    sd = np.sqrt(np.diag(P))
    assert np.linalg.eigvalsh(P / np.outer(sd, sd))[0] > 0
    assert not res["diverged"][0]
    assert np.all(res["nis"][0][np.isfinite(res["nis"][0])] >= 0)
    from tumblenav import evaluation

    _, err = evaluation.error_states(hu.histories(res, s), [tr])
    t = res["t"]
    kk = np.flatnonzero(t >= 45.0)
    e, Pw = err[0, kk, 9:12], res["P"][0, kk][:, 9:12, 9:12]
    nees = np.einsum("ki,ki->k", e, np.linalg.solve(Pw, e[..., None])[..., 0]) / 3
    assert np.mean(nees) < 3.0  # 3e4 before the floor
    # the floor: a positive definite P is returned as is, an indefinite one raised
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    Q = A @ A.T + np.eye(6)
    assert positive_definite(Q) is Q
    V = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    bad = (V * np.array([-1e-9, 1e-3, 1, 2, 3, 4])) @ V.T
    fixed = positive_definite(bad)
    sd = np.sqrt(np.diag(fixed))
    assert np.linalg.eigvalsh(fixed / np.outer(sd, sd))[0] >= 1e-10 * (1 - 1e-6)
    assert np.allclose(fixed, bad, atol=1e-8)
    assert positive_definite(np.zeros((3, 3))).shape == (3, 3)  # nothing to floor


def test_least_squares_torque_follows_the_scenario(monkeypatch):
    """ls_torque_rad2_s4 'auto' (the default): the inertia least squares allows for the
    filter's sigma_r^2 where the scenario states that its process noise is a real
    disturbance (process_noise.disturb_truth), and is torque-free (Hu 2024 eq. 10)
    otherwise; an explicit value or 'process_noise' wins. Twenty-fifth session: with the
    torque-free least squares on a disturbed target nobody tuned for, the frame's covariance
    was over-confident (attitude block NEES/dof 28 over 4 runs, 0.94 with the torque)."""
    from tumblenav.estimators.hu2024 import filter as F
    from tumblenav.frontends import stereo_points

    seen = []

    def fake_process(meas_list, settings):
        seen.append(settings.q_r)
        raise RuntimeError("stop")

    monkeypatch.setattr(stereo_points, "process", fake_process)
    cases = [
        ({}, True, 3e-9),
        ({}, False, 0.0),
        ({"frontend": {"ls_torque_rad2_s4": "process_noise"}}, False, 3e-9),
        ({"frontend": {"ls_torque_rad2_s4": 1e-12}}, True, 1e-12),
        ({"frontend": {"ls_torque_rad2_s4": 0.0}}, True, 0.0),
    ]
    for tuning, disturbed, want in cases:
        tun = hu.parse_tuning(tuning)
        try:
            F.frontend([], tun, 3e-9, disturbed=disturbed)
        except RuntimeError:
            pass
        assert seen[-1] == want, (tuning, disturbed)


def test_template_features_carry_the_fits_common_shift():
    """init.template_features_cov against 4000 draws: the fitted features' errors with a
    large common shift (the fit barely places the mass centre), the templates' own 1 cm,
    and the features taken from the template, f_i = g_i - mean_fit(g_j - f_j). The stated
    covariance of all features' errors (fitted, template-taken) holds them: NEES/dof inside
    its 99.9 % bounds. Before the twenty-fifth session the template-taken features had 1 cm
    alone, independent of the fit (NEES/dof ~1e3 here)."""
    from scipy import stats

    from tumblenav.estimators.hu2024.init import TEMPLATE_VAR_M2, template_features_cov

    rng = np.random.default_rng(25)
    N, fit = 6, np.array([True, False, True, True, False, False])
    kn = np.array([True, True, True, True, True, False])
    idx = np.flatnonzero(fit)
    M = rng.normal(size=(3 * len(idx), 3 * len(idx))) * 0.004
    shift = np.kron(np.ones((len(idx), 1)), np.diag([0.5, 0.3, 0.1]))  # the common shift
    C_fit = M @ M.T + shift @ shift.T
    sel = (3 * idx[:, None] + np.arange(3)).ravel()
    C = np.zeros((3 * N, 3 * N))
    C[np.ix_(sel, sel)] = C_fit
    F = template_features_cov(C, fit, kn, 3.0)
    ok = np.repeat(kn, 3)
    Fk = F[np.ix_(ok, ok)]
    L = np.linalg.cholesky(C_fit)
    draws = 4000
    nees = np.empty(draws)
    for d in range(draws):
        df_fit = (L @ rng.normal(size=3 * len(idx))).reshape(-1, 3)
        dg = rng.normal(scale=np.sqrt(TEMPLATE_VAR_M2), size=(N, 3))
        dc = np.mean(dg[idx] - df_fit, axis=0)  # the mass centre the fit puts in G
        df = dg - dc
        df[idx] = df_fit
        e = df[kn].ravel()
        nees[d] = e @ np.linalg.solve(Fk, e) / len(e)
    dof = int(ok.sum())
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], dof * draws) / (dof * draws)
    assert lo < nees.mean() < hi
    assert np.allclose(np.diag(F)[~ok], 9.0)  # never seen: the prior


def test_dpacf_restarts_when_its_alarm_fires():
    """Fault injection: from 60 s on, every sighting of one run is moved by 20 px along u
    in both images (a target that jumped sideways, not where the filter holds it). ekf-dpacf's innovations no longer fit,
    its lost-track alarm fires, and the run starts again from the measurements after the
    alarm (restart_on_alarm, the default since the twenty-fifth session), the restart
    counted; with restart_on_alarm off it keeps its estimate and only raises the alarm."""
    s = load_scenario("hu2024").with_updates(duration_s=100.0, steady_state_window_s=[90.0, 100.0])
    _, m = simulate(s, run_seed(2024, 0))
    t = np.asarray(m.t)
    late = t >= 60.0
    m.uv[late, :, :, 0] += 20.0
    res = hu.run_filter(s, [m], True)
    assert len(res["reinit_epochs"][0]) >= 1
    assert res["t"][res["reinit_epochs"][0][0]] > 60.0
    h = hu.histories(res, s)[0]
    assert h.skipped["reinitialised"] == len(res["reinit_epochs"][0])
    off = s.with_updates(**{"estimator.tuning": s.estimator.tuning | {"restart_on_alarm": False}})
    res0 = hu.run_filter(off, [m], True)
    assert res0["reinit_epochs"][0] == []
    assert hu.histories(res0, off)[0].skipped["nis_alarm"] > 0
