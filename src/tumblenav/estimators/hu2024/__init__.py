"""Hu 2024 error-state EKF with the DPACF attitude measurement (``ekf-dpacf``), and the same
filter without DPACF (``ekf-baseline``, principal frame left free as Aghili & Parsa 2009).

State (Hu 2024 eq. 24) ``x = [q_TI, omega_TI_T, p, r_L, v_L, f_1..f_N]`` with Hu's inertia
ratios ``p = [(Iy-Iz)/Ix, (Iz-Ix)/Iy, (Ix-Iy)/Iz]`` (eq. 19); error state (eq. 26)
``dx = [dtheta, domega, dp, dr, dv, df_1..df_N]``, ``q = exp(dtheta) (x) q_hat`` (eq. 27 in
tumblenav's Hamilton convention: the JPL sign of Hu's eq. 27/29/35 flips, see
:mod:`tumblenav.rotations`).

Error dynamics (Hu 2024 eq. 28-30, re-derived for the Hamilton error)::

    dtheta' = -[omega x] dtheta - domega        (Hu eq. 29 prints +I for the JPL error)
    domega' = M(omega, p) domega + N(omega) dp + J(p) n_r
    dr' = dv,   dv' = E1 dr + E2 dv + n_t       (Hu eq. 4-5)

Measurements: the DPACF attitude ``y0 = q_TI`` (eq. 31, front end
:mod:`tumblenav.frontends.stereo_points`) with ``H0 = [I3 0 ...]``, and every triangulated
feature in L (eq. 32) ``y_i = r + R_LT f_i`` with ``dy_i/dtheta = R_LT [f_i x]``
(Hu eq. 35 prints ``-R[f x]`` for the JPL error), ``dy_i/dr = I``, ``dy_i/df_i = R_LT``.

Discretisation: ``Phi = exp(F dt)`` (eq. 38) by a 4th-order series (|F dt| = 0.10 at 10 Hz
for hu2024 because of the -I block: 9e-11 from ``expm`` at 0.1 rad/s, 5e-8 at 0.5 rad/s) and
``Q_k`` (eq. 39) by the Van Loan series to third order in dt (the attitude block starts at
dt^3, so its relative error is of order |F dt|: 0.3% for hu2024); nominal attitude and
rate by RK4. Update: Joseph form (eq. 41), gain eq. 42, multiplicative quaternion update
(eq. 44), and beyond the paper a per-feature chi-square innovation gate (rejections counted).

The package, one idea a module: :mod:`.tuning` (the settings and their defaults),
:mod:`.model` (layout, dynamics, propagation, the feature measurement, the inertia
constraint), :mod:`.init` (the start), :mod:`.frame` (the DPACF frame's branch and its
'consider' error model), :mod:`.update` (the measurement updates), :mod:`.filter` (the front
end's view, the steps on a frozen belief folded per run, :func:`run_filter`) and
:mod:`.kernels` (the compiled fold, used by campaigns).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from tumblenav.errors import InputError
from tumblenav.estimators.base import EstimateHistory, register
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.hu2024.filter import histories, run_filter
from tumblenav.estimators.hu2024.tuning import parse_tuning
from tumblenav.measurements import STEREO_TRACKS

__all__ = ["HuEKF", "histories", "parse_tuning", "run_filter"]


def _check_size(measurements: Any, name: str) -> None:
    """Refuse a run whose covariance history cannot fit in this machine's memory: the state
    carries 3 coordinates per feature tracked and a run keeps one covariance per epoch."""
    uv = getattr(measurements, "uv", None)
    if uv is None:
        return
    n_features = int(np.shape(uv)[2])
    dim = 13 + 3 * n_features
    epochs = len(measurements.t)
    need = epochs * dim * dim * 8.0
    try:
        have = float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return
    if need > have:
        raise InputError(
            f"{name} on {n_features} features keeps a {dim} x {dim} covariance per epoch: "
            f"{epochs} epochs need ~{need / 2**30:.0f} GiB, this machine has "
            f"{have / 2**30:.0f} GiB; use fewer features or a shorter run"
        )


class HuEKF:
    """Shared implementation of ekf-dpacf and ekf-baseline."""

    consumes: tuple[str, ...] = (STEREO_TRACKS,)  # the measurement types it runs on
    needs = "stereo feature tracks (stereo sensor)"
    compiled = True  # numba kernels: campaigns warm them up before forking their workers

    def __init__(self, use_dpacf: bool) -> None:
        self.use_dpacf = use_dpacf
        self.name = "ekf-dpacf" if use_dpacf else "ekf-baseline"
        self.description = (
            "Hu 2024: inertia least squares + unique principal frame (DPACF) + error-state EKF"
            if use_dpacf
            else "Hu 2024's EKF without DPACF (principal frame free, Aghili & Parsa 2009)"
        )

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        if scenario.sensor.kind != "stereo":
            raise InputError(
                f"{self.name} needs a stereo sensor; scenario {scenario.name} has "
                f"a {scenario.sensor.kind} sensor"
            )
        noise = scenario.sensor.noise
        if not (noise.angular_rad or noise.pixels):
            raise InputError(
                f"sensor.noise is 0: {self.name} weights the triangulated features by the "
                "sensor's noise and cannot weigh exact measurements; give the sensor's noise "
                "(it may be tiny, e.g. angular_rad: 1.0e-7)"
            )
        parse_tuning(scenario.estimator.tuning, self.use_dpacf)

    def run(self, scenario: Any, measurements: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        self.check(scenario)
        _check_size(measurements, self.name)
        return histories(run_filter(scenario, [measurements], self.use_dpacf), scenario)[0]

    def run_batch(
        self, scenario: Any, measurements: list, rngs: list, p_every: int = 1
    ) -> list[EstimateHistory]:
        """Many runs at once (vectorised); the same histories as :meth:`run`, with the
        covariance reported every ``p_every`` epochs (NaN in between)."""
        scenario = context_from_scenario(scenario)  # never the target's truth
        self.check(scenario)
        res = run_filter(scenario, measurements, self.use_dpacf, p_every=p_every)
        return histories(res, scenario)


register("ekf-dpacf")(lambda: HuEKF(True))
register("ekf-baseline")(lambda: HuEKF(False))
