"""Numbers behind docs/results/foundation.md: polhode periods, conservation, CW vs nonlinear.

Usage: python benchmarks/foundation_checks.py
Last line: ``polhode_max_err_s=<s> energy_drift=<rel> momentum_drift=<rel> cw_vs_nonlinear_m=<m>``
"""

from __future__ import annotations

import numpy as np

from tumblenav import dynamics as dyn
from tumblenav import rotations as rot
from tumblenav.scenario import load_scenario
from tumblenav.simulation import simulate

KABIR_I = np.array([90.0, 100.0, 112.0])
KABIR_DIR = np.array([2, 1, 2]) / 3.0  # printed as [0.67, 0.33, 0.67]
PRINTED = {0.025: 441.045, 0.075: 147.015, 0.125: 88.209, 0.175: 63.006}


def main() -> None:
    worst = 0.0
    for f, tp in PRINTED.items():
        T = dyn.polhode_period(KABIR_I, 2 * np.pi * f * KABIR_DIR)
        worst = max(worst, abs(T - tp))
        print(f"f_T = {f} Hz: polhode period {T:.4f} s (Kabir 2025 prints {tp} s)")
    # conservation over 3000 s (hu2024 body)
    I = np.array([8.0, 5.0, 4.0])
    t = np.arange(3001.0)
    q, w = dyn.propagate_attitude([0, 0, 0, 1.0], [0.1, 0.1, 0.1], I, t)
    E = 0.5 * np.sum(I * w**2, axis=1)
    H_I = np.einsum("tji,tj->ti", rot.quat_to_matrix(q), I * w)
    e_drift = np.max(np.abs(E / E[0] - 1))
    h_drift = np.max(np.linalg.norm(H_I - H_I[0], axis=1)) / np.linalg.norm(H_I[0])
    wj = dyn.jacobi_omega(I, [0.1, 0.1, 0.1], t)
    jac = np.max(np.abs(wj - w)) / np.linalg.norm([0.1, 0.1, 0.1])
    print(
        f"3000 s: energy drift {e_drift:.2e}, momentum drift {h_drift:.2e}, "
        f"vs Jacobi elliptic {jac:.2e} (relative)"
    )
    # CW closed form vs nonlinear truth, hu2024
    s = load_scenario("hu2024")
    truth, _ = simulate(s, 0)
    r_cw, _ = dyn.cw_propagate(
        s.target.r0_L_m, s.target.v0_L_m_s, s.chaser.orbit.mean_motion_rad_s, truth.t
    )
    cw = np.max(np.linalg.norm(r_cw - truth.r_L, axis=1))
    rng = np.linalg.norm(truth.r_L, axis=1)
    print(
        f"hu2024: CW vs nonlinear max {cw * 1e3:.3f} mm over 200 s; range {rng.min():.1f} to "
        f"{rng.max():.1f} m (final {rng[-1]:.1f} m)"
    )
    print(
        f"polhode_max_err_s={worst:.2e} energy_drift={e_drift:.2e} momentum_drift={h_drift:.2e} "
        f"cw_vs_nonlinear_m={cw:.2e}"
    )


if __name__ == "__main__":
    main()
