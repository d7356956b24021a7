"""Checks behind docs/results/hu2024.md, Seventh and Eighth sessions: the template's
refinement and the iterated update.

* ``template``: the template's error per feature (rms after the best rotation onto the true
  features, median over runs) with the one-sighting template (``template_refine_s=0``) and
  the refined one, at each noise level (45-s runs); and the G attitude's wander about its
  mean after the refinement at a constant 17 m (60-s runs, 2e-5 rad).
* ``occlusion``: four features, 1e-5 rad, held at 17 m, run 6 of seed 2024 (the scenario of
  ``tests/test_ekf_dpacf.py::test_iterated_update_after_a_long_occlusion``), start gate
  0.03: attitude and position error and 1-sigma around the end of the 60-80 s occlusion,
  with the iterated update and without (``iterate_max=0``).

* ``schedule``: the front end alone on 20 hu2024 runs (the campaign's seeds) at 2e-5 and
  5e-5 rad, four settings: the seventh session's (``template_refine_s=30
  ls_unbiased_rates=false``), that with the unbiased rows, the eighth session's schedule
  (8, 10, 30 s) with the per-epoch rate fit throughout, and the defaults (both). The template's error per version, the
  DPACF frame's error against the true principal frame (median over the runs; a run without
  a frame counts as failing) at 8-12, 50 and 200 s, and the inertia moments' error at 200 s.

Usage: python benchmarks/hu2024_refinement_checks.py template|occlusion|schedule
Last line: ``template_error_mm=<one sighting>,<refined> (2e-5 rad) wander_deg=<...>,<...>``
or ``position_nees=<iterated>,<single>`` or ``frame_deg_10s=<per setting, 2e-5 then 5e-5>
moments_err_200s=<...>``
"""

from __future__ import annotations

import sys

import numpy as np

from tumblenav import evaluation
from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import ekf_dpacf as hu
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate


def _aligned(a, b):  # rotation R with a ~ R b about their own centroids
    U, _, Vt = np.linalg.svd((b - b.mean(0)).T @ (a - a.mean(0)))
    return Vt.T @ np.diag([1, 1, np.linalg.det(Vt.T @ U.T)]) @ U.T


def template() -> None:
    last = None
    for noise in (1e-6, 5e-6, 2e-5):
        s = load_scenario("hu2024").with_updates(
            duration_s=45.0, steady_state_window_s=[40.0, 45.0],
            **{"sensor.noise.angular_rad": noise},
        )  # fmt: skip
        sims = [simulate(s, run_seed(3, k)) for k in range(6)]
        out = []
        for v in (0.0, 30.0):
            fe = hu.frontend([m for _, m in sims], hu.parse_tuning({"template_refine_s": v}))
            r = []
            for b, (truth, _) in enumerate(sims):
                kn = fe.known[b]
                g, f = fe.template_G[b][kn], truth.features_T[kn]
                e = (g - g.mean(0)) - (f - f.mean(0)) @ _aligned(g, f).T
                r.append(np.sqrt(np.mean(np.sum(e**2, axis=1))))
            out.append(1e3 * np.median(r))
        print(f"{noise:g} rad: template error per feature {out[0]:.3f} mm (one sighting), "
              f"{out[1]:.3f} mm (refined), median of 6 runs")  # fmt: skip
        last = out
    s = load_scenario("hu2024").with_updates(
        duration_s=60.0, steady_state_window_s=[50.0, 60.0], **{"target.v0_L_m_s": [0.0] * 3}
    )
    sims = [simulate(s, run_seed(3, k)) for k in range(8)]
    fes = {v: hu.frontend([m for _, m in sims], hu.parse_tuning({"template_refine_s": v}))
           for v in (0.0, 30.0)}  # fmt: skip
    spread = {0.0: [], 30.0: []}
    for b, (truth, _) in enumerate(sims):
        k_ref = -(-(int(np.argmax(fes[30.0].known_at[b].any(axis=1))) + 300) // 10) * 10
        for v, f in fes.items():
            kn = f.known[b]
            R_GT = _aligned(f.template_G[b][kn], truth.features_T[kn])
            ks = np.arange(k_ref, len(f.t))
            ks = ks[np.all(np.isfinite(f.R_GI[b, ks]), axis=(-1, -2))]
            R_true = R_GT @ rot.quat_to_matrix(truth.q_TI[ks])
            e = rot.log_map(f.R_GI[b, ks] @ np.swapaxes(R_true, -1, -2))
            spread[v].append(np.degrees(np.sqrt(np.mean(np.sum((e - e.mean(0)) ** 2, 1)))))
    for v in spread:
        print(f"constant 17 m, 2e-5 rad, template_refine_s={v:g}: G attitude wander after the "
              f"switch {min(spread[v]):.3f}-{max(spread[v]):.3f} deg over 8 runs")  # fmt: skip
    print(
        f"template_error_mm={last[0]:.3f},{last[1]:.3f} "
        f"wander_deg={np.median(spread[0.0]):.3f},{np.median(spread[30.0]):.3f}"
    )


def occlusion() -> None:
    s = load_scenario("hu2024").with_updates(
        duration_s=100.0,
        steady_state_window_s=[90.0, 100.0],
        **{
            "target.features_T_m.count": 4,
            "target.omega0_T_rad_s": [0.05, -0.12, 0.08],
            "target.v0_L_m_s": [0.0, 0.0, 0.0],
            "sensor.noise.angular_rad": 1e-5,
        },
    )
    truth, meas = simulate(s, run_seed(2024, 6))
    nees = []
    for extra in ({}, {"iterate_max": 0}):
        sc = s.with_updates(**{"estimator.tuning": {"max_ratio_sigma": 0.03, **extra}})
        res = hu.run_filter(sc, [meas], True)
        res["x_true"], res["err"] = evaluation.error_states(hu.histories(res, sc), [truth])
        t, e, P = res["t"], res["err"][0], res["P"][0]
        print(f"tuning {extra or 'defaults'}:")
        for tt in (79.8, 80.1, 81.0, 90.0, 100.0):
            i = int(np.argmin(abs(t - tt)))
            print(f"  t={t[i]:5.1f} s attitude {np.degrees(np.linalg.norm(e[i, :3])):.2f} deg "
                  f"(1-sigma {np.degrees(np.sqrt(np.trace(P[i, :3, :3]))):.2f}), position "
                  f"{1e3 * np.linalg.norm(e[i, 9:12]):.1f} mm (1-sigma "
                  f"{1e3 * np.sqrt(np.trace(P[i, 9:12, 9:12])):.1f})")  # fmt: skip
        w = (t > 80.5) & (t < 100.0)
        ew, Pw = e[w, 9:12], P[w, 9:12, 9:12]
        q = np.einsum("ki,ki->k", ew, np.linalg.solve(Pw, ew[..., None])[..., 0])
        nees.append(float(np.mean(q)) / 3.0)
        print(f"  position NEES/dof over 80.5-100 s: {nees[-1]:.3g}")
    print(f"position_nees={nees[0]:.3g},{nees[1]:.3g}")


def schedule() -> None:
    from hu2024_diagnostics import true_frame  # noqa: I001 (benchmarks/, on sys.path)

    settings = {
        "seventh session (30 s, per-epoch rate fit)": {
            "template_refine_s": 30.0,
            "ls_unbiased_rates": False,
        },
        "30 s, unbiased rows": {"template_refine_s": 30.0},
        "8, 10, 30 s, per-epoch rate fit": {"ls_unbiased_rates": False},
        "defaults (8, 10, 30 s, unbiased rows)": {},
    }
    f10, m200 = [], []
    for noise in (2e-5, 5e-5):
        s = load_scenario("hu2024").with_updates(**{"sensor.noise.angular_rad": noise})
        sims = [simulate(s, run_seed(s.montecarlo.seed, k)) for k in range(20)]
        lam = np.array([8.0, 5.0, 4.0]) / 8.0
        for name, tuning in settings.items():
            fe = hu.frontend([m for _, m in sims], hu.parse_tuning(tuning))
            t = fe.t
            E = np.full(fe.R_GT.shape[:2], np.inf)
            for b, (truth, _) in enumerate(sims):
                ok = np.all(np.isfinite(fe.R_GT[b]), axis=(-1, -2))
                Rc = true_frame(fe.template_G[b], fe.known[b], truth)
                E[b, ok] = np.degrees(np.linalg.norm(rot.log_map(Rc.T @ fe.R_GT[b, ok]), axis=-1))
            errs = []
            for v, (k_v, tmpl) in enumerate(fe.template_history or [(None, fe.template_G)]):
                r = []
                for b, (truth, _) in enumerate(sims):
                    kn = fe.known_at[b, min(int(k_v[b]), len(t)) - 1] if v else fe.known[b]
                    g, f = tmpl[b][kn], truth.features_T[kn]
                    e = (g - g.mean(0)) - (f - f.mean(0)) @ _aligned(g, f).T
                    r.append(np.sqrt(np.mean(np.sum(e**2, axis=1))))
                errs.append(f"{1e3 * np.median(r):.3g}")
            med = np.median(E, axis=0)
            at = {ts: med[int(np.argmin(abs(t - ts)))] for ts in (8, 9, 10, 11, 12, 50, 200)}
            mom = np.nanmedian(np.abs(fe.moments[:, -1] - lam).max(-1))
            print(f"{noise:g} rad, {name}: template error per version {' / '.join(errs)} mm; "
                  f"frame error median at 8/9/10/11/12 s "
                  f"{' / '.join(f'{at[x]:.3g}' for x in (8, 9, 10, 11, 12))} deg, at 50 / 200 s "
                  f"{at[50]:.3g} / {at[200]:.3g} deg; moments error at 200 s {mom:.2g}")  # fmt: skip
            f10.append(at[10])
            m200.append(mom)
    print(f"frame_deg_10s={','.join(f'{x:.3g}' for x in f10)} "
          f"moments_err_200s={','.join(f'{x:.2g}' for x in m200)}")  # fmt: skip


if __name__ == "__main__":
    {"template": template, "occlusion": occlusion, "schedule": schedule}[
        sys.argv[1] if len(sys.argv) > 1 else "template"
    ]()
