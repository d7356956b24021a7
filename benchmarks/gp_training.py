"""GP training speed and accuracy (Kabir 2025 Sec. 2.3): tumblenav's ICM GP against GPy.

Data: the kabir2025 scenario (f_T = 0.025 Hz, five features, parallel rig, sigma_p = 1e-5 rad),
one run, no occlusion, ``--duration`` s at 1 Hz.  Per feature, ``[u_R, v_R, u_L]`` (normalised
projections, rad) for ``t <= T_train = 1500 s`` train one multi-output GP (ICM over the three
outputs, product of two periodic kernels, Kabir 2025 eq. 26).  Accuracy is the RMSE of the
predicted means against the noise-free projections over the 1500 s after training (Kabir's
T_predict), pooled over features and outputs (rad); the first 2000 s after training are also
reported when the run is long enough (the default 3500 s is).

* ours: ``tumblenav.estimators.ukf_gp.train_feature_models`` (all five features, 4 period
  candidates, 2 worker processes); wall time of the call, median of ``--repeats``.
* GPy (the library Kabir 2025 used): ``GPy.util.multioutput.ICM`` with
  ``StdPeriodic * StdPeriodic`` in a ``GPCoregionalizedRegression`` (one Gaussian noise per
  output), initial periods from Kabir 2025 Algorithm 1 (``fft_period_guess``), L-BFGS
  (``model.optimize('lbfgs', max_iters=...)``; paramz passes max_iters to scipy as both
  maxiter and maxfun, so it caps the likelihood evaluations).  Outputs centred and divided by one common
  scale (as ours).  GPy's StdPeriodic is ``exp(-0.5 sin^2(pi tau/P) / l_GPy^2)``, Kabir's
  ``exp(-2 sin^2(pi tau/P) / l^2)``: ``l_GPy = l / 2``.  The two kernel variances are fixed to
  1 (they multiply B and are not identifiable apart from it).  One GPy model costs minutes
  (an exact likelihood on N D = 4500 values per evaluation), so ``--gpy-models K`` trains the
  first K features only and scales the time to five models (printed as extrapolated).

GPy is a benchmark-only dependency (the ``bench`` extra); a separate venv keeps it apart::

    python -m venv /tmp/gpyvenv
    /tmp/gpyvenv/bin/pip install -e . 'GPy>=1.15,<2'   # 1.15 is the first to support numpy 2
    /tmp/gpyvenv/bin/python benchmarks/gp_training.py --gpy-models 1

Without GPy the script reports ours and prints nan for the GPy fields.

Usage: python benchmarks/gp_training.py [--seed 0] [--gpy-models 5] [--gpy-max-iters 200]
Last line: ``gp_train_s=<ours, five models> gpy_train_s=<GPy, five models> ratio=<gpy/ours>
rmse=<ours, five features> gpy_rmse=<GPy, its K features>``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tumblenav.estimators.gp import ELL0, fft_period_guess
from tumblenav.estimators.ukf_gp import train_feature_models
from tumblenav.frontends.projections import normalised
from tumblenav.scenario import load_scenario
from tumblenav.sensors.stereo import project
from tumblenav.simulation import simulate

T_TRAIN = 1500.0
SIGMA_P = 1e-5
WINDOWS = (1500.0, 2000.0)  # prediction windows after T_train (s)


def make_data(seed: int, duration: float):
    """Times, noisy ``[u_R, v_R, u_L]`` (n, N, 3) and the noise-free ones (rad)."""
    sc = load_scenario("kabir2025").with_updates(
        **{"occlusion.loss_from_s": None, "duration_s": duration}
    )
    truth, meas = simulate(sc, seed)
    w, _ = normalised(meas)
    uv, _ = project(meas.rig, truth.features_C)  # (n, 2, N, 2), camera 0 = left
    cams = meas.rig.cameras
    f = np.array([c.focal_px for c in cams])[:, None, None]
    pp = np.array([c.principal_point_px for c in cams])[:, None, :]
    x = (uv - pp) / f
    wt = np.concatenate([x[:, 1], x[:, 0]], axis=-1)  # as normalised(): right, then left
    return np.asarray(meas.t, float), w[..., :3], wt[..., :3]


def rmse(err) -> float:
    return float(np.sqrt(np.mean(np.square(err))))


def window_rmses(t, pred, truth) -> list[float]:
    """RMSE per prediction window after T_train (nan where the run is too short)."""
    out = []
    for span in WINDOWS:
        sel = (t > T_TRAIN) & (t <= T_TRAIN + span)
        full = t[-1] >= T_TRAIN + span - 1e-9
        out.append(rmse(pred[sel] - truth[sel]) if full else float("nan"))
    return out


def noise_guess(y) -> float:
    """Noise std of one series from third differences (white noise passes with gain 20)."""
    return float(max(np.median(np.abs(np.diff(y, 3))) / 0.6745 / np.sqrt(20.0), 1e-9))


def scalar(param) -> float:
    """A GPy parameter of shape (1,) as a float (numpy 2 refuses float() on 1-d arrays)."""
    return float(np.asarray(param).ravel()[0])


def fit_gpy(GPy, t, Y, max_iters: int, rank: int):
    """Kabir 2025's GP in GPy on ``Y`` (N, 3); returns (predict(t) -> (n, 3), info)."""
    t0 = time.perf_counter()
    N, D = Y.shape
    mean = Y.mean(axis=0)
    scale = float(np.sqrt(np.mean((Y - mean) ** 2)))
    Yn = (Y - mean) / scale
    origin = t[0]
    tc = t - origin
    P1, P2 = fft_period_guess(tc, Yn)[0]  # Kabir 2025 Algorithm 1's choice
    k1 = GPy.kern.StdPeriodic(1, variance=1.0, period=P1, lengthscale=ELL0[0] / 2.0, name="per1")
    k2 = GPy.kern.StdPeriodic(1, variance=1.0, period=P2, lengthscale=ELL0[1] / 2.0, name="per2")
    k1.variance.fix()
    k2.variance.fix()
    # B = W W^T + diag(kappa) starts at the data covariance (the signal dominates the noise)
    C = np.cov(Yn.T)
    ev, V = np.linalg.eigh(C)
    ev, V = ev[::-1], V[:, ::-1]
    W = V[:, :rank] * np.sqrt(np.maximum(ev[:rank], 1e-12))
    kappa = np.maximum(np.diag(C - W @ W.T), 1e-3 * np.trace(C) / D)
    kern = GPy.util.multioutput.ICM(
        input_dim=1, num_outputs=D, kernel=k1 * k2, W_rank=rank, W=W, kappa=kappa
    )
    X = tc[:, None]
    # noise set at construction: every later parameter change re-runs the exact inference
    liks = [
        GPy.likelihoods.Gaussian(variance=noise_guess(Yn[:, j]) ** 2, name=f"Gaussian_noise_{j}")
        for j in range(D)
    ]
    m = GPy.models.GPCoregionalizedRegression(
        [X] * D, [Yn[:, [j]] for j in range(D)], kernel=kern, likelihoods_list=liks
    )
    m.optimize("lbfgs", max_iters=max_iters)
    train_s = time.perf_counter() - t0
    run = m.optimization_runs[-1]
    per1, per2 = k1, k2  # GPy flattens the product: m.kern.parts is [per1, per2, B]
    info = {
        "train_s": train_s,
        "periods": (scalar(per1.period), scalar(per2.period)),
        "lengthscales_kabir": (2.0 * scalar(per1.lengthscale), 2.0 * scalar(per2.lengthscale)),
        "noise_std_rad": [
            np.sqrt(scalar(lk.variance)) * scale for lk in m.likelihood.likelihoods_list
        ],
        "nfev": int(getattr(run, "funct_eval", -1)),
        "status": str(getattr(run, "status", "")),
        "init_periods": (float(P1), float(P2)),
    }

    def predict(tp):
        Xp = (np.asarray(tp, float) - origin)[:, None]
        out = np.empty((len(tp), D))
        for j in range(D):
            idx = np.full((len(tp), 1), j)
            mu, _ = m.predict(np.hstack([Xp, idx]), Y_metadata={"output_index": idx})
            out[:, j] = mu[:, 0] * scale + mean[j]
        return out

    return predict, info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=3500.0, help="simulated span (s)")
    ap.add_argument("--repeats", type=int, default=3, help="timings of ours (median)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--gpy-models", type=int, default=5, help="features trained with GPy")
    ap.add_argument("--gpy-max-iters", type=int, default=200)
    ap.add_argument("--gpy-rank", type=int, default=3, help="W_rank of GPy's ICM (3 = full)")
    args = ap.parse_args()

    t, w, wt = make_data(args.seed, args.duration)
    train = t <= T_TRAIN
    n_feat = w.shape[1]
    print(
        f"kabir2025 seed {args.seed}: {n_feat} features, {train.sum()} training epochs "
        f"(t <= {T_TRAIN:.0f} s), prediction to {t[-1]:.0f} s"
    )

    # --- ours ------------------------------------------------------------------------------
    times, models = [], None
    for _ in range(max(args.repeats, 1)):
        t0 = time.perf_counter()
        models = train_feature_models(
            t[train], w[train], SIGMA_P, candidates=4, workers=args.workers
        )
        times.append(time.perf_counter() - t0)
    ours_s = float(np.median(times))
    ours_pred = np.full(wt.shape, np.nan)
    for i, m in enumerate(models):
        if isinstance(m, str):
            print(f"ours feature {i}: no model ({m})")
            continue
        ours_pred[:, i, :] = m.predict(t)[0]
        r = window_rmses(t, ours_pred[:, i], wt[:, i])
        print(
            f"ours feature {i}: {m.train_time_s:.2f} s in its worker, "
            f"{m.info['nfev']} evaluations, ok={m.ok}, periods "
            f"{m.periods_s[0]:.2f}/{m.periods_s[1]:.2f} s, rmse {r[0]:.3e} rad "
            f"(2000 s: {r[1]:.3e})"
        )
    ours_r = window_rmses(t, ours_pred, wt)
    print(
        f"ours: {ours_s:.2f} s for {n_feat} models (median of {len(times)}: "
        + ", ".join(f"{x:.2f}" for x in times)
        + f"; {args.workers} workers), rmse {ours_r[0]:.3e} rad (2000 s: {ours_r[1]:.3e})"
    )

    # --- GPy -------------------------------------------------------------------------------
    gpy_s = gpy_rmse = float("nan")
    try:
        import GPy
    except ImportError:
        GPy = None
        print("GPy not installed: see the module docstring for the benchmark venv")
    if GPy is not None:
        K = max(1, min(args.gpy_models, n_feat))
        per, gpy_pred = [], np.full((len(t), K, 3), np.nan)
        for i in range(K):
            predict, info = fit_gpy(GPy, t[train], w[train, i], args.gpy_max_iters, args.gpy_rank)
            per.append(info["train_s"])
            gpy_pred[:, i] = predict(t)
            r = window_rmses(t, gpy_pred[:, i], wt[:, i])
            print(
                f"GPy {GPy.__version__} feature {i}: {info['train_s']:.1f} s, {info['nfev']} "
                f"evaluations ({info['status']}), periods {info['init_periods'][0]:.2f}/"
                f"{info['init_periods'][1]:.2f} -> {info['periods'][0]:.2f}/"
                f"{info['periods'][1]:.2f} s, l (Kabir) {info['lengthscales_kabir'][0]:.3g}/"
                f"{info['lengthscales_kabir'][1]:.3g}, noise "
                + "/".join(f"{s:.2e}" for s in info["noise_std_rad"])
                + f" rad, rmse {r[0]:.3e} rad (2000 s: {r[1]:.3e})"
            )
            if "Maximum" in info["status"]:
                print(
                    f"  GPy stopped at --gpy-max-iters {args.gpy_max_iters} before converging: "
                    "its time is a lower bound and its model may be undertrained"
                )
        gpy_r = window_rmses(t, gpy_pred, wt[:, :K])
        gpy_rmse = gpy_r[0]
        gpy_s = float(np.sum(per)) * n_feat / K
        same = window_rmses(t, ours_pred[:, :K], wt[:, :K])
        note = (
            ""
            if K == n_feat
            else (f" EXTRAPOLATED from {K} model(s) ({np.sum(per):.1f} s) x {n_feat}/{K}")
        )
        print(f"GPy: {gpy_s:.1f} s for {n_feat} models{note}")
        print(
            f"on GPy's {K} feature(s): rmse ours {same[0]:.3e} vs GPy {gpy_r[0]:.3e} rad "
            f"(2000 s: {same[1]:.3e} vs {gpy_r[1]:.3e})"
        )
    ratio = gpy_s / ours_s
    print(
        f"gp_train_s={ours_s:.2f} gpy_train_s={gpy_s:.1f} ratio={ratio:.1f} "
        f"rmse={ours_r[0]:.3e} gpy_rmse={gpy_rmse:.3e}"
    )


if __name__ == "__main__":
    main()
