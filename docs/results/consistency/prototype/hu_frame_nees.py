"""The front end's DPACF frame against the truth over many runs (twenty-fourth session, issue
18): its NEES/dof at the given times, branch-free (the proper signed axis permutation of the
truth closest to the estimate: the half turns and the axes' order do not count), mean, median
and worst runs. With RUN, that run alone at each time: the error (deg, about T's axes, the
permutation fixed at the run's last frame, so a half turn shows as 180 deg), the sigmas and
the NEES/dof.

Usage::

    python hu_frame_nees.py SCENARIO NRUNS T1,T2,... [RUN]

hu_conv30, 40 runs: 1.02 / 1.01 / 0.90 at 250 / 350 / 450 s (worst 3.2-4.4): the frame's
covariance is right on average; with the truth torque-free the frame errors are ~0.01 deg.
hu_conv30 run 20 (`... 1 150,175,...,325 20`): 178 deg about y from 150 to 325 s, its error
about z 7-9 deg at a sigma of 1.4-2 deg; hu_selfocc run 147 (`... 1 60,80,...,200 147`):
NEES/dof 0.2-1.35.
"""

import itertools
import sys

import numpy as np
from scipy.spatial.transform import Rotation

from tumblenav.campaign.store import run_seed
from tumblenav.estimators.hu2024 import filter as F
from tumblenav.estimators.hu2024.tuning import parse_tuning
from tumblenav.frontends import stages
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

sc = load_scenario(sys.argv[1]).with_updates(**{"estimator.name": "ekf-dpacf"})
runs = range(int(sys.argv[2]))
times = [float(x) for x in sys.argv[3].split(",")]
one = int(sys.argv[4]) if len(sys.argv) > 4 else None
if one is not None:
    runs = range(one, one + 1)
Ps = []
for perm in itertools.permutations(range(3)):
    for sg in itertools.product([1, -1], repeat=3):
        P = np.zeros((3, 3))
        P[list(perm), range(3)] = sg
        if np.linalg.det(P) > 0:
            Ps.append(P)
tun = parse_tuning(sc.estimator.tuning, True)
q_r = sc.process_noise.rotational_rad2_s4 if sc.process_noise else 0.0
res = {t: [] for t in times}
for k in runs:
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tracks, _ = stages.prepare(meas, ("stereo_points",), None)
    fe = F.frontend([tracks], tun, q_r, disturbed=sc.process_noise.disturb_truth)
    n = fe.R_GT.shape[1]
    dt = fe.t[1] - fe.t[0]
    om = fe.omega_G[0]
    ok = np.all(np.isfinite(om), -1)
    # the true G -> T from the rates of every epoch (the torque moves H, not R_GT)
    U, _, Vt = np.linalg.svd(om[ok].T @ truth.omega_TI_T[:n][ok])
    R0 = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    last = np.flatnonzero(np.all(np.isfinite(fe.R_GT[0]), axis=(-1, -2)))
    if one is not None and len(last):  # one permutation for the whole run: its last frame's
        Rl = fe.R_GT[0, last[-1]]
        Ps = [
            min(Ps, key=lambda P: np.linalg.norm(Rotation.from_matrix(Rl.T @ R0 @ P).as_rotvec()))
        ]
    for t in times:
        j = int(round(t / dt)) - 1
        R = fe.R_GT[0, j]
        if not np.all(np.isfinite(R)):
            continue
        e = min((Rotation.from_matrix(R.T @ R0 @ P).as_rotvec() for P in Ps), key=np.linalg.norm)
        C = fe.cov_frame[0, j]
        res[t].append((k, e @ np.linalg.solve(C, e) / 3))
        if one is not None:
            sg = np.degrees(np.sqrt(np.diag(C)))
            print(
                f"t={fe.t[j]:6.1f} error deg {np.round(np.degrees(e), 2)} sigma deg "
                f"{np.round(sg, 2)} NEES/dof {res[t][-1][1]:.2f}"
            )
if one is not None:
    sys.exit(0)
for t in times:
    v = np.array([x[1] for x in res[t]])
    worst = sorted(res[t], key=lambda x: -x[1])[:5]
    print(
        f"t={t}: runs {len(v)} mean {v.mean():.2f} median {np.median(v):.2f} "
        f"worst {[(a, round(b, 1)) for a, b in worst]}"
    )
