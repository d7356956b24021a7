"""Diagnostics behind docs/results/hu2024.md, Consistency: is each covariance honest?

Three readings of hu2024 runs (the campaign's seeds), ekf-dpacf front end and filter:

* ``frame``: the DPACF frame of the front end against the true principal frame, NEES per
  degree of freedom with its ``cov_frame``, per run averaged over time windows (with
  ``--run``: also each listed run's frame error at the end; a run on the other branch shows
  a half turn);
* ``ratios``: the front end's inertia ratios against the truth, NEES/dof with
  ``cov_ratios`` (2 dof: the ratios obey one constraint) at the filter's start and over
  windows;
* ``start``: for the runs given by ``--run``, the filter's errors and 1-sigma (square root of
  the block's trace) per block at and after its start;
* ``g``: the photogrammetric frame's attitude of every epoch against the truth's G (the
  template aligned to the true features), its error and NEES/dof with ``cov_G``;
* ``branches``: front end only, are the half-turn probabilities calibrated? Their sum over
  the runs (expected number of runs whose final frame is the truth's turned by a half turn)
  against the number of such runs.

Usage: python benchmarks/hu2024_diagnostics.py frame|ratios|g [--runs 40 | --run K ...]
       [--noise 2e-5]
       python benchmarks/hu2024_diagnostics.py start --run 475 [--run ...] [--noise 2e-5]
       python benchmarks/hu2024_diagnostics.py branches --runs 500 [--noise 2e-5]
       [--set key=value ...]  (estimator.tuning overrides, YAML values)
       [--scenario NAME_OR_YAML]  (default hu2024; its own noise unless --noise)
Last line: ``frame_nees_mean=<last window>`` / ``g_nees_mean=<last window>`` / ``ratio_nees_start_mean=<...>`` /
``start_attitude_err_over_sigma=<first run, at the start>`` / ``expected_flips=<sum p> flips=<runs>``
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
from _tuning import with_tuning  # noqa: I001 (benchmarks/, on sys.path when run)

from tumblenav import evaluation
from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators import ekf_dpacf as hu
from tumblenav.frontends.inertia import branch_probabilities, inertia_ratios, principal_frame
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

WINDOWS = ((20, 30), (30, 60), (60, 100), (100, 150), (150, 200))


def true_frame(template_G, known, truth) -> np.ndarray:
    """R_GT of the true inertia in this run's G (as ekf_dpacf.canonical_frame)."""
    g, f = template_G[known], truth.features_T[known]
    U, _, Vt = np.linalg.svd((f - f.mean(0)).T @ (g - g.mean(0)))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R_GT = Vt.T @ D @ U.T
    return principal_frame(R_GT @ np.asarray(truth.inertia_T) @ R_GT.T)


def per_window(t, v, label):
    last = float("nan")
    for w in WINDOWS:
        m = (t >= w[0]) & (t <= w[1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            pr = np.nanmean(v[:, m], axis=1)
        pr = pr[np.isfinite(pr)]
        if len(pr):
            last = float(np.mean(pr))
            print(f"{label} {w}: per-run NEES/dof median {np.median(pr):.3g} mean {last:.3g} "
                  f"p90 {np.percentile(pr, 90):.3g} ({len(pr)} runs)")  # fmt: skip
    return last


def branch_calibration(sc, ks, batch: int = 50) -> None:
    """Front end only: the half-turn probabilities of the final DPACF frame against the runs
    whose final frame is the truth's turned by a half turn."""
    tun = hu.parse_tuning(sc.estimator.tuning)
    ps, flipped = [], []
    for s0 in range(0, len(ks), batch):
        part = ks[s0 : s0 + batch]
        sims = [simulate(sc, run_seed(sc.montecarlo.seed, k)) for k in part]
        fe = hu.filter_view(hu.frontend([m for _, m in sims], tun), tun.max_dpacf_sigma_rad)
        for b in range(len(part)):
            if not np.all(np.isfinite(fe.R_GT[b, -1])):
                continue
            ps.append(branch_probabilities(fe.R_GT[b, -1], fe.cov_frame[b, -1]).sum())
            Rc = true_frame(fe.template_G[b], fe.known[b], sims[b][0])
            flipped.append(np.trace(Rc.T @ fe.R_GT[b, -1]) < 1.0)
    ps, flipped = np.array(ps), np.array(flipped)
    print(f"{len(ps)} runs with a final frame; sum of the half-turn probabilities "
          f"{ps.sum():.2f}; runs on a turned frame {flipped.sum()} (their p: "
          f"{np.round(ps[flipped], 3).tolist()}); runs with p > 0.01: {(ps > 0.01).sum()}")  # fmt: skip
    print(f"expected_flips={ps.sum():.3g} flips={flipped.sum()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["frame", "ratios", "start", "branches", "g"])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--run", type=int, action="append", default=[])
    ap.add_argument("--noise", type=float, default=None, help="rad (default: hu2024's 2e-5)")
    ap.add_argument("--scenario", default="hu2024", help="a built-in name or a YAML path")
    ap.add_argument("--set", action="append", default=[], help="tuning key=value")
    args = ap.parse_args()
    noise = (
        {}
        if args.noise is None and args.scenario != "hu2024"
        else {"sensor.noise.angular_rad": 2e-5 if args.noise is None else args.noise}
    )
    sc = with_tuning(load_scenario(args.scenario), args.set, **noise)
    ks = args.run if args.run else list(range(args.runs))
    if args.what == "branches":
        branch_calibration(sc, ks)
        return
    sims = [simulate(sc, run_seed(sc.montecarlo.seed, k)) for k in ks]
    truths = [t for t, _ in sims]
    res = hu.run_filter(sc, [m for _, m in sims], True)
    res["x_true"], res["err"] = evaluation.error_states(hu.histories(res, sc), truths)
    fe, t = res["frontend"], res["t"]
    if args.what == "g":  # the G attitude of each epoch against the truth's G
        v = np.full(fe.R_GI.shape[:2], np.nan)
        vw = np.full(fe.R_GI.shape[:2], np.nan)
        err = np.full(fe.R_GI.shape[:2], np.nan)
        for b, tr in enumerate(truths):
            g, f = fe.template_G[b][fe.known[b]], tr.features_T[fe.known[b]]
            U, _, Vt = np.linalg.svd((f - f.mean(0)).T @ (g - g.mean(0)))
            D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
            R_GIt = (Vt.T @ D @ U.T) @ rot.quat_to_matrix(tr.q_TI)
            ok = np.all(np.isfinite(fe.R_GI[b]), axis=(-1, -2))
            e = rot.log_map(fe.R_GI[b, ok] @ np.swapaxes(R_GIt[ok], -1, -2))
            err[b, ok] = np.degrees(np.linalg.norm(e, axis=-1))
            v[b, ok] = np.einsum("ki,kij,kj->k", e, np.linalg.inv(fe.cov_G[b, ok]), e) / 3
            # the rate of G against the truth's, NEES/dof with its full covariance
            okw = np.all(np.isfinite(fe.omega_G[b]), axis=-1)
            ew = fe.omega_G[b, okw] - ((Vt.T @ D @ U.T) @ tr.omega_TI_T[okw].T).T
            Cw = fe.cov_omega[b, okw]
            vw[b, okw] = np.einsum("ki,kij,kj->k", ew, np.linalg.inv(Cw), ew) / 3
        for w in WINDOWS:
            m = (t >= w[0]) & (t <= w[1])
            print(f"G attitude {w}: error median {np.nanmedian(err[:, m]):.3g} deg, p90 "
                  f"{np.nanpercentile(err[:, m], 90):.3g} deg")  # fmt: skip
        per_window(t, vw, "rate of G")
        print(f"g_nees_mean={per_window(t, v, 'G attitude'):.3g}")
    elif args.what == "frame":
        v = np.full(fe.R_GT.shape[:2], np.nan)
        for b, tr in enumerate(truths):
            Rc = true_frame(fe.template_G[b], fe.known[b], tr)
            ok = np.all(np.isfinite(fe.R_GT[b]), axis=(-1, -2))
            e = rot.log_map(Rc.T @ fe.R_GT[b, ok])
            v[b, ok] = np.einsum("ki,kij,kj->k", e, np.linalg.inv(fe.cov_frame[b, ok]), e) / 3
        if args.run:  # the listed runs: the frame's error and 1-sigma at the end, per T axis
            for b, k in enumerate(ks):
                Rc = true_frame(fe.template_G[b], fe.known[b], truths[b])
                e = np.degrees(rot.log_map(Rc.T @ fe.R_GT[b, -1]))
                sd = np.degrees(np.sqrt(np.diag(fe.cov_frame[b, -1])))
                print(f"run {k}: frame error at the end {np.round(e, 2)} deg, 1-sigma "
                      f"{np.round(sd, 2)} deg")  # fmt: skip
        # the DPACF attitude measurement q_T'I = q_T'G q_GI against the exact truth (the true
        # principal frame, snapped to the DPACF convention: no template in the truth), with
        # its covariance cov_TI (frame part + G attitude part)
        va = np.full(fe.R_GT.shape[:2], np.nan)
        for b, tr in enumerate(truths):
            R_TcT = evaluation.alignment.canonical_frame(fe.template_G[b], fe.known[b], tr)
            qt = rot.quat_multiply(rot.matrix_to_quat(R_TcT), tr.q_TI)
            ok = np.all(np.isfinite(fe.q_TI[b]), -1) & np.all(np.isfinite(fe.cov_TI[b]), (-1, -2))
            e = rot.log_map(
                rot.quat_to_matrix(fe.q_TI[b, ok]) @ np.swapaxes(rot.quat_to_matrix(qt[ok]), -1, -2)
            )
            va[b, ok] = np.einsum("ki,kij,kj->k", e, np.linalg.inv(fe.cov_TI[b, ok]), e) / 3
        per_window(t, va, "DPACF attitude (exact truth)")
        print(f"frame_nees_mean={per_window(t, v, 'DPACF frame'):.3g}")
    elif args.what == "ratios":
        e = inertia_ratios(fe.moments) - res["x_true"][:, -1:, 7:10]
        ok = np.all(np.isfinite(e), -1) & np.all(np.isfinite(fe.cov_ratios), (-1, -2))
        v = np.full(ok.shape, np.nan)
        Ci = np.linalg.pinv(fe.cov_ratios[ok], hermitian=True, rcond=1e-10)
        v[ok] = np.einsum("ki,kij,kj->k", e[ok], Ci, e[ok]) / 2
        k0 = res["k0"]
        v0 = np.array([v[b, k0[b]] for b in range(len(ks)) if k0[b] >= 0])
        print(f"at the start: NEES/dof median {np.median(v0):.3g} mean {v0.mean():.3g} "
              f"p90 {np.percentile(v0, 90):.3g} ({len(v0)} runs)")  # fmt: skip
        per_window(t, v, "ratios")
        print(f"ratio_nees_start_mean={v0.mean():.3g}")
    else:
        names = ("attitude", "rate", "inertia", "position", "velocity")
        first = float("nan")
        for b, k in enumerate(ks):
            k0 = res["k0"][b]
            print(f"run {k}: start {t[k0]:.1f} s (error / 1-sigma per block)")
            if k0 < 0:
                continue
            for kk in (k0, k0 + 10, k0 + 100, len(t) - 1):
                kk = min(kk, len(t) - 1)
                e, P = res["err"][b, kk], res["P"][b, kk]
                if not np.all(np.isfinite(e)):
                    continue
                cells = []
                for j, nm in enumerate(names):
                    s = slice(3 * j, 3 * j + 3)
                    cells.append(
                        f"{nm} {np.linalg.norm(e[s]):.3g}/{np.sqrt(np.trace(P[s, s])):.3g}"
                    )
                print(f"  t={t[kk]:.1f}  " + "  ".join(cells))
                if b == 0 and kk == k0:
                    first = np.linalg.norm(e[:3]) / np.sqrt(np.trace(P[:3, :3]))
        print(f"start_attitude_err_over_sigma={first:.3g}")


if __name__ == "__main__":
    main()
