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

What the pseudo-measurements' error is (tuning ``gp_drift_in_r``, default true; tumblenav
addition, issue 18: Kabir 2025's truth is torque-free, ours carries the scenario's random torque):

* They are made from the training data the filter has already used, so they carry no new
  information on the rigid parameters: wherever no feature is really measured, the inertia
  ratios and features are consider parameters (Schmidt update, no process noise on them;
  :func:`~tumblenav.estimators.kabir2025.filter.run_ukf`'s ``consider``). Updating them pulled
  the features 200 sigma onto the GPs' extrapolation (kabir2025: features NEES/dof 136).
  Frozen, they keep the error of their last estimate, whose covariance is not the filter's:
  the filter's Q floor on them (:func:`~.tuning.derive_tuning`) is a random walk the rigid
  truth does not have, and a filter with more Q than the truth reports more than its error
  (kabir2025 before the loss: features NEES/dof 0.41-0.45, inertia 0.28). Where they are
  frozen they are reported with the actual error covariance under the filter's gains
  (:func:`rigid_floor_correction`; against it, before the loss: features 1.05-1.11,
  inertia 1.39-1.53, rate 0.93-1.42, attitude 1.13-1.63, 3 seeds).
* Their error common to every feature is a motion: the truth's departure from the torque-free
  motion the GPs fitted over the whole training span (:func:`gp_motion_covariance`). The
  filter follows it (a rigid motion explains it), so it is added to the reported covariance of
  the rate and attitude, not to R.
* The rest is each GP's own extrapolation error, measured at every epoch by the residual no
  rigid motion explains (:func:`gp_inconsistency`): it is their R in a second filter pass
  (without the sensor's noise, which the GP's mean averages out: :func:`pseudo_r`) and,
  through one epoch's least squares, goes into the reported covariance. Only the GP's own
  outputs ``[u_R, v_R, u_L]`` and their flows are used: Kabir's ``v_L = v_R``, disparity and
  ``v_L`` flow repeat them with independent variances, counting the same error twice
  (:func:`pseudo_measurements` ``copies``).
* Where a single GP predicts, nothing disagrees with it: its R is matched to the filter's
  innovations instead (:func:`_matched_single_gp`, covariance matching over the GPs' shortest
  period; tuning ``gp_single_match_passes``), so the NIS there is matched, not a test.

``gp_drift_in_r: false`` keeps the paper's filter (R as above, every state updated); the
reported covariance gets the same two terms.

A GP judged badly trained (:class:`~tumblenav.estimators.kabir2025.gp.GPFit` ``ok`` False: its fitted
noise is far above the sensor's, or the fit failed) gives no pseudo-measurements: the filter
propagates that feature through the occlusion, and the history says so in
``info['gp_fallback']`` and ``skipped['gp_fallback_features']``.  Training spans shorter than
three of the fitted long periods (Kabir 2025 Sec. 3.1: ``T_train >= 3 T_p``) give a warning.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
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
from tumblenav.estimators.kabir2025.mismatch import (  # shared with ukf, ukf-mult
    actual_map,
    analysis_setup,
    filter_update,
    floor_congruence,
    moving_q,
    write_coast,
)
from tumblenav.estimators.kabir2025.mismatch import step_jacobians as _step_jacobians
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
        description="the pseudo-measurements' error model: the GPs' own error (their "
        "disagreement no rigid motion explains) in their R (a second filter pass), only the GP's "
        "own outputs u_R, v_R, u_L and their flows (not the copies v_L, disparity), and no "
        "update of the inertia and features where nothing is really measured (consider "
        "parameters); false: the paper's R and update. Either way the reported covariance "
        "carries the fitted motion's error under the scenario's random torque and the GPs' own",
    )
    gp_single_match_passes: int = Field(
        3,
        ge=0,
        description="with gp_drift_in_r: where a single GP predicts (its own error cannot be "
        "measured by disagreement), its pseudo-measurements' R is matched to the filter's "
        "innovations: up to this many extra filter passes, each scaling that R by the last "
        "pass's NIS/dof there (covariance matching); 0: the sensor's R (the paper's)",
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


# the pseudo-measurement components that copy or difference the GP's outputs [u_R, v_R, u_L]:
# v_L (= v_R), the disparity (u_L - u_R) and v_L's flow (= v_R's)
_GP_COPIES = [3, 4, 8]


def pseudo_measurements(
    t: Array,
    z: Array,
    R: Array,
    models: list[gpm.GPFit | str],
    tun: UKFGPTuning,
    sigma_p: float,
    copies: bool = True,
) -> tuple[Array, Array, list[int]]:
    """Fill every unobserved feature epoch of ``z``/``R`` (n, N, 9) with GP predictions
    (Kabir 2025 Algorithm 2 steps 4-5 and eq. 27); returns the features left without one.

    ``copies`` False leaves out (NaN) the components that are functions of the GP's three
    outputs, not measurements of their own: ``v_L = v_R``, the disparity ``u_L - u_R`` and
    ``v_L``'s flow. Kabir gives each its own independent variance, which counts the same GP
    error twice (kabir_gp_geometry: NIS/dof 1.24 / 1.26 with them, 1.03 / 1.02 without, runs
    0-1, docs/results/consistency.md)."""
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
        if not copies:
            zi[:, _GP_COPIES] = np.nan
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


def _linearisation_path(hist: EstimateHistory, t: Array, first: int) -> Array:
    """The estimate (n, nominal) where the filter reports one, and before its start back to
    epoch ``first`` the torque-free propagation of its first estimate backwards (the GP
    trains from the first observation; the identified start comes later)."""
    lay = hist.layout
    x = np.array(hist.x, dtype=float)
    ok = np.flatnonzero(np.all(np.isfinite(x), axis=1))
    if len(ok) == 0:
        return x
    nr, na, nk = lay.nom("rate"), lay.nom("attitude"), lay.nom("inertia")
    for k in range(int(ok[0]) - 1, first - 1, -1):
        w, q = ukf_model.propagate_rotation(
            x[k + 1, nr], x[k + 1, na], x[k + 1, nk], t[k] - t[k + 1]
        )
        x[k] = x[k + 1]
        x[k, nr] = w
        x[k, na] = q / np.linalg.norm(q)
    return x


def gp_motion_covariance(
    hist: EstimateHistory,
    t: Array,
    real: NDArray[np.bool_],
    pseudo: NDArray[np.bool_],
    q_r: float,
    sigma_att: float,
) -> Array:
    """(n, 6, 6) covariance over the rate and attitude errors of the motion the GP
    extrapolates, at the pseudo-measurement epochs (zero elsewhere): the truth's departure
    from the torque-free motion the GP fitted to the training data.

    The GP is a deterministic quasi-periodic function fitted to every observed epoch at once
    (Kabir 2025 Sec. 2.3: periodic kernels, no decay in time), i.e. a torque-free motion
    fitted by least squares over the whole training span. A random disturbance torque (the
    scenario's process noise: white angular acceleration, ``q_r (I_max / I_i)^2`` about
    principal axis ``i``, :mod:`tumblenav.dynamics.disturbances`) makes the truth wander from
    any such motion: at the end of the training the fit is off by the wander it averaged
    over (rate and phase), and after it the truth keeps wandering. Both are the error of a
    filter that trusts a torque-free model (no process noise) against a truth that has it:
    over the rate, attitude and inertia ratios, linearised along the estimate (Kabir 2025
    eq. 8-10, Jacobians ``F`` by finite differences), from the first observation::

        fit (no process noise):  P_f <- F P_f F^T,            gain K from P_f, H = attitude
        its actual error:        P_a <- F P_a F^T + Q_true,   P_a <- (I-KH) P_a (I-KH)^T + K R K^T

    with the attitude "measured" at every observed epoch with ``sigma_att`` (the sensor's
    resolution on the attitude; its value hardly matters: the disturbance dominates), and no
    update at the pseudo-measurement epochs. ``P_a``'s rate and attitude block there is the
    result. Measured on kabir2025 (20 runs, 1e-12 rad^2/s^3): the GP's common rotation error
    in the loss is 6e-3 to 4.3e-2 rad rms, this model's 1-sigma 5.7e-3 to 4.7e-2 rad; a
    model started at zero at the last measurement (the truth's wander after the loss alone)
    gives 4e-5 to 2.7e-2 rad: 100x too small at the loss's start, where the pseudo-
    measurements then dragged the features by 200 sigma. tumblenav addition (Kabir 2025's
    truth is torque-free).
    """
    n = len(t)
    out = np.zeros((n, 6, 6))
    seen = np.flatnonzero(real)
    if not pseudo.any() or len(seen) == 0 or hist.P is None:
        return out
    lay = hist.layout
    E = np.arange(lay.dim)
    idx = np.r_[E[lay.err("rate")], E[lay.err("attitude")], E[lay.err("inertia")]]
    d = len(idx)
    first = int(seen[0])
    x = _linearisation_path(hist, t, first)
    ks = np.arange(first + 1, n)
    F = _step_jacobians(lay, x, t, idx, ks)
    kk = x[:, lay.nom("inertia")]
    H = np.zeros((3, d))
    H[:, 3:6] = np.eye(3)
    Rf = sigma_att**2 * np.eye(3)
    # no prior: the fit knows the motion only from the data
    Pf = np.diag([1e-2] * 3 + [1.0] * 3 + [1.0] * (d - 6))

    def fit(Pf: Array, Pa: Array) -> tuple[Array, Array]:
        S = H @ Pf @ H.T + Rf
        K = np.linalg.solve(S, H @ Pf).T
        A = np.eye(d) - K @ H
        return A @ Pf @ A.T + K @ Rf @ K.T, A @ Pa @ A.T + K @ Rf @ K.T

    Pf, Pa = fit(Pf, Pf.copy())  # the first observation
    Qc = np.zeros((d, d))
    for j, k in enumerate(ks.tolist()):
        dt = float(t[k] - t[k - 1])
        if np.all(np.isfinite(kk[k - 1])):
            m = np.exp(np.array([kk[k - 1, 0], 0.0, kk[k - 1, 1]]))  # I_i / I_2
            Qc[:3, :3] = np.diag(q_r * (m.max() / m) ** 2)
        Fj = F[j]
        Pa = Fj @ Pa @ Fj.T + 0.5 * (Fj @ Qc @ Fj.T + Qc) * dt
        Pf = Fj @ Pf @ Fj.T
        if real[k]:
            Pf, Pa = fit(Pf, Pa)
        elif pseudo[k]:
            out[k] = Pa[:6, :6]
    return out


def rigid_floor_correction(
    hist: EstimateHistory,
    t: Array,
    z: Array,
    R: Array,
    tun: ukf_tuning.KabirTuning,
    geom: Any,
) -> tuple[Array, Array]:
    """The actual error covariance of the rigid parameters (inertia ratios and features)
    against the one the filter reports, along the real measurements of ``hist``.

    The filter's Q on the rigid parameters is a floor (:func:`~.tuning.derive_tuning`,
    ``q_k_var``, ``q_feature_var``): a random walk the rigid truth does not have. A filter
    whose Q exceeds the truth's reports more than its error: for a constant estimated with a
    fictitious walk ``q`` and measurements of variance ``r``, the steady state is
    ``P = sqrt(q r)`` while the error's variance is ``P / 2`` (gain ``K = sqrt(q / r)``,
    error variance ``K r / (2 - K)``) -- measured on kabir2025 before the loss: features
    NEES/dof 0.41-0.45, inertia 0.28 (3 seeds). Where the rigid parameters are then frozen
    (ukf-gp's consider epochs) the estimate keeps that error, so its covariance is the
    actual one. Covariance analysis of the mismatched filter (Gelb 1974 Sec. 7.2), linearised
    along the estimate (Kabir 2025 eq. 8-10 for ``F``, eq. 22-23 for ``H``; finite
    differences), from the filter's covariance at its start::

        filter:  P_f <- F P_f F^T + Q,          K = P_f H^T (H P_f H^T + R)^-1,  P_f <- (I-KH) P_f
        actual:  P_a <- F P_a F^T + Q_true,     P_a <- (I-KH) P_a (I-KH)^T + K R K^T

    with ``Q_true`` = Q without the floor. Returns ``P_f`` and ``P_a`` (n, d, d) after each
    epoch (NaN before the start). tumblenav addition."""
    lay = hist.layout
    n, d = len(t), lay.dim
    Pf_out = np.full((n, d, d), np.nan)
    Pa_out = np.full((n, d, d), np.nan)
    su = analysis_setup(hist, t, z, tun, geom)
    if su is None:
        return Pf_out, Pa_out
    k0, ks, Fd, Hk, Hof, dyn = su.k0, su.ks, su.Fd, su.Hk, su.Hof, su.dyn
    Qa = np.diag(su.q_moving)
    Qf = np.diag(su.q_moving + su.q_rigid)
    Pf = np.array(hist.P[k0], dtype=float)
    Pa = Pf.copy()
    Pf_out[k0], Pa_out[k0] = Pf, Pa
    F = np.eye(d)
    for j, k in enumerate(ks.tolist()):
        F[np.ix_(dyn, dyn)] = Fd[j]
        i = Hof.get(k)
        # where nothing is really measured the filter has no Q on the rigid parameters
        # (consider epochs) and its pseudo-measurements leave them as they are
        Pf = F @ Pf @ F.T + (Qf if i is not None else Qa)
        Pa = F @ Pa @ F.T + Qa
        if i is not None:
            rows, _, Rk, K, A, Pf = filter_update(Pf, Hk[i], z[k], R[k])
            Pa = A @ Pa @ A.T + (K * Rk[rows]) @ K.T
        Pf_out[k], Pa_out[k] = Pf, Pa
    return Pf_out, Pa_out


def pseudo_jacobians(
    hist: EstimateHistory,
    geom: Any,
    ks: NDArray[Any],
    stencil_dt: float | None = None,
    eps: float = 1e-7,
) -> tuple[Array, Array]:
    """At epochs ``ks``: the predicted measurements ``h`` (m, N, 9) of the estimate (Kabir 2025
    eq. 22-23; the flow as eq. 27 of the propagated projections with ``stencil_dt``, as the
    filter predicts it with ``flow_model: stencil``) and their Jacobians (m, N, 9, 6) over
    the rate and attitude errors (the instantaneous flow's), by finite differences."""
    lay = hist.layout
    E = np.arange(lay.dim)
    idx = np.r_[E[lay.err("rate")], E[lay.err("attitude")]]
    x = hist.x[ks]
    dX = np.zeros((len(ks), 7, lay.dim))
    dX[:, 1:, idx] = eps * np.eye(6)
    X = lay.boxplus(np.repeat(x[:, None, :], 7, axis=1), dX)
    h = ukf_obs.measurement_model(
        X, geom.R_CI, geom.rho0_C[ks][:, None, :], geom.rho0_dot_C[ks][:, None, :], geom.centres_x
    )  # (m, 7, N, 9)
    J = np.moveaxis((h[:, 1:] - h[:, :1]) / eps, 1, -1)
    h0 = h[:, 0]
    if stencil_dt is not None:
        h0 = ukf_obs.stencil_measurement_model(
            x, geom.R_CI, geom.rho0_C[ks], geom.rho0_dot_C[ks], geom.centres_x, stencil_dt
        )
    return h0, J


# components of a pseudo-measurement that carry independent GP information: u_R, v_R, u_L
# (v_L = v_R and the disparity are copies) and their flows
_POS, _FLOW = np.array([0, 1, 2]), np.array([5, 6, 7])


def gp_inconsistency(
    hist: EstimateHistory,
    geom: Any,
    zp: Array,
    Rs: Array,
    pseudo: NDArray[np.bool_],
    window: int,
    stencil_dt: float | None = None,
) -> tuple[Array, Array, Array]:
    """The GPs' own extrapolation error, measured by their disagreement: at each
    pseudo-measurement epoch the residual of the features' predictions ``zp`` after the rigid
    motion (rate and attitude, weighted least squares about the estimate) that fits them best
    is what no rigid body explains -- each feature's GP extrapolates on its own (Kabir 2025
    Algorithm 2 step 3) and they drift apart (measured on kabir2025: 1e-5 to 8e-3 rad after
    the loss's start, largest 30-200 s into it). Its mean square per component (projections
    and flows apart, over the ``3N - 3`` degrees of freedom each), averaged over ``window``
    epochs, is a variance ``s2`` of every GP's error; its effect on the rate and attitude is
    that of one epoch's least squares, ``(J^T diag(1/s2) J)^-1`` -- not averaged over epochs,
    because the error is the same from one epoch to the next.

    Returns ``s2`` (n, 2) (projections rad^2, flows rad^2/s^2), ``D_b`` (n, 6, 6) and the
    Jacobians (n, N, 9, 6) at the pseudo-measurement epochs (zero elsewhere).
    tumblenav addition."""
    n, N = zp.shape[:2]
    s2 = np.zeros((n, 2))
    Db = np.zeros((n, 6, 6))
    Jall = np.zeros((n, N, 9, 6))
    ks = np.flatnonzero(pseudo & np.all(np.isfinite(hist.x), axis=1))
    if len(ks) == 0:
        return s2, Db, Jall
    h, J = pseudo_jacobians(hist, geom, ks, stencil_dt)
    Jall[ks] = J
    cols = np.r_[_POS, _FLOW]
    r = (zp[ks] - h)[:, :, cols]  # (m, N, 6)
    w = 1.0 / Rs[ks][:, :, cols]  # the sensor's variances: the weights of the rigid fit
    use = np.isfinite(r) & np.isfinite(w)
    r, w = np.where(use, r, 0.0), np.where(use, w, 0.0)
    Jc = J[:, :, cols, :].reshape(len(ks), -1, 6)
    rf, wf = r.reshape(len(ks), -1), w.reshape(len(ks), -1)
    A = np.swapaxes(Jc * wf[..., None], 1, 2) @ Jc
    A += 1e-12 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(6)
    dx = np.linalg.solve(A, np.swapaxes(Jc * wf[..., None], 1, 2) @ rf[..., None])[..., 0]
    res = (rf - (Jc @ dx[..., None])[..., 0]).reshape(len(ks), N, 6) * use
    cnt = use.reshape(len(ks), N, 2, 3).sum(axis=(1, 3))  # (m, 2) components per kind
    ss = np.sum(res.reshape(len(ks), N, 2, 3) ** 2, axis=(1, 3))
    raw = np.where(cnt > 3, ss / np.maximum(cnt - 3, 1), np.nan)
    # centred moving average over the pseudo-measurement epochs
    for j in range(2):
        okv = np.isfinite(raw[:, j])
        m = _moving_ratio(np.where(okv, raw[:, j], 0.0), okv, window)
        s2[ks, j] = np.where(np.isfinite(m), m, 0.0)
    # the effect on rate and attitude of one epoch's least squares with these variances; an
    # epoch missing a kind (no flow at the predictions' ends) keeps the previous epoch's
    floor = 1e-4 * np.nanmedian(Rs[ks][:, :, cols], axis=(1, 2))[:, None]
    vb = np.maximum(np.repeat(s2[ks], 3, axis=1), np.repeat(floor, 6, axis=1))  # (m, 6)
    wb = np.where(use, 1.0 / vb[:, None, :], 0.0).reshape(len(ks), -1)
    Ib = np.swapaxes(Jc * wb[..., None], 1, 2) @ Jc
    Ib += 1e-12 * np.trace(Ib, axis1=1, axis2=2)[:, None, None] * np.eye(6)
    Dk = np.linalg.inv(Ib)
    full = np.all(cnt > 3, axis=1)
    last = np.maximum.accumulate(np.where(full, np.arange(len(ks)), -1))
    if np.any(last >= 0):
        first = int(np.flatnonzero(last >= 0)[0])
        last = np.where(last >= 0, last, first)
        Db[ks] = Dk[last]
        s2[ks] = s2[ks][last]
    return s2, Db, Jall


def pseudo_variance(s2: Array, z: Array, zp: Array) -> Array:
    """(n, N, 9) variance to add to the pseudo-measurements' R: the GPs' own error ``s2``
    (:func:`gp_inconsistency`; projections, the disparity and flows), zero where a component
    is not a pseudo-measurement. The motion error common to every feature
    (:func:`gp_motion_covariance`) is not noise to the filter: a rigid motion explains it,
    the filter follows it, and it goes into the reported covariance instead."""
    out = np.zeros(z.shape)
    out[..., 0:4] = s2[:, None, 0:1]
    out[..., 4] = 2.0 * s2[:, None, 0]
    out[..., 5:9] = s2[:, None, 1:2]
    pseudo = np.isfinite(zp) & ~np.isfinite(z)
    return np.where(pseudo & np.isfinite(out), out, 0.0)


def pseudo_r(R: Array, extra: Array) -> Array:
    """The pseudo-measurements' variances for the second pass: the GPs' own error ``extra``
    (:func:`pseudo_variance`, > 0 exactly at the pseudo-measurement components) plus 1 % of
    the sensor's variance ``R`` there; ``R`` elsewhere. The sensor's white noise is not in a
    pseudo-measurement: the GP's posterior mean (Kabir 2025 eq. 26, over the whole training
    span) and eq. 27's flow of it average it out; the 1 % is what a mean over 100 samples
    keeps of it (as ``gp_variance: predictive``'s ``(0.1 sigma_p)^2``). With the sensor's
    variance kept in R, kabir2025's NIS/dof in 2250-3000 s was 0.58 (6 seeds), 0.97 without;
    the estimate moved by < 0.005 deg."""
    return np.where(extra > 0, extra + 0.01 * R, R)


def _gp_window(models: list[gpm.GPFit | str], dt: float) -> int:
    """Epochs over which the GPs' own error is averaged: their shortest fitted period (at
    least 10 epochs)."""
    periods = [float(np.min(m.periods_s)) for m in models if not isinstance(m, str) and m.ok]
    return max(10, int(round(min(periods, default=0.0) / dt)))


def _moving_ratio(num: Array, den: Array, window: int) -> Array:
    """Centred moving ``sum(num) / sum(den)`` over ``window`` entries (NaN where den sums to 0)."""
    half = window // 2
    c = np.concatenate([[0.0], np.cumsum(num)])
    d = np.concatenate([[0.0], np.cumsum(den)])
    i = np.arange(len(num))
    lo, hi = np.clip(i - half, 0, len(num)), np.clip(i + half + 1, 0, len(num))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(d[hi] > d[lo], (c[hi] - c[lo]) / (d[hi] - d[lo]), np.nan)


def gp_error_model(
    hist: EstimateHistory,
    scenario: Any,
    tun: UKFGPTuning,
    tun_r: ukf_tuning.KabirTuning,
    t: Array,
    real: NDArray[np.bool_],
    pseudo: NDArray[np.bool_],
    z: Array,
    zp: Array,
    Rp: Array,
    geom: Any,
    models: list[gpm.GPFit | str],
) -> tuple[Array, Array]:
    """The error of the GP pseudo-measurements along a filter run ``hist``: ``D`` (n, 6, 6)
    over the rate and attitude errors (the fitted motion's, :func:`gp_motion_covariance`,
    plus the GPs' own, :func:`gp_inconsistency`; zero outside the pseudo-measurement epochs)
    and the variance it adds to each pseudo-measurement component (n, N, 9,
    :func:`pseudo_variance`). The disturbance is the scenario's
    ``process_noise.rotational_rad2_s4`` (an explicit ``q_omega_var``: that over the step)."""
    n, N = z.shape[:2]
    if not pseudo.any() or len(t) < 2:
        return np.zeros((n, 6, 6)), np.zeros(z.shape)
    dt = float(np.median(np.diff(t)))
    window = _gp_window(models, dt)
    stencil = dt if tun_r.flow_model == "stencil" else None
    s2, Db, J = gp_inconsistency(hist, geom, zp, Rp, pseudo, window, stencil)
    if tun.q_omega_var is None:
        pn = getattr(scenario, "process_noise", None)
        q_r = float(getattr(pn, "rotational_rad2_s4", 0.0) or 0.0)
    else:
        q_r = float(np.min(ukf_tuning.rate_q(tun_r.q_omega_var))) / dt  # the largest moment
    Da = np.zeros((n, 6, 6))
    if q_r > 0:
        # the sensor's resolution on the attitude at one epoch (the fit's "measurement")
        Jp = J[pseudo][:, :, _POS, 3:6].reshape(-1, 3)
        sp2 = float(np.nanmedian(Rp[..., 0]))
        info = float(np.trace(Jp.T @ Jp)) / max(int(pseudo.sum()), 1) / (3.0 * sp2)
        sigma_att = float(np.sqrt(1.0 / info)) if info > 0 else float(np.sqrt(sp2))
        Da = gp_motion_covariance(hist, t, real, pseudo, q_r, sigma_att)
    D = Da + Db
    return D, pseudo_variance(s2, z, zp)


def _matched_single_gp(
    hist: EstimateHistory,
    rerun: Callable[[Array], EstimateHistory],
    z: Array,
    zp: Array,
    Rp: Array,
    extra: Array,
    pseudo: NDArray[np.bool_],
    passes: int,
    window: int,
) -> tuple[EstimateHistory, Array]:
    """Where a single GP predicts (no other to disagree with, so :func:`gp_inconsistency`
    cannot measure its own error), its pseudo-measurements' R is matched to the filter's
    innovations (covariance matching, Mehra 1970): each pass scales that R at each epoch by
    the NIS/dof the previous pass had over a centred ``window`` of those epochs (the GPs'
    shortest period, as :func:`gp_inconsistency` averages), up to ``passes`` (tuning
    ``gp_single_match_passes``) filter runs by ``rerun`` (R -> history) or until every scale
    is within 10 % of 1 (tumblenav's; Kabir 2025 keeps the sensor's R). The sensor's R is
    wrong there both ways: the GP's mean has averaged the sensor's noise out, and its own
    error (a phase walk of ~1e-3 rad over the 375-s window at 0.05 Hz) is mostly a motion
    the filter follows. Measured on the four one-GP runs of
    kabir_gp_rate005 (runs 3, 11, 12, 19; NIS/dof over 1125-1500 s, a session script with
    the GPs cached): the sensor's R 0.135, the GP's posterior variance plus 1 % of the
    sensor's 0.51, 1 % alone 5.1; one scale over the whole loss 0.57-0.68 (the NIS 1.3 early
    in the loss, 0.65 late); matched per window, run 12: 0.984 after three passes (NEES/dof
    0.689 -> 0.728). The NIS on those epochs is then matched, not a test; the NEES is."""
    if passes == 0:
        return hist, Rp
    single = pseudo & ~np.any(extra > 0, axis=(1, 2))
    pm = single[:, None, None] & np.isfinite(zp) & ~np.isfinite(z)
    if not pm.any():
        return hist, Rp
    ks = np.flatnonzero(single)
    for _ in range(passes):
        ok = (hist.nis_dof[ks] > 0) & np.isfinite(hist.nis[ks])
        if not ok.any():
            break
        c = _moving_ratio(
            np.where(ok, hist.nis[ks], 0.0), np.where(ok, hist.nis_dof[ks], 0), window
        )
        c = np.where(np.isfinite(c), c, 1.0)
        if np.all(np.abs(c - 1.0) < 0.1):
            break
        scale = np.ones(len(pseudo))
        scale[ks] = c
        Rp = np.where(pm, scale[:, None, None] * Rp, Rp)
        hist = rerun(Rp)
    return hist, Rp


def _frozen_rigid_actual(
    hist: EstimateHistory,
    t: Array,
    z: Array,
    R: Array,
    tun: ukf_tuning.KabirTuning,
    geom: Any,
    consider: NDArray[np.bool_],
) -> tuple[Array, Array]:
    """Where the rigid parameters are frozen (``consider`` epochs), their reported covariance
    becomes the actual error covariance of the estimate they were frozen at
    (:func:`rigid_floor_correction`): ``P <- T P T^T``, ``T`` the identity but for the rigid
    block, :func:`floor_congruence` of the last real measurement's ``P_f`` and ``P_a`` (the
    rate and attitude block is unchanged; their cross-covariances with the rigid parameters
    follow). In place; returns the analysis' ``P_f``, ``P_a``."""
    assert hist.P is not None
    lay = hist.layout
    E = np.arange(lay.dim)
    rig = np.r_[E[lay.err("inertia")], E[lay.err("features")]]
    Pf, Pa = rigid_floor_correction(hist, t, z, R, tun, geom)
    okf = np.all(np.isfinite(Pf), axis=(1, 2)) & np.all(np.isfinite(Pa), axis=(1, 2))
    src = np.flatnonzero(~np.asarray(consider, dtype=bool) & okf)
    if len(src) == 0:
        return Pf, Pa
    last = np.maximum.accumulate(np.where(np.isin(np.arange(len(t)), src), np.arange(len(t)), -1))
    cache: dict[int, Array] = {}
    for k in np.flatnonzero(np.asarray(consider, dtype=bool) & (last >= 0)).tolist():
        j = int(last[k])
        if j not in cache:
            T = np.eye(lay.dim)
            T[np.ix_(rig, rig)] = floor_congruence(Pf[j][np.ix_(rig, rig)], Pa[j][np.ix_(rig, rig)])
            cache[j] = T
        P = np.asarray(hist.P[k], dtype=float)
        if np.all(np.isfinite(P)):
            T = cache[j]
            hist.P[k] = T @ P @ T.T
    return Pf, Pa


def _coasts_actual(
    hist: EstimateHistory,
    t: Array,
    real: NDArray[np.bool_],
    coast: NDArray[np.bool_],
    Pf: Array,
    Pa: Array,
    q_moving: Array,
) -> None:
    """Where nothing is measured, real or predicted by a GP (every feature's GP unusable: the
    filter only propagates), the covariance is ukf's through a coast
    (:func:`~tumblenav.estimators.kabir2025.mismatch.write_coast`) from the actual error's
    covariance at the last real measurement (the filter's mapped by
    :func:`~tumblenav.estimators.kabir2025.mismatch.actual_map`). In place."""
    assert hist.P is not None
    n = len(t)
    k = 0
    while k < n:
        if not (coast[k] and k > 0 and real[k - 1]):
            k += 1
            continue
        j = k
        while j < n and coast[j]:
            j += 1
        kl = k - 1
        P = hist.P[kl]
        ok = P is not None and all(np.all(np.isfinite(a)) for a in (P, Pf[kl], Pa[kl]))
        if ok:
            try:
                T = actual_map(Pf[kl], Pa[kl])
            except np.linalg.LinAlgError:
                T = None
            if T is not None:
                write_coast(hist, t, kl, np.arange(k, j), T @ np.asarray(P) @ T.T, q_moving)
        k = j


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
        said: list[str] = []  # the GPs' warnings: said at the end and kept in info["warnings"]
        for i, m in enumerate(models):
            seen = t[np.all(np.isfinite(w[:, i, :3]), axis=-1)]
            T_train = float(seen[-1] - seen[0]) if len(seen) else 0.0
            summaries.append(_model_summary(m, T_train))
            if not isinstance(m, str) and m.ok and T_train < 3.0 * float(m.periods_s.max()):
                said.append(
                    f"feature {i}: GP trained on {T_train:.0f} s, less than 3 of its longest "
                    f"period ({m.periods_s.max():.0f} s); Kabir 2025 Sec. 3.1 needs T_train >= "
                    "3 T_p for reliable long predictions"
                )
        prep = ukf_filter.prepare(scenario, t, z, R, geom, tun)
        tun_r = prep.tuning
        assert isinstance(tun_r, UKFGPTuning)
        honest = tun.gp_drift_in_r
        zp, Rp, fallback = pseudo_measurements(
            t, z, prep.R_diag, models, tun_r, sigma_p, copies=not honest
        )
        prep = dataclasses.replace(prep, R_diag=Rp)
        real = np.any(np.isfinite(z[..., 0]), axis=1)
        pseudo = np.any(np.isfinite(zp[..., 0]), axis=1) & ~real  # only GP predictions
        # without a real measurement nothing new is learnt about the rigid parameters: the
        # GP's predictions come from the data the filter already used (and where no GP is
        # usable the filter only propagates)
        consider = ~real if honest else None
        hist = ukf_filter.run_ukf(
            scenario, t, zp, Rp, tun.variant, tun_r, geom, prepared=prep, consider=consider
        )
        D, extra = gp_error_model(
            hist, scenario, tun, tun_r, t, real, pseudo, z, zp, Rp, geom, models
        )
        if honest and pseudo.any():
            # second pass: the pseudo-measurements' R carries the GP's error measured along
            # the first pass (the linearisation point; the GP predictions are the same)

            def rerun(R: Array) -> EstimateHistory:
                return ukf_filter.run_ukf(
                    scenario,
                    t,
                    zp,
                    R,
                    tun.variant,
                    tun_r,
                    geom,
                    prepared=dataclasses.replace(prep, R_diag=R),
                    consider=consider,
                )

            Rp = pseudo_r(Rp, extra)
            hist = rerun(Rp)
            window = _gp_window(models, float(np.median(np.diff(t))))
            hist, Rp = _matched_single_gp(
                hist, rerun, z, zp, Rp, extra, pseudo, tun.gp_single_match_passes, window
            )
        if hist.P is not None:
            lay = hist.layout
            E = np.arange(lay.dim)
            idx = np.r_[E[lay.err("rate")], E[lay.err("attitude")]]
            hist.P[:, idx[:, None], idx[None, :]] += D
            if honest and consider is not None:
                Pf, Pa = _frozen_rigid_actual(hist, t, z, Rp, tun_r, geom, consider)
                coast = ~real & ~np.any(np.isfinite(zp[..., 0]), axis=1)
                if coast.any():
                    _coasts_actual(hist, t, real, coast, Pf, Pa, moving_q(hist.layout, tun_r))
        hist.skipped["gp_fallback_features"] = len(fallback)
        # its NIS stays the filter's: the GP's pseudo-measurements are not in the analysis'
        # innovation model (ukf, ukf-mult: kabir2025._report_nis)
        hist.innovations = None
        hist.info["gp"] = summaries
        hist.info["gp_fallback"] = fallback
        if fallback:
            said.append(
                f"no usable GP for feature(s) {fallback}: pure propagation for them during the "
                "occlusion"
            )
        # kept with the run as the UKF keeps its own (run_ukf: the tuning's), so that a
        # campaign counts the runs that said each line (summary.json estimator_warnings)
        hist.info["warnings"] = [*(hist.info.get("warnings") or []), *said]
        for line in hist.info["warnings"]:
            warnings.warn(line, stacklevel=2)
        return hist


register("ukf-gp")(KabirUKFGP)
