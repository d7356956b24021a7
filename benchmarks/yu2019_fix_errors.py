"""How good is the first-order covariance of a rectangle fix (Yu 2019 Sec. 2, ``ekf-depth``)?

For each scan of a simulated yu2019 run, every recognised rectangle gives a fix (model
attitude and origin, :func:`tumblenav.frontends.depth_pose.pose_fixes`, with the true attitude
as the prediction); its error against the truth is compared with the first-order covariance of
:func:`tumblenav.estimators.ekf_depth.fix_covariance`.  Printed per run: the mean of the
squared whitened errors per axis of the rectangle frame (short side, long side, normal; 1 if
the model is right) for the origin and for the attitude, and the lag-1 correlation of the
whitened errors between consecutive scans.  Gross fixes (d^2 > 30 on 3 dof: a wrong rectangle
or case, which the filter's NIS gate rejects) are counted and left out.

Usage: python benchmarks/yu2019_fix_errors.py [scenario] [--runs 3]
Last line: ``pos_var_ratio=<short,long,normal> att_var_ratio=<...> pos_lag1=<...>`` (means
over runs).
"""

from __future__ import annotations

import argparse

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.runner import run_seed
from tumblenav.estimators.ekf_depth import fix_covariance
from tumblenav.frontends.depth_pose import pose_fixes
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate, target_model


def fix_errors(sc, run: int):
    """Every fix of run ``run``: ``(k, fx, za, zp, ea)``, the scan, the fix, its whitened
    attitude and origin errors in the rectangle frame, and its attitude error in T (rad)."""
    model, sigma = target_model(sc), sc.sensor.range_noise_m
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, run))
    rng = np.random.default_rng(run)
    R_CL, R_LI = rot.quat_to_matrix(meas.q_CL), rot.quat_to_matrix(meas.q_LI)
    b = np.asarray(truth.mass_centre_offset_T)
    for k in range(len(meas.t)):
        R_LT = R_LI[k] @ rot.quat_to_matrix(truth.q_TI[k]).T
        origin_L = truth.r_L[k] - R_LT @ b
        pts = meas.points[k][meas.observed[k]]
        fixes, _ = pose_fixes(pts, model, 3 * sigma, rng, sigma, R_CL[k] @ R_LT)
        for fx in fixes:
            cov_att, cov_pos = fix_covariance(fx, sigma)
            R_LP = R_CL[k].T @ fx.R_SM @ fx.R_MP
            zp = (R_LP.T @ (R_CL[k].T @ fx.p_MinS - origin_L)) / np.sqrt(np.diag(cov_pos))
            q_meas = rot.matrix_to_quat((R_LI[k].T @ R_CL[k].T @ fx.R_SM).T)
            ea = rot.boxminus(q_meas, truth.q_TI[k])
            za = (fx.R_MP.T @ ea) / np.sqrt(np.diag(cov_att))
            yield k, fx, za, zp, ea


def gross(za: np.ndarray, zp: np.ndarray) -> bool:
    """A wrong rectangle or case (d^2 > 30 on 3 dof), which the filter's NIS gate rejects."""
    return bool(zp @ zp > 30 or za @ za > 30)


def one_run(sc, run: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    wp, wa, ks, n_gross = [], [], [], 0
    for k, _, za, zp, _ in fix_errors(sc, run):
        if gross(za, zp):
            n_gross += 1
            continue
        wp.append(zp), wa.append(za), ks.append(k)
    return np.array(wp), np.array(wa), np.array(ks), n_gross


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="docs/results/scenarios/yu2019_1cm_noise.yaml")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    P, A, L = [], [], []
    for run in range(args.runs):
        wp, wa, ks, gross = one_run(sc, run)
        cons = np.flatnonzero(np.diff(ks) == 1)
        lag = [float(np.corrcoef(wp[cons, i], wp[cons + 1, i])[0, 1]) for i in range(3)]
        P.append(np.mean(wp**2, axis=0)), A.append(np.mean(wa**2, axis=0)), L.append(lag)
        print(
            f"run {run}: {len(wp)} fixes ({gross} gross left out); variance ratio origin "
            f"{np.round(P[-1], 2)}, attitude {np.round(A[-1], 2)}; lag-1 origin {np.round(lag, 2)}"
        )

    def fmt(x):
        return ",".join(f"{v:.2f}" for v in np.mean(x, axis=0))

    print(f"pos_var_ratio={fmt(P)} att_var_ratio={fmt(A)} pos_lag1={fmt(L)}")


if __name__ == "__main__":
    main()
