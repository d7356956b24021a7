"""The batch start's figures in docs/results/consistency.md (seventeenth session, issue 18).

    python chang_batch_start.py synthetic
        the fit on the six synthetic windows of tests/test_chang2021_estimator.py (a rate 70 deg
        off the truth's): per window the end state's NEES/dof (14 dof: attitude, position,
        velocity, inertia), cost/dof, attitude error (deg)
    python chang_batch_start.py starts SCENARIO SEEDS
        per run: how far the window's rate line at k0 points from the truth's rate (deg), and
        the fit from it and from each turned start (cost/dof, iterations, the rate at k1), e.g.
        SCENARIO docs/results/scenarios/consistency/chang_points59.yaml, SEEDS 2,4
"""

import sys

import numpy as np

sys.path.insert(0, "tests")


def synthetic() -> None:
    import test_chang2021_estimator as T

    n = 1.1e-3
    for seed in range(6):
        fit, e = T._synthetic_batch_fit(seed, n)
        sel = np.r_[0:3, 6:17]
        nees = e[sel] @ np.linalg.solve(fit.P[np.ix_(sel, sel)], e[sel]) / 14
        print(
            f"window {seed}: NEES/dof {nees:.2f} cost/dof {fit.cost / fit.dof:.3f} "
            f"attitude {np.degrees(np.linalg.norm(e[:3])):.3f} deg"
        )


def starts(path: str, seeds: str) -> None:
    from tumblenav import rotations as rot
    from tumblenav.campaign.store import run_seed
    from tumblenav.dynamics.relative_orbit import cw_stm
    from tumblenav.estimators.chang2021 import batch as B
    from tumblenav.estimators.chang2021 import slam as S
    from tumblenav.estimators.chang2021.model import omega_LI_L
    from tumblenav.estimators.chang2021.tuning import PoseTuning
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import simulate

    sc = load_scenario(path)
    n = float(sc.chaser.orbit.mean_motion_rad_s)
    for seed in (int(a) for a in seeds.split(",")):
        truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, seed))
        tun = PoseTuning(**(sc.estimator.tuning or {}))
        steps = S.StateSteps(meas=meas, tun=tun, n_orbit=n)
        st, _ = steps.start_at(steps.k0 + tun.init_frames - 1)
        k0 = st.k0
        R_TL = rot.quat_to_matrix(truth.q_TI[k0]) @ rot.quat_to_matrix(truth.q_LI[k0]).T
        w_true = R_TL.T @ (truth.omega_TI_T[k0] - R_TL @ omega_LI_L(n))  # in That = L(k0)
        wg = st.omega_k0
        ang = np.degrees(np.arccos(wg @ w_true / np.linalg.norm(wg) / np.linalg.norm(w_true)))
        print(f"run {seed}: the rate line at k0 {ang:.1f} deg off the truth's rate")
        rv0 = cw_stm(n, float(meas.t[st.k0] - meas.t[st.k])) @ st.x[7:13]
        for w0 in B._start_rates(wg):
            only = B._start_rates
            B._start_rates = lambda w: [np.asarray(w, float)]  # this start alone
            try:
                fit = B.fit_window(
                    steps.tracks, meas.t, st.k0, st.k, w0, rv0, n, estimate_inertia=True,
                    inertia_sigma=tun.inertia_sigma, centre_sigma=tun.prior_mass_centre_sigma_m,
                    noise_scale=1.0, first_noise_scale=1.0,
                    gate_probability=tun.feature_gate_probability,
                    max_features=tun.max_map_features,
                )  # fmt: skip
            finally:
                B._start_rates = only
            if fit is None:
                print("  start: no fit")
                continue
            print(
                f"  start: cost/dof {fit.cost / fit.dof:.4f} iterations {fit.iterations} "
                f"rate at k1 {np.round(fit.x[4:7], 4)}"
            )


if __name__ == "__main__":
    if sys.argv[1] == "synthetic":
        synthetic()
    else:
        starts(sys.argv[2], sys.argv[3])
