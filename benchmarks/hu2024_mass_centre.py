"""How good is the batch mass centre of ekf-dpacf's start?

For each run of a scenario (default hu2024) at one noise level, at the filter's start: the
error of the batch estimate of the mass centre against the truth, and the NEES per degree
of freedom of that error under the least-squares covariance alone (before the floor
``p0_mass_centre_floor_m``). ``--method joint`` (``features_from_rotation``, the default
since the seventh session): the error of the fitted features' mean; ``rotation``
(``mass_centre_from_rotation``): of the template's features less the batch mass centre.
Both after the rotation that best aligns the features with the true ones (it moves no
centre), so that no frame enters.

Usage: python benchmarks/hu2024_mass_centre.py [--noise 2e-5] [--runs 100]
       [--method joint|rotation] [--scenario hu2024|FILE] [--set key=value ...]
       (the sixth session's template of one sighting: --set template_refine_s=0)
Last line: ``rms_per_axis_mm=<rms error per axis> median_mm=<median |error|>
nees_ls_median=<median NEES/dof of the least-squares covariance>``
"""

from __future__ import annotations

import argparse

import numpy as np
from _tuning import with_tuning  # noqa: I001 (benchmarks/, on sys.path when run)

from tumblenav.campaign.store import run_seed
from tumblenav.estimators import ekf_dpacf as hu
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", type=float, default=2e-5)
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--method", choices=("joint", "rotation"), default="joint")
    ap.add_argument("--scenario", default="hu2024")
    ap.add_argument("--set", action="append", default=[], help="tuning key=value")
    args = ap.parse_args()
    sc = with_tuning(
        load_scenario(args.scenario), args.set, **{"sensor.noise.angular_rad": args.noise}
    )
    tun = hu.parse_tuning(sc.estimator.tuning)
    n = sc.chaser.orbit.mean_motion_rad_s
    sims = [simulate(sc, run_seed(sc.montecarlo.seed, k)) for k in range(args.runs)]
    fe = hu.filter_view(hu.frontend([m for _, m in sims], tun), tun.max_dpacf_sigma_rad)
    init = hu._initial_state(fe, tun, True, hu.layout(fe.usable.shape[2]), n)
    errs, nees = [], []
    for b, (truth, _) in enumerate(sims):
        k0 = init.k0[b]
        if k0 < 0:
            continue
        kn = fe.known[b]
        if args.method == "joint":
            out = hu.features_from_rotation(fe, b, k0, n)
            if out is None:
                continue
            f_G, cov_f, fitted = out
            idx = np.flatnonzero(fitted)
            sel = (3 * idx[:, None] + np.arange(3)).ravel()
            S = np.kron(np.ones((1, len(idx))) / len(idx), np.eye(3))
            feats, cov = f_G[idx], S @ cov_f[np.ix_(sel, sel)] @ S.T
        else:
            out = hu.mass_centre_from_rotation(fe, b, k0, n)
            if out is None:
                continue
            c, cov = out
            idx = np.flatnonzero(kn)
            feats = fe.template_G[b][idx] - c
        ftrue = truth.features_T[idx]
        U, _, Vt = np.linalg.svd(ftrue.T @ feats)
        R = Vt.T @ np.diag([1, 1, np.linalg.det(Vt.T @ U.T)]) @ U.T  # feats ~ R ftrue
        e = feats.mean(0) - R @ ftrue.mean(0)
        errs.append(np.linalg.norm(e))
        nees.append(e @ np.linalg.solve(cov, e) / 3)
    errs, nees = np.array(errs), np.array(nees)
    print(
        f"{args.scenario}, {args.method}, noise {args.noise:g} rad: {len(errs)} runs with a batch estimate; |error| median "
        f"{1e3 * np.median(errs):.1f} mm, 90th percentile {1e3 * np.percentile(errs, 90):.1f} "
        f"mm, max {1e3 * errs.max():.1f} mm"
    )
    print(
        f"rms_per_axis_mm={1e3 * np.sqrt(np.mean(errs**2) / 3):.1f} "
        f"median_mm={1e3 * np.median(errs):.1f} nees_ls_median={np.median(nees):.3g}"
    )


if __name__ == "__main__":
    main()
