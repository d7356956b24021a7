"""The DPACF frame's jumps between solutions of one run (twenty-third session, issue 18):
runs ekf-dpacf's front end on run RUN of SCENARIO and prints every re-solution that turns
the frame by more than DEG degrees (default 90: the half turns), with the branch
probabilities before and after (frontends.inertia.branch_statistics) and the frame's sigma;
then the template's versions and the frame's sigma at a few times.

Usage::

    python hu_frame_jumps.py SCENARIO RUN [DEG]

hu_occ20 run 43: half turns at 63, 90, 112, 121, 147 and 159 s, p 0.47-0.50;
hu_selfocc run 173 with DEG 3: 21 deg at 94 s, sigma 1.9 deg.
"""

import sys

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators.hu2024 import filter as F
from tumblenav.estimators.hu2024.tuning import parse_tuning
from tumblenav.frontends import stages
from tumblenav.frontends.inertia import branch_statistics
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

sc = load_scenario(sys.argv[1])
k = int(sys.argv[2])
deg = float(sys.argv[3]) if len(sys.argv) > 3 else 90.0
sc = sc.with_updates(**{"estimator.name": "ekf-dpacf"})
truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
tracks, _ = stages.prepare(meas, ("stereo_points",), None)
tun = parse_tuning(sc.estimator.tuning, True)
q_r = sc.process_noise.rotational_rad2_s4 if sc.process_noise else 0.0
fe = F.frontend([tracks], tun, q_r, disturbed=sc.process_noise.disturb_truth)
t = fe.t
p, _, _ = branch_statistics(fe.R_GT, fe.cov_frame)
R = fe.R_GT[0]
prev = None
for i in range(0, len(t), 10):  # the front end re-solves every ls_every = 10 epochs
    if not np.all(np.isfinite(R[i])):
        continue
    if prev is not None:
        ang = np.degrees(np.linalg.norm(rot.log_map(R[prev].T @ R[i])))
        if ang > deg:
            sig = np.degrees(np.sqrt(np.linalg.eigvalsh(fe.cov_frame[0, i])[-1]))
            print(f"t={t[i]:.1f} frame turned by {ang:.0f} deg; p_turn before "
                  f"{np.round(p[0, prev], 4)} after {np.round(p[0, i], 4)}; sigma {sig:.2f} deg")
    prev = i
if fe.template_history:
    print("template versions from t =", [float(t[min(int(np.asarray(kk)[0]), len(t) - 1)])
                                         for kk, _ in fe.template_history])
