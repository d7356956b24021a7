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
    gp_drift_in_r: bool = Field(
        True,
        description="add the disturbance drift the GP cannot know (from the scenario's process "
        "noise) to the pseudo-measurements' R (a second filter pass); false: the paper's R",
    )
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
        # (n, 3) [u_R, v_R, u_L]; the posterior variance only where it is the noise
        mean, var = m.predict(t, variance=tun.gp_variance == "predictive")
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


def drift_covariance(
    hist: EstimateHistory, t: Array, z: Array, zp: Array, q_psd: float
) -> tuple[Array, Array] | None:
    """The drift the GP cannot know: (n, 6, 6) covariance over the rate and attitude errors
    (zero outside the pseudo-measurement epochs) and the indices of those errors in ``P``.

    The GP extrapolates the projections as they were while the features were seen; a random
    disturbance torque after that (the scenario's process noise, white angular acceleration of
    spectral density ``q_psd`` per axis, as the filter's Q) turns the target away from that
    extrapolation. Its covariance ``D`` over the rate and attitude errors starts at zero at
    the last real measurement and is propagated through the rigid-body dynamics linearised
    along the estimate (Kabir 2025 eq. 8-10, Jacobian by finite differences)::

        D_k = F_k D_{k-1} F_k^T + Q_k,   Q_k = q_psd dt I (rate)

    so that a changed rate also shifts the polhode's phase (body-rate errors growing much
    faster than ``sqrt(q T)``: measured 5e-4 rad/s after 1500 s at 1e-12 rad^2/s^3, where
    ``sqrt(q T)`` = 4e-5). The pseudo-measurements cannot see this drift (the GP extrapolates
    without it, and its error is common to every feature and epoch), so ``D`` is independent
    of the filter's information and adds to its covariance (a consider term).
    tumblenav addition (Kabir 2025's truth is torque-free)."""
    if q_psd <= 0.0 or hist.P is None or len(t) != hist.P.shape[0]:
        return None
    real = np.any(np.isfinite(z[..., 0]), axis=1)
    pseudo = np.any(np.isfinite(zp[..., 0]) & ~np.isfinite(z[..., 0]), axis=1) & ~real
    if not pseudo.any():
        return None
    lay = hist.layout
    nr, na, nk = lay.nom("rate"), lay.nom("attitude"), lay.nom("inertia")
    idx = np.r_[np.arange(lay.dim)[lay.err("rate")], np.arange(lay.dim)[lay.err("attitude")]]
    eps = 1e-6
    ks = np.flatnonzero(pseudo[1:]) + 1
    x = hist.x[ks - 1]  # (m, nom) the estimate the step starts from
    dX = np.zeros((len(ks), 7, lay.dim))
    dX[:, 1:, idx] = eps * np.eye(6)
    X = lay.boxplus(np.repeat(x[:, None, :], 7, axis=1), dX)
    dts = (t[ks] - t[ks - 1])[:, None]
    ok = np.all(np.isfinite(x), axis=1)
    F = np.zeros((len(ks), 6, 6))
    for dt in np.unique(dts):  # one batch per step length (one at a constant rate)
        sel = (dts[:, 0] == dt) & ok
        if not sel.any():
            continue
        w1, q1 = ukf_model.propagate_rotation(X[sel][..., nr], X[sel][..., na], X[sel][..., nk], dt)
        X1 = X[sel].copy()
        X1[..., nr] = w1
        X1[..., na] = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
        E = lay.boxminus(X1[:, 1:], X1[:, :1])[..., idx] / eps  # (m, perturbation j, error)
        F[sel] = np.swapaxes(E, 1, 2)
    out = np.zeros((len(t), 6, 6))
    D = np.zeros((6, 6))
    prev = -1
    for j, k in enumerate(ks.tolist()):
        if prev != k - 1:  # a real measurement in between: the GP's extrapolation restarts
            D = np.zeros((6, 6))
        prev = k
        if ok[j]:
            D = F[j] @ D @ F[j].T
        D[:3, :3] += q_psd * float(t[k] - t[k - 1]) * np.eye(3)
        out[k] = D
    return out, idx


def add_disturbance_drift(
    hist: EstimateHistory, t: Array, z: Array, zp: Array, q_psd: float
) -> None:
    """:func:`drift_covariance` added to the covariance the history reports (in place)."""
    r = drift_covariance(hist, t, z, zp, q_psd)
    if r is not None and hist.P is not None:
        D, idx = r
        hist.P[:, idx[:, None], idx[None, :]] += D


def drift_variance_of_pseudo(
    hist: EstimateHistory, D: Array, rho0_C: Array, z: Array, zp: Array
) -> Array:
    """(n, N, 9) variance the drift ``D`` (:func:`drift_covariance`) gives each GP
    pseudo-measurement component, 0 elsewhere: a turn ``dtheta`` of the target moves feature
    ``i`` by ``dtheta x rho_i``, i.e. its projections by about ``|rho_i| / |rho_0|`` times one
    axis of ``dtheta`` (``trace(D_att) / 3``), its flows by that times the rate's drift and
    ``|omega| dtheta``. Added to the pseudo-measurements' R, it stops their common error from
    being read as information on the rigid parameters (inertia, features), which it pulled to
    5x their sigma (kabir2025 at 1e-12 rad^2/s^3: features NEES/dof 173 -> 0.2).
    tumblenav addition."""
    lay = hist.layout
    n, N = z.shape[:2]
    f = hist.x[:, lay.nom("features")].reshape(n, N, 3)
    s2 = np.sum(f**2, axis=-1) / np.sum(np.asarray(rho0_C) ** 2, axis=-1)[:, None]  # (n, N)
    var_att = np.trace(D[:, 3:, 3:], axis1=1, axis2=2) / 3.0
    var_rate = np.trace(D[:, :3, :3], axis1=1, axis2=2) / 3.0
    w2 = np.sum(hist.x[:, lay.nom("rate")] ** 2, axis=-1)
    out = np.zeros(z.shape)
    out[..., :5] = (s2 * var_att[:, None])[..., None]
    out[..., 5:] = (s2 * (var_rate + w2 * var_att)[:, None])[..., None]
    pseudo = np.isfinite(zp) & ~np.isfinite(z)
    return np.where(pseudo & np.isfinite(out), out, 0.0)


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
        drift = drift_covariance(hist, t, z, zp, q_psd)
        if drift is not None and tun.gp_drift_in_r:
            # second pass: the pseudo-measurements' R carries the drift of the first pass's
            # trajectory (the linearisation point; the GP predictions are the same)
            Rp = Rp + drift_variance_of_pseudo(hist, drift[0], geom.rho0_C, z, zp)
            prep = dataclasses.replace(prep, R_diag=Rp)
            hist = ukf_filter.run_ukf(scenario, t, zp, Rp, tun.variant, tun_r, geom, prepared=prep)
            drift = drift_covariance(hist, t, z, zp, q_psd)
        if drift is not None and hist.P is not None:
            hist.P[:, drift[1][:, None], drift[1][None, :]] += drift[0]
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
