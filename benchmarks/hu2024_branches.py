"""Wrong DPACF branch and consistency of the rest, from the run files of a hu2024 campaign.

For each noise level of a ``tumblenav reproduce hu2024`` folder (or one ``montecarlo`` folder
with ``--single``): the runs with an estimate in the window, those that ended on the DPACF
branch turned by a half turn (mean attitude error in the window above 90 deg), the NEES per
degree of freedom averaged over the right-branch runs (as summary.json averages all runs),
and the median over runs of the per-run NEES per degree of freedom.

Usage: python benchmarks/hu2024_branches.py out/hu2024 [--estimator ekf-dpacf]
       python benchmarks/hu2024_branches.py out/hold --single
Last line: ``wrong_branch=<runs at 2e-5 rad> nees_right_branch=<at 2e-5> median_run=<at 2e-5>``
(or of the single campaign).
"""

from __future__ import annotations

import argparse
import glob
import warnings
from pathlib import Path

import numpy as np


def stats(folder: Path, window=(150.0, 200.0)) -> dict:
    started = wrong = 0
    right_rows, per_run = [], []
    for f in sorted(glob.glob(str(folder / "runs" / "run_*.npz"))):
        with np.load(f) as z:
            t = z["t"]
            m = (t >= window[0]) & (t <= window[1])
            att = z["err_attitude_deg"][m]
            if not np.isfinite(att).any():
                continue
            started += 1
            is_wrong = bool(np.nanmean(att) > 90.0)
            wrong += is_wrong
            ne = z["nees"][m] / int(z["nees_dof"])
        if not is_wrong:
            right_rows.append(ne)
        per_run.append(np.nanmean(ne))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        per_t = np.nanmean(np.array(right_rows), axis=0)
    return {
        "runs": len(glob.glob(str(folder / "runs" / "run_*.npz"))),
        "started": started,
        "wrong": wrong,
        "nees_right": float(np.nanmean(per_t)),
        "median_run": float(np.median(per_run)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--estimator", default="ekf-dpacf")
    ap.add_argument("--single", action="store_true", help="FOLDER is one campaign")
    args = ap.parse_args()
    if args.single:
        cases = {"campaign": args.folder}
    else:
        cases = {
            p.name.removeprefix("noise_"): p / args.estimator
            for p in sorted(args.folder.glob("noise_*"), key=lambda p: float(p.name[6:]))
        }
    last = None
    for name, folder in cases.items():
        s = stats(folder)
        print(
            f"{name}: {s['runs']} runs, {s['started']} with an estimate in the window, "
            f"{s['wrong']} on the wrong branch; NEES/dof of the right-branch runs "
            f"{s['nees_right']:.3g}; median per-run NEES/dof {s['median_run']:.3g}"
        )
        if args.single or name == "2.0e-05":
            last = s
    if last is not None:
        print(
            f"wrong_branch={last['wrong']} nees_right_branch={last['nees_right']:.4g} "
            f"median_run={last['median_run']:.4g}"
        )


if __name__ == "__main__":
    main()
