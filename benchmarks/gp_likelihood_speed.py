"""Cost of one GP likelihood-and-gradient evaluation (``tumblenav.estimators.gp``) and, with
``--ukf-gp``, of one whole ``ukf-gp`` run.

The data of ``benchmarks/gp_training.py`` (kabir2025, seed 0, feature 0, T_train = 1500 s at
1 Hz, [u_R, v_R, u_L]), normalised; one evaluation of ``nll_and_grad`` with the feature sets
of two lengthscale floors (0.8 x the start (1, 2): R = 323, and (0.8, 5): R = 211), one BLAS
thread as in training; best of 5 repeats of 20 evaluations.

``--ukf-gp``: one run of ``ukf-gp`` on the built-in kabir2025 as a campaign makes it (run 0 of
its Monte Carlo seed: the GP trained on 1500 s of five features, then the UKF's two passes over
3000 s), CPU time on one thread (BLAS, numba, OpenMP), the least of ``--repeats`` runs (the
machine may be shared); also the GP training alone and the two UKF passes (the run's own
``run_ukf`` calls, replayed). A first run compiles the numba kernels (cached on disk after).
Measured on the 2-core development machine (the other core busy), before -> after the
compiled loops and the likelihood's memory (gp/compiled.py, gp/likelihood.py ``_Objective``,
kabir2025/kernels.py): ``eval_ms_R323`` 13.6 -> 8.2 (5.4 on a quieter machine),
``ukf_gp_run_cpu_s`` 32.2 -> 19.0, ``gp_train_cpu_s`` 26.9 -> 17.6, ``ukf_passes_cpu_s`` 4.67
-> 0.97 (a fresh process per run: 36-39 s -> 19-20 s); every fitted GP the same to the last
bit, the filter's x and P equal to rounding.

Usage: python benchmarks/gp_likelihood_speed.py [--ukf-gp] [--repeats 2]
Last line: ``eval_ms_R323=<ms> eval_ms_R211=<ms>`` (with ``--ukf-gp`` followed by
``ukf_gp_run_cpu_s=<s> gp_train_cpu_s=<s> ukf_passes_cpu_s=<s>``)
"""

from __future__ import annotations

import argparse
import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # before numpy / numba load: one thread, as a campaign

import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402
from gp_training import make_data  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from tumblenav.estimators import gp  # noqa: E402


def likelihood_ms() -> dict[int, float]:
    t, w, _ = make_data(0, 3500.0)
    sel = t <= 1500.0
    Y, tt = w[sel, 0, :], t[sel] - t[0]
    Yn = (Y - Y.mean(0)) / Y.std()
    theta = gp._initial_theta(Yn, (441.0, 41.57), 1e-4)
    out = {}
    for ell in ((0.8, 1.74), (0.8, 5.0)):
        feat = gp._Features.build(np.array(ell))
        with threadpool_limits(limits=1, user_api="blas"):
            gp.nll_and_grad(theta, tt, Yn, feat)
            best = np.inf
            for _ in range(5):
                t0 = time.perf_counter()
                for _ in range(20):
                    gp.nll_and_grad(theta, tt, Yn, feat)
                best = min(best, (time.perf_counter() - t0) / 20 * 1e3)
        out[feat.R] = best
        print(f"lengthscale floor {ell}: R = {feat.R}, {best:.2f} ms per evaluation")
    return out


def ukf_gp_cpu(repeats: int) -> tuple[float, float, float]:
    """CPU seconds (least of ``repeats``) of one ukf-gp run on kabir2025, of its GP training
    and of its two UKF passes."""
    from tumblenav.campaign.store import run_seed
    from tumblenav.estimators import base
    from tumblenav.estimators.context import context_from_scenario
    from tumblenav.estimators.kabir2025 import filter as ukf_filter
    from tumblenav.estimators.kabir2025 import observations as ukf_obs
    from tumblenav.estimators.kabir2025 import tuning as ukf_tuning
    from tumblenav.estimators.kabir2025 import ukf_gp
    from tumblenav.frontends import projections as proj
    from tumblenav.scenario import load_scenario
    from tumblenav.simulation import run_streams, simulate

    sc = load_scenario("kabir2025")
    ss = run_seed(sc.montecarlo.seed, 0)
    _, meas = simulate(sc, ss)
    ctx, est = context_from_scenario(sc), base.get("ukf-gp")
    calls: list = []
    run_ukf = ukf_filter.run_ukf

    def keep(*a, **k):
        calls.append((a, k))
        return run_ukf(*a, **k)

    w, _ = proj.normalised(meas)  # the GP's training data and noise, as ukf-gp takes them
    tun = ukf_tuning.parse_tuning(ctx.estimator.tuning, model=ukf_gp.UKFGPTuning)
    sigma_p = float(np.sqrt(np.nanmax(ukf_obs.stereo_measurements(meas, tun)[1][..., 0])))
    run_s, train_s, passes_s = [], [], []
    with threadpool_limits(limits=1), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(repeats + 1):  # the first compiles (or loads) the numba kernels
            calls.clear()
            ukf_filter.run_ukf = keep
            c0 = time.process_time()
            est.run(ctx, meas, run_streams(ss)["estimator"])
            c1 = time.process_time()
            ukf_filter.run_ukf = run_ukf
            ukf_gp.train_feature_models(np.asarray(meas.t, float), w[..., :3], sigma_p)
            c2 = time.process_time()
            for a, k in calls:
                run_ukf(*a, **k)
            c3 = time.process_time()
            if i > 0 or repeats == 0:
                run_s.append(c1 - c0)
                train_s.append(c2 - c1)
                passes_s.append(c3 - c2)
                print(
                    f"ukf-gp run {i}: {c1 - c0:.2f} s CPU (GP training {c2 - c1:.2f} s, "
                    f"{len(calls)} UKF passes {c3 - c2:.2f} s)"
                )
    return min(run_s), min(train_s), min(passes_s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ukf-gp", action="store_true", help="also time a whole ukf-gp run")
    ap.add_argument("--repeats", type=int, default=2, help="ukf-gp runs timed (least kept)")
    args = ap.parse_args()
    out = likelihood_ms()
    line = " ".join(f"eval_ms_R{r}={ms:.2f}" for r, ms in out.items())
    if args.ukf_gp:
        run_s, train_s, passes_s = ukf_gp_cpu(args.repeats)
        line += f" ukf_gp_run_cpu_s={run_s:.2f} gp_train_cpu_s={train_s:.2f}"
        line += f" ukf_passes_cpu_s={passes_s:.2f}"
    print(line)


if __name__ == "__main__":
    main()
