"""Kabir 2025's UKF on stereo projections and optical flow (``ukf``), and a multiplicative
(USQUE-style) variant of it (``ukf-mult``).

Kabir & Bai, Sensors 2025, 25, 647, Sec. 2.1-2.2 and 3.2.  Known (Sec. 2.1): the target's mass
centre ``rho0`` relative to the chaser, and the chaser's (fixed) attitude; the chaser does not
rotate and L = I (``chaser.orbit: null``).

State (Kabir 2025 eq. 5), in tumblenav's names and order::

    x = [omega_TI_T (3), q_TI (4, [x,y,z,w]), k1, k2, p_1..p_N in T (3N)]

Kabir's B is our T and his ``q`` (scalar first, ``nu_B = C(q) nu_I``) is our ``q_TI``.
Inertia (Kabir 2025 eq. 6-8): the paper defines ``k1 = log(I1/I2)``, ``k2 = log(I2/I3)``
(eq. 6) but then writes ``I = diag(exp k1, 1, exp k2)`` (eq. 7) and builds the Euler equations
(eq. 8) on it; the two disagree on ``k2``.  We implement eq. 7, i.e. ``k2 = log(I3/I2)``:
``I / I2 = diag(e^k1, 1, e^k2)`` and, from ``I w' = -w x (I w)``::

    wx' = e^-k1 (1 - e^k2) wy wz,   wy' = (e^k2 - e^k1) wx wz,   wz' = e^-k2 (e^k1 - 1) wx wy

(the extracted eq. 8 lost the minus signs in the exponents).  Kinematics ``dq_TI/dt`` by
:func:`tumblenav.rotations.quat_derivative`; ``k`` and ``p`` constant (eq. 11-12); RK4 over
each step (eq. 13).

Measurements (eq. 16-25): per feature ``[u_R, v_R, u_L, v_L, u_L - u_R, du_R, dv_R, du_L,
dv_L]`` (rad, rad/s) from :mod:`tumblenav.frontends.projections` with the flow taken by finite
differences of the measured projections (eq. 27).  Features in C: ``rho_i = rho0_C + R_CI
R_IT p_i``; the flow is that of a rigid rotation about ``rho0`` with ``omega_C = R_CI R_IT
omega_TI_T``.  ``R`` is diagonal (``sigma_p``, ``sigma_d``, ``sigma_o``).  Beyond the paper
(tuning ``flow_edges``, default ``drop``): no flow where eq. 27 falls back to its first- and
second-order formulas, i.e. two samples at each end of every run of measurements; their
truncation error is 30 (0.075 Hz) to 180 (0.025 Hz) times the paper's ``sigma_o`` and its last
sample before an occlusion otherwise throws ``k`` off just before the filter must coast.

Filters
-------
* ``ukf`` (the paper's): additive UKF on the 24-dim state with the 4-component quaternion
  (normalised after every predict and update), scaled unscented transform (Sec. 3.2:
  alpha = 0.1, beta = 2, kappa = 0), diagonal P0 and Q with the quaternion's variances on its
  four components.  Its history reports the 23-dim error-state covariance: the quaternion
  block is mapped by ``dtheta = 2 vec(dq (x) conj(q_hat))`` (the first-order form of
  :func:`tumblenav.rotations.boxminus`, which also drops the quaternion's norm direction).
* ``ukf-mult``: sigma points on the 23-dim error state with the attitude as a rotation vector,
  ``q = exp(dtheta) (x) q_hat`` (tumblenav's boxplus), the quaternion kept unit, the mean
  attitude as the weighted mean of the sigma points' errors about the propagated centre point
  (USQUE-like, Crassidis & Markley 2003, in the left/global error of
  :mod:`tumblenav.rotations`).  The quaternion variances of P0 and Q map to ``4 x`` those
  values in rad^2 (``dtheta = 2 dq_vec``).  After each update the covariance is moved to the
  new nominal attitude (error reset ``G = I + 1/2 [dtheta x]``, from the BCH formula); without
  it the large early corrections from the paper's initial guess sent the filter to wrong
  solutions (70 deg off at 1000 s on three seeds of four).  Once the attitude is lost (sigma > 180 deg, long
  occlusions) its rotation-vector sigma points wrap and the run diverges; it is then stopped.

Both filters propagate the sigma points (RK4) and redraw them from the predicted covariance
for the update.  Their histories report the actual error's covariance (tuning
``covariance_report: actual``, :mod:`~tumblenav.estimators.kabir2025.mismatch`: a covariance
analysis of the mismatched filter, the Q floor of the rigid parameters and the flow's reuse of
the projections' noise counted); the estimate is the filter's.  A run is stopped and counted
in ``skipped['diverged']`` once its state or covariance stops being finite or becomes absurd
(see ``_MAX_STATE``); later epochs are NaN.

Behaviour worth knowing: the measurements are very precise (1e-5 rad) and the body frame is
fixed only through the Euler dynamics, so from the paper's initial guess (27.8 deg, omega x
1.75) the filters claim sub-degree attitude within a few steps while still ~28 deg off (NEES
in the thousands) and converge only as the process noise lets them, over a few polhode
periods (kabir2025 at 0.075 Hz, four seeds, after 1000 s: 0.6-0.7 deg for ``ukf``, 0.9-2.1
deg for ``ukf-mult``).  From 10 % of those initial errors both are consistent (NEES/dof
~0.8) and reach ~0.3 deg in 400 s (tests/test_ukf.py).

Entry points: :func:`run_ukf` runs either filter on prepared measurements ``z`` (n, N, 9) and
variances (n, N, 9) (NaN = not available), so that pseudo-measurements (the GP predictions of
``ukf-gp``) with their own variances can be fed; :func:`stereo_measurements` builds ``z`` and
``R`` from a :class:`~tumblenav.measurements.StereoMeasurements`; :func:`paper_tuning` gives the
paper's per-frequency Q and flow noise.
"""

from __future__ import annotations

import warnings
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from tumblenav.estimators.base import (
    EstimateHistory,
    register,
)
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.kabir2025.filter import _filter, _history, prepare, run_ukf
from tumblenav.estimators.kabir2025.init import error_to_filter_cov
from tumblenav.estimators.kabir2025.mismatch import actual_covariance, moving_q, report_actual
from tumblenav.estimators.kabir2025.model import _process_noise, check_scenario, geometry
from tumblenav.estimators.kabir2025.observations import stereo_measurements
from tumblenav.estimators.kabir2025.tuning import parse_tuning
from tumblenav.measurements import STEREO_TRACKS

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


class KabirUKF:
    """``ukf`` (Kabir 2025's additive UKF) and ``ukf-mult`` (USQUE-style variant)."""

    consumes: tuple[str, ...] = (STEREO_TRACKS,)  # the measurement types it runs on
    needs = (
        "stereo feature tracks from a parallel rig, an inertially fixed chaser and the target's "
        "mass-centre position, known (Kabir 2025 Sec. 2.1): estimator.tuning.mass_centre_L_m"
    )

    def __init__(self, variant: Variant) -> None:
        self.variant = variant
        self.name = "ukf" if variant == "additive" else "ukf-mult"
        self.description = (
            "Kabir 2025: UKF on stereo projections, disparity and optical flow (quaternion in "
            "the state, additive)"
            if variant == "additive"
            else "Kabir 2025's UKF with a multiplicative attitude error (USQUE-style, 23-dim)"
        )

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        check_scenario(scenario)
        parse_tuning(scenario.estimator.tuning)

    def run(self, scenario: Any, measurements: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        check_scenario(scenario)
        tun = parse_tuning(scenario.estimator.tuning)
        geom = geometry(scenario, measurements.t, measurements)
        z, R = stereo_measurements(measurements, tun)
        t = np.asarray(measurements.t, dtype=float)
        prep = prepare(scenario, t, z, R, geom, tun)
        hist = run_ukf(scenario, t, z, R, self.variant, tun, geom, prepared=prep)
        _report(hist, scenario, t, z, prep, geom)
        for line in hist.info.get("warnings", []):
            warnings.warn(line, stacklevel=2)
        return hist

    def run_batch(
        self, scenario: Any, measurements: list, rngs: list, p_every: int = 1
    ) -> list[EstimateHistory]:
        """Many runs at once (vectorised over runs): the same histories as :meth:`run`
        (``p_every`` is accepted for the campaign runner; every covariance is kept)."""
        scenario = context_from_scenario(scenario)  # never the target's truth
        check_scenario(scenario)
        tun = parse_tuning(scenario.estimator.tuning)
        t = measurements[0].t
        geoms = [geometry(scenario, m.t, m) for m in measurements]
        g0 = geoms[0]
        same = all(
            np.array_equal(m.t, t)
            and np.allclose(g.R_CI, g0.R_CI)
            and np.allclose(g.rho0_C, g0.rho0_C)
            and np.allclose(g.centres_x, g0.centres_x)
            for m, g in zip(measurements, geoms, strict=True)
        )
        if not same:
            raise ValueError("run_batch needs runs with the same epochs and geometry")
        zs, Rs, x0s, P0s, Qs, preps = [], [], [], [], [], []
        for m in measurements:
            z, R = stereo_measurements(m, tun)
            prep = prepare(scenario, t, z, R, g0, tun)
            N = z.shape[1]
            zs.append(z)
            Rs.append(prep.R_diag)
            x0s.append(prep.start.x0)
            P0s.append(error_to_filter_cov(prep.start.x0, prep.start.P0_err, self.variant))
            Qs.append(_process_noise(prep.tuning, N, self.variant))
            preps.append(prep)
        res = _filter(
            t,
            np.stack(zs),
            np.stack(Rs),
            np.stack(x0s),
            np.stack(P0s),
            g0,
            preps[0].tuning,
            self.variant,
            k0=np.array([p.start.k0 for p in preps]),
            skip_first=np.array([p.start.info.get("init") == "identified" for p in preps]),
            Q=np.stack(Qs),
        )
        hists = [
            _history(t, res, b, self.variant, preps[b].tuning, x0s[b], preps[b])
            for b in range(len(measurements))
        ]
        for h, z, p in zip(hists, zs, preps, strict=True):
            _report(h, scenario, t, z, p, g0)
        return hists


def _report(hist: EstimateHistory, scenario: Any, t: Array, z: Array, prep: Any, geom: Any) -> None:
    """``covariance_report: actual``: the history's covariance mapped onto the actual error's
    (:func:`~tumblenav.estimators.kabir2025.mismatch.actual_covariance`,
    :func:`~tumblenav.estimators.kabir2025.mismatch.report_actual`); the estimate is the
    filter's. In place."""
    tun = prep.tuning
    hist.info["covariance_report"] = tun.covariance_report
    innov, hist.innovations = hist.innovations, None
    if tun.covariance_report != "actual" or hist.P is None:
        return
    pn = getattr(scenario, "process_noise", None)
    q_r = float(getattr(pn, "rotational_rad2_s4", 0.0) or 0.0)
    walk = float(prep.derived.get("flow_process_noise_rad_s", 0.0)) ** 2
    world = tun.update_chart == "world"
    S: dict = {}
    Pf, Pa = actual_covariance(hist, t, z, prep.R_diag, tun, geom, q_r, walk, world, S)
    measured = np.any(np.isfinite(z[..., 0]), axis=1)
    report_actual(hist, Pf, Pa, measured, t, moving_q(hist.layout, tun))
    if innov is not None:
        _report_nis(hist, innov, S)


def _report_nis(hist: EstimateHistory, innov: Array, S: dict) -> None:
    """The NIS against the innovations' actual covariance (``actual_covariance``'s
    ``innovations``), as the NEES is against the actual error's: the flows are eq. 27's
    stencil of the projections at ``t +- dt, +- 2 dt``, which the filter has already updated
    with (or will), so the prediction holds part of the current measurement noise and the
    innovations are smaller than the filter's ``H P H^T + R`` says (expected NIS/dof 0.91 on
    kabir_paper_observed, measured 0.90-0.91 on every observed case before issue 18's
    twenty-fourth session). Epochs the analysis did not replay with the same components (a
    gate's rejections) keep the filter's own; ``info["nis_filter"]`` keeps that series."""
    nis = np.array(hist.nis, dtype=float)
    hist.info["nis_filter"] = nis.copy()
    for k, (rows, _, S_a) in S.items():
        nu = innov[k]
        used = np.isfinite(nu)
        if used.sum() != rows.sum() or not np.array_equal(used, rows):
            continue
        v = nu[used]
        try:
            nis[k] = float(v @ np.linalg.solve(S_a, v))
        except np.linalg.LinAlgError:
            continue
    hist.nis = nis
    hist.info["nis_report"] = "actual"


register("ukf")(lambda: KabirUKF("additive"))
register("ukf-mult")(lambda: KabirUKF("mult"))

# ukf-gp: the UKF fed by the GP through long occlusions (registers itself)
from tumblenav.estimators.kabir2025 import ukf_gp  # noqa: E402, F401
