"""How far can the GP of Kabir 2025 Sec. 2.3 predict, by its own account?

For the GP study of ``reproduce kabir2025`` (one feature at [1, 1, 1] m, sigma_p = 1e-5 rad at
1 Hz, the same seeds), train on [0, T_train] and predict the next 2000 s; print per run the
prediction RMSE against the noise-free projections, the GP's own predictive standard deviation
(RMS over the window and outputs), their ratio, and the RMSE per 500-s quarter of the window
(an error that grows linearly in time is a period error; a flat one is the amplitudes).

Usage: python benchmarks/gp_calibration.py [--f-T 0.175] [--T-train 200] [--runs 20]
Last line: ``rmse_median=<rad> pred_std_median=<rad> ratio_median=<rmse / pred std>``
"""

from __future__ import annotations

import argparse

import numpy as np

from tumblenav.estimators import gp as gpm
from tumblenav.frontends import projections as proj
from tumblenav.papers import kabir2025 as k
from tumblenav.sensors.stereo import project
from tumblenav.simulation import simulate


def one_run(f_T: float, T_train: float, run: int, seed: int = 2025) -> dict[str, float]:
    base = k.scenario_for(f_T)
    feats = [list(k.GP_FEATURE_M)] + [list(p) for p in base.target.features_T_m[1:]]
    sc = base.with_updates(
        **{
            "target.features_T_m": feats,
            "duration_s": T_train + k.T_PREDICT_S,
            "occlusion.loss_from_s": None,
            "steady_state_window_s": None,
        }
    )
    truth, meas = simulate(sc, np.random.SeedSequence(seed).spawn(run + 1)[run])  # as _gp_job
    w, _ = proj.normalised(meas)
    f = meas.rig.left.focal_px
    cu, cv = meas.rig.left.principal_point_px
    uv, _ = project(meas.rig, truth.features_C)
    w_true = np.stack(
        [(uv[:, 1, 0, 0] - cu) / f, (uv[:, 1, 0, 1] - cv) / f, (uv[:, 0, 0, 0] - cu) / f], axis=1
    )
    t = meas.t
    tr = t <= T_train
    fit = gpm.fit_icm_gp(t[tr], w[tr, 0, :3], sensor_noise_std=float(meas.noise_px / f))
    mean, var = fit.predict(t[~tr])
    err = mean - w_true[~tr]
    dt = t[~tr] - T_train
    quarters = [
        float(np.sqrt(np.mean(err[(dt > a) & (dt <= a + 500)] ** 2))) for a in range(0, 2000, 500)
    ]
    rmse = float(np.sqrt(np.mean(err**2)))
    std = float(np.sqrt(np.mean(var)))
    return {"rmse": rmse, "pred_std": std, "ratio": rmse / std, "quarters": quarters}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--f-T", type=float, default=0.175)
    ap.add_argument("--T-train", type=float, default=200.0)
    ap.add_argument("--runs", type=int, default=20)
    args = ap.parse_args()
    rows = []
    for run in range(args.runs):
        r = one_run(args.f_T, args.T_train, run)
        rows.append(r)
        q = " ".join(f"{x:.2e}" for x in r["quarters"])
        print(
            f"run {run}: rmse {r['rmse']:.3e} pred std {r['pred_std']:.3e} ratio {r['ratio']:.2f}"
            f" | per 500 s: {q}",
            flush=True,
        )
    med = {key: float(np.median([r[key] for r in rows])) for key in ("rmse", "pred_std", "ratio")}
    print(
        f"rmse_median={med['rmse']:.3e} pred_std_median={med['pred_std']:.3e} "
        f"ratio_median={med['ratio']:.2f}"
    )


if __name__ == "__main__":
    main()
