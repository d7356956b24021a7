"""The inertia least squares' errors-in-variables compensation in one run (twenty-third
session, issue 18): runs ekf-dpacf's front end on run RUN of SCENARIO and prints, at each
solution between T0 and T1 s, the normalised moments of the solution and the two largest
generalized eigenvalues of (Nc, N) (the rates' noise's expected share of the information,
per direction; the compensation divides a direction by 1 - lambda).

Usage::

    python hu_eiv_share.py SCENARIO RUN [T0 T1]

hu_selfocc run 173, 70-100 s: lambda 1.39 at 78 s, 1.00 at 82 s, 0.87 at 84 s; the moments
(1, 0.705, 0.497) to 82 s, (1, 0.194, -0.098) at 84 s (c71fdd0's code; from the twenty-fourth
session on, with the compensation on the rates' zero-mean noise, lambda stays below 0.06 after
77 s and the moments at (1, 0.70, 0.50)).
"""

import sys

import numpy as np
import scipy.linalg as sl

from tumblenav.campaign.store import run_seed
from tumblenav.estimators.hu2024 import filter as F
from tumblenav.estimators.hu2024.tuning import parse_tuning
from tumblenav.frontends import stages
from tumblenav.frontends.stereo_points import inertia_ls as L
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

sc = load_scenario(sys.argv[1]).with_updates(**{"estimator.name": "ekf-dpacf"})
k = int(sys.argv[2])
t0, t1 = (float(sys.argv[3]), float(sys.argv[4])) if len(sys.argv) > 4 else (70.0, 100.0)
sums, inertia = [], []
orig_sums, orig_inertia = L._version_sums, L._inertia_from_l


def version_sums(rows, omega_G, R_GI, s, dt, delay, sel):
    out = orig_sums(rows, omega_G, R_GI, s, dt, delay, sel)
    sums.append((sel, out, dt))
    return out


def inertia_from_l(l):
    out = orig_inertia(l)
    inertia.append(out)
    return out


L._version_sums, L._inertia_from_l = version_sums, inertia_from_l
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
tracks, _ = stages.prepare(meas, ("stereo_points",), None)
tun = parse_tuning(sc.estimator.tuning, True)
q_r = sc.process_noise.rotational_rad2_s4 if sc.process_noise else 0.0
F.frontend([tracks], tun, q_r, disturbed=sc.process_noise.disturb_truth)
sel, (N, r, bb, cnt, V, E, Nc, rc, M, Ew, Sw), dt = sums[0]  # the last template's rows
I_G = inertia[-1][0]  # the solutions' inertia, at the same epochs
for si, kk in enumerate(sel):
    if not t0 <= kk * dt <= t1:
        continue
    lam = np.linalg.eigvalsh(I_G[si])[::-1]
    try:
        g = sl.eigh(Nc[0, si], N[0, si], eigvals_only=True)
    except np.linalg.LinAlgError:  # no rows yet (N singular)
        continue
    print(f"t={kk * dt:.0f} moments {np.round(lam / lam[0], 4)} lambda {g[-1]:.3g}, {g[-2]:.3g}")
