"""Cost of one GP likelihood-and-gradient evaluation (``tumblenav.estimators.gp``).

The data of ``benchmarks/gp_training.py`` (kabir2025, seed 0, feature 0, T_train = 1500 s at
1 Hz, [u_R, v_R, u_L]), normalised; one evaluation of ``nll_and_grad`` with the feature sets
of two lengthscale floors (0.8 x the start (1, 2): R = 323, and (0.8, 5): R = 211), one BLAS
thread as in training; best of 5 repeats of 20 evaluations.

Usage: python benchmarks/gp_likelihood_speed.py
Last line: ``eval_ms_R323=<ms> eval_ms_R211=<ms>``
"""

from __future__ import annotations

import time

import numpy as np
from gp_training import make_data
from threadpoolctl import threadpool_limits

from tumblenav.estimators import gp


def main() -> None:
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
    print(" ".join(f"eval_ms_R{r}={ms:.2f}" for r, ms in out.items()))


if __name__ == "__main__":
    main()
