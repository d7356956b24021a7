"""The rates of G that enter the inertia least squares, against the truth (twenty-fourth
session, issue 18): runs ekf-dpacf's front end on runs RUNS of SCENARIO and prints, per time
window, the rate errors' mean whitened square per axis (1 if the stated covariance is right)
under the rows' whitening (``cov_w``, the fit's covariance from G's whole covariance) and
under the rates' zero-mean noise (``cov_w_noise``, from the points' own share of G's
covariance: what the errors-in-variables compensation takes); with T0 T1, every epoch between
them (whitened square, the error's size, G's error against the truth and G's sigmas).

The truth's rate is rotated into G by the rotation that best fits the measured rates
(Kabsch), so a constant frame offset does not count.

Usage::

    python hu_rate_errors.py SCENARIO RUNS [T0 T1]

hu_selfocc (7aea559's code): runs 0, 1, 2: whole 0.49-0.79, noise share 0.92-1.12 (1.80 in
one window); run 173: whole 0.16-0.30, noise share 1.0-4.6 (the template's share matters
there); run 96 at 93.5-94.4 s, before the visible features change at 94.5 s (G's sigma 2.8
-> 55 mrad): rate errors up to 0.12 rad/s at 14-3400 times their stated variance with the
centre's covariance taken for the window (f60a9e3's code), at most 8.8 with each attitude's.
"""

import sys

import numpy as np

from tumblenav import rotations as rot
from tumblenav.campaign.store import run_seed
from tumblenav.estimators.hu2024 import filter as F
from tumblenav.estimators.hu2024.tuning import parse_tuning
from tumblenav.frontends import stages
from tumblenav.frontends import stereo_points as SP
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

sc = load_scenario(sys.argv[1]).with_updates(**{"estimator.name": "ekf-dpacf"})
runs = [int(x) for x in sys.argv[2].split(",")]
window = (float(sys.argv[3]), float(sys.argv[4])) if len(sys.argv) > 4 else None
cap: dict = {}
orig = SP.identify_and_dpacf


def capture(*a, **kw):
    cap.update(om=a[0], R=a[2], cf=kw.get("cov_w"), cn=kw.get("cov_w_noise"))
    cap.update(cG=kw.get("cov_G_rows"))
    return orig(*a, **kw)


SP.identify_and_dpacf = capture
tun = parse_tuning(sc.estimator.tuning, True)
q_r = sc.process_noise.rotational_rad2_s4 if sc.process_noise else 0.0
for k in runs:
    truth, meas = simulate(sc, run_seed(sc.montecarlo.seed, k))
    tracks, _ = stages.prepare(meas, ("stereo_points",), None)
    F.frontend([tracks], tun, q_r, disturbed=sc.process_noise.disturb_truth)
    om, cf, cn = cap["om"][0], cap["cf"][0], cap["cn"][0]
    n = om.shape[0]
    dt = truth.t[1] - truth.t[0]
    wT = truth.omega_TI_T[:n]
    ok = np.all(np.isfinite(om), -1) & np.all(np.isfinite(cf), (-1, -2))
    U, _, Vt = np.linalg.svd(om[ok].T @ wT[ok])
    R_GT = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    dw = om - wT @ R_GT.T
    z = {}
    for name, C in (("whole", cf), ("noise share", cn)):
        z[name] = np.full(n, np.nan)
        for j in np.flatnonzero(ok):
            z[name][j] = dw[j] @ np.linalg.solve(C[j], dw[j]) / 3
    out = []
    for lo, hi in [(0, 30), (30, 90), (90, 1e9)]:
        m = ok & (np.arange(n) * dt >= lo) & (np.arange(n) * dt < hi)
        span = f"{lo}-{hi if hi < 1e8 else 'end'} s"
        out.append(span + ": " + ", ".join(f"{a} {np.mean(v[m]):.2f}" for a, v in z.items()))
    print(f"run {k}: " + "; ".join(out))
    if window is None:
        continue
    R_true = R_GT @ rot.quat_to_matrix(truth.q_TI[:n])
    Rm, cG = cap["R"][0], cap["cG"][0]
    for j in range(int(window[0] / dt), min(int(window[1] / dt) + 1, n)):
        if not np.all(np.isfinite(Rm[j])):
            continue
        psi = rot.log_map(Rm[j] @ R_true[j].T)
        sg = np.sqrt(np.linalg.eigvalsh(cG[j]))
        print(
            f"  t={j * dt:6.1f} whitened {z['whole'][j]:9.2f} |error| {np.linalg.norm(dw[j]):.4f} "
            f"rad/s; G error {np.round(psi * 1e3, 2)} mrad, G sigmas {np.round(sg * 1e3, 2)}"
        )
