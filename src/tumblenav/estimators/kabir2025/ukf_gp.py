"""Kabir 2025's UKF-GP (Sec. 2.4, Algorithm 2): the UKF of :mod:`tumblenav.estimators.kabir2025`
kept updated through a long occlusion by multi-output GP predictions of the projections
(:mod:`tumblenav.estimators.kabir2025.gp`) and their optical flow (eq. 27), used as pseudo-measurements.

Per feature, the GP is trained on the epochs where the feature was seen by both cameras
(Kabir's ``D_i``: ``[u_R, v_R, u_L]``, eq. 26 and Table 1); wherever the feature is not
observed, its predicted ``[u_R, v_R, u_L, v_L = v_R, u_L - u_R]`` and the flow of the
predictions by eq. 27 replace the measurement (Algorithm 2, steps 4-9).  The paper trains on
``[0, T_train]`` and predicts ``(T_train, T_total]``; here that is what a scenario with
``occlusion.loss_from_s`` produces, and any other occlusion pattern works the same way.

Noise of the pseudo-measurements (tuning ``gp_variance``):

* ``fixed`` (the paper): the sensor's ``sigma_p``, ``sigma_d`` and ``sigma_flow``.
* ``predictive`` (beyond the paper): the GP's posterior variance of each predicted projection
  (plus ``(0.1 sigma_p)^2``), the sum of the two for the disparity, and ``sigma_flow`` for the
  flow.  docs/results/kabir2025.md reports whether it helps.

A GP judged badly trained (:class:`~tumblenav.estimators.kabir2025.gp.GPFit` ``ok`` False: its fitted
noise is far above the sensor's, or the fit failed) gives no pseudo-measurements: the filter
propagates that feature through the occlusion, and the history says so in
``info['gp_fallback']`` and ``skipped['gp_fallback_features']``.  Training spans shorter than
three of the fitted long periods (Kabir 2025 Sec. 3.1: ``T_train >= 3 T_p``) give a warning.
"""

from __future__ import annotations

import dataclasses
import warnings
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from tumblenav.errors import InputError
from tumblenav.estimators.base import EstimateHistory, register
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.kabir2025 import filter as ukf_filter
from tumblenav.estimators.kabir2025 import gp as gpm
from tumblenav.estimators.kabir2025 import model as ukf_model
from tumblenav.estimators.kabir2025 import observations as ukf_obs
from tumblenav.estimators.kabir2025 import tuning as ukf_tuning
from tumblenav.frontends import projections as proj
from tumblenav.measurements import STEREO_TRACKS

Array = NDArray[np.float64]


class UKFGPTuning(ukf_tuning.KabirTuning):
    """ukf-gp's keys on top of :class:`~tumblenav.estimators.ukf_tuning.KabirTuning`."""

    gp_variance: Literal["fixed", "predictive"] = Field(
        "fixed",
        description="noise of the GP pseudo-measurements: 'fixed' = the sensor's (Kabir 2025), "
        "'predictive' = the GP's posterior variance",
    )
    gp_candidates: int = Field(
        4, ge=1, le=12, description="period pairs scored before the full GP optimisation"
    )
    gp_workers: int = Field(1, ge=1, description="processes training the per-feature GPs")
    variant: Literal["additive", "mult"] = Field(
        "additive", description="the UKF under the GP: Kabir's additive one or ukf-mult's"
    )


def _fit_one(args: tuple[Array, Array, float, int]) -> gpm.GPFit | str:
    t, w, sigma_p, candidates = args
    try:
        return gpm.fit_icm_gp(t, w, candidates=candidates, sensor_noise_std=sigma_p)
    except (InputError, np.linalg.LinAlgError, ValueError) as exc:
        return str(exc)


def train_feature_models(
    t: Array,
    w: Array,
    sigma_p: float,
    candidates: int = 4,
    workers: int = 1,
) -> list[gpm.GPFit | str]:
    """One multi-output GP per feature on its observed epochs (Kabir 2025 Algorithm 2 step 3).

    Parameters
    ----------
    t : (n,) s.  w : (n, N, 3) ``[u_R, v_R, u_L]`` (rad), NaN where not observed.
    sigma_p : the sensor's projection noise (rad), for the badly-trained check.
    workers : processes (the features are independent).

    Returns
    -------
    list
        Per feature a :class:`~tumblenav.estimators.kabir2025.gp.GPFit`, or a string saying why no
        model could be trained (too few samples, no periodicity, ...).
    """
    jobs = []
    for i in range(w.shape[1]):
        ok = np.all(np.isfinite(w[:, i, :]), axis=-1)
        jobs.append((t[ok], w[ok, i, :], sigma_p, candidates))
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as ex:
            return list(ex.map(_fit_one, jobs))
    return [_fit_one(j) for j in jobs]


def pseudo_measurements(
    t: Array,
    z: Array,
    R: Array,
    models: list[gpm.GPFit | str],
    tun: UKFGPTuning,
    sigma_p: float,
) -> tuple[Array, Array, list[int]]:
    """Fill every unobserved feature epoch of ``z``/``R`` (n, N, 9) with GP predictions
    (Kabir 2025 Algorithm 2 steps 4-5 and eq. 27); returns the features left without one."""
    z, R = z.copy(), R.copy()
    dt = float(np.median(np.diff(t)))
    fallback = []
    for i, m in enumerate(models):
        missing = ~np.isfinite(z[:, i, 0])
        if not missing.any():
            continue
        if isinstance(m, str) or not m.ok:
            fallback.append(i)
            continue
        mean, var = m.predict(t)  # (n, 3) [u_R, v_R, u_L]
        w4 = np.concatenate([mean, mean[:, 1:2]], axis=1)  # v_L = v_R (Kabir 2025 eq. 16-17)
        flow = proj.finite_difference_rate(w4, dt)  # eq. 27 over the whole predicted series
        if (
            tun.frontend.flow_edges == "drop"
        ):  # as for measured flows: only where eq. 27 is 4th order
            flow = np.where(proj.finite_difference_order(w4) == 4, flow, np.nan)
        disparity = mean[:, 2:3] - mean[:, 0:1]
        if not tun.use_disparity:  # as for the measurements (stereo_measurements)
            disparity = np.full_like(disparity, np.nan)
        zi = np.concatenate([w4, disparity, flow], axis=1)
        z[missing, i, :] = zi[missing]
        if tun.gp_variance == "predictive":
            v = var + (0.1 * sigma_p) ** 2
            vi = np.concatenate(
                [
                    v,
                    v[:, 1:2],
                    v[:, 0:1] + v[:, 2:3],
                    np.full((len(t), 4), (tun.sigma_flow_rad_s or 0.0) ** 2),
                ],
                axis=1,
            )
            R[missing, i, :] = vi[missing]
        # 'fixed': R keeps the sensor's variances, which stereo_measurements gives at every epoch
    return z, R, fallback


def _model_summary(m: gpm.GPFit | str, T_train: float) -> dict[str, Any]:
    if isinstance(m, str):
        return {"ok": False, "reason": m}
    return {
        "ok": m.ok,
        "reason": m.reason,
        "periods_s": m.periods_s.tolist(),
        "lengthscales": m.lengthscales.tolist(),
        "noise_std_rad": m.noise_std.tolist(),
        "train_time_s": m.train_time_s,
        "T_train_s": T_train,
    }


def add_disturbance_drift(
    hist: EstimateHistory, t: Array, z: Array, zp: Array, q_psd: float
) -> None:
    """The drift the GP cannot know, added to the covariance the history reports.

    The GP extrapolates the projections as they were while the features were seen; a random
    disturbance torque after that (the scenario's process noise, white angular acceleration of
    spectral density ``q_psd``, the largest axis's) turns the target away from that
    extrapolation by a random walk: after ``T`` s without a real measurement, per axis, rate
    variance ``q T`` and attitude variance ``q T^3 / 3``. Pseudo-measurements repeated every
    epoch with that common, slowly growing error would otherwise shrink the covariance far
    below it (measured: kabir2025 with a 1e-12 rad^2/s^3 disturbance, attitude error 1.4 deg
    against a 3-sigma of 0.03 deg, NEES/dof 1.3e5). The drift is independent of the GP's
    information, so its covariance adds to the filter's; only the diagonal blocks are added:
    the expected NEES of the drift, ``trace(D^-1 P_drift)``, is the same as with its
    rate-attitude correlation. tumblenav addition (Kabir 2025's truth is torque-free)."""
    if q_psd <= 0.0 or hist.P is None or len(t) != hist.P.shape[0]:
        return
    real = np.any(np.isfinite(z[..., 0]), axis=1)
    pseudo = np.any(np.isfinite(zp[..., 0]) & ~np.isfinite(z[..., 0]), axis=1) & ~real
    if not pseudo.any():
        return
    last = np.maximum.accumulate(np.where(real, np.arange(len(t)), 0))
    T = np.where(pseudo, t - t[last], 0.0)
    lay = hist.layout
    ia, ir = lay.err("attitude"), lay.err("rate")
    for k in np.flatnonzero(pseudo):
        P = hist.P[k]
        P[ir, ir] += q_psd * T[k] * np.eye(3)
        P[ia, ia] += q_psd * T[k] ** 3 / 3.0 * np.eye(3)


class KabirUKFGP:
    name = "ukf-gp"
    consumes: tuple[str, ...] = (STEREO_TRACKS,)  # the measurement types it runs on
    needs = (
        "as ukf; the GP is trained on each feature's observed epochs and replaces its "
        "measurements wherever it is not observed"
    )
    description = (
        "Kabir 2025: UKF fed by multi-output GP predictions (ICM, product of periodic kernels) "
        "through long occlusions"
    )

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        ukf_model.check_scenario(scenario)
        ukf_tuning.parse_tuning(scenario.estimator.tuning, model=UKFGPTuning)

    def run(self, scenario: Any, measurements: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        ukf_model.check_scenario(scenario)
        tun = ukf_tuning.parse_tuning(scenario.estimator.tuning, model=UKFGPTuning)
        assert isinstance(tun, UKFGPTuning)
        t = np.asarray(measurements.t, float)
        geom = ukf_model.geometry(scenario, t, measurements)
        z, R = ukf_obs.stereo_measurements(measurements, tun)
        w, _ = proj.normalised(measurements)
        sigma_p = float(np.sqrt(np.nanmax(R[..., 0])))
        models = train_feature_models(t, w[..., :3], sigma_p, tun.gp_candidates, tun.gp_workers)
        summaries = []
        for i, m in enumerate(models):
            seen = t[np.all(np.isfinite(w[:, i, :3]), axis=-1)]
            T_train = float(seen[-1] - seen[0]) if len(seen) else 0.0
            summaries.append(_model_summary(m, T_train))
            if not isinstance(m, str) and m.ok and T_train < 3.0 * float(m.periods_s.max()):
                warnings.warn(
                    f"feature {i}: GP trained on {T_train:.0f} s, less than 3 of its longest "
                    f"period ({m.periods_s.max():.0f} s); Kabir 2025 Sec. 3.1 needs T_train >= "
                    "3 T_p for reliable long predictions",
                    stacklevel=2,
                )
        prep = ukf_filter.prepare(scenario, t, z, R, geom, tun)
        tun_r = prep.tuning
        assert isinstance(tun_r, UKFGPTuning)
        zp, Rp, fallback = pseudo_measurements(t, z, prep.R_diag, models, tun_r, sigma_p)
        prep = dataclasses.replace(prep, R_diag=Rp)
        hist = ukf_filter.run_ukf(scenario, t, zp, Rp, tun.variant, tun_r, geom, prepared=prep)
        q_psd = float(tun_r.q_omega_var or 0.0) / float(np.median(np.diff(t))) if len(t) > 1 else 0
        add_disturbance_drift(hist, t, z, zp, q_psd)
        for line in prep.warnings:
            warnings.warn(line, stacklevel=2)
        hist.skipped["gp_fallback_features"] = len(fallback)
        hist.info["gp"] = summaries
        hist.info["gp_fallback"] = fallback
        if fallback:
            warnings.warn(
                f"no usable GP for feature(s) {fallback}: pure propagation for them during the "
                "occlusion",
                stacklevel=2,
            )
        return hist


register("ukf-gp")(KabirUKFGP)
