"""Yu 2019 Sec. 3: EKF on depth point clouds with the mass-centre offset (``ekf-depth``).

State: relative position ``r`` and velocity ``v`` of the target's mass centre in L (the Hill
equations of Yu 2019 eq. 26-27, the same matrices as Hu 2024 eq. 4-5), the mass-centre offset
``b`` from the model origin (in T), the attitude ``q_TI``, the rate ``omega`` (in T) and the five
inertia ratios of Yu 2019 eq. 29, ``l = [Iyy, Izz, Ixy, Ixz, Iyz] / Ixx`` (Euler equations with
the full matrix, eq. 28). Error state ``[dtheta, domega, dl, dr, dv, db]`` (20), attitude error
as in :mod:`tumblenav.rotations`.

Measurements (eq. 30-32 written in L): every rectangle recognised in a scan
(:mod:`tumblenav.frontends.depth_pose`) gives the model attitude, i.e. ``q_TI`` (the model frame
is parallel to T), and the model origin ``p_ML = r - R_LT b``; the four-fold symmetry of each
rectangle is resolved against the filter's prediction (eq. 21-25). Their noise is taken from the
scatter of the plane fit (first order: centroid ``sigma / sqrt(n)`` per axis; attitude
``sigma / (sqrt(n) * side / sqrt(12))`` per axis), scaled by ``position_noise_scale`` and
``attitude_noise_scale`` for the larger, scan-to-scan correlated errors of a real ray grid.

Beyond Yu 2019: the inertia ratios that the motion does not excite (a spin about a principal
axis) get a Schmidt (consider) update, so the EKF does not learn them from its own rate noise
(:func:`unexcited_ratios`); docs/results/yu2019.md has the measurements behind both.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator
from scipy.stats import chi2

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import discretise, rk4_step
from tumblenav.dynamics.relative_orbit import cw_discrete
from tumblenav.errors import InputError
from tumblenav.estimators.base import (
    Belief,
    Block,
    EstimateHistory,
    StateLayout,
    StepInfo,
    fold,
    register,
)
from tumblenav.estimators.base import parse_tuning as base_parse_tuning
from tumblenav.estimators.context import context_from_scenario
from tumblenav.frontends.depth_pose import consistent_start, model_symmetries, pose_fixes
from tumblenav.measurements import DEPTH_CLOUDS

Array = NDArray[np.float64]

LAYOUT = StateLayout(
    (
        Block("attitude", "quat", 3),
        Block("rate", "vector", 3),
        Block("inertia", "vector", 5),
        Block("position", "vector", 3),
        Block("velocity", "vector", 3),
        Block("offset", "vector", 3),
    )
)
# The blocks' slices, taken once from LAYOUT: in the nominal state x ...
_X_ATT, _X_RATE, _X_INERTIA, _X_POS, _X_VEL, _X_OFFSET = (
    LAYOUT.nom(b) for b in ("attitude", "rate", "inertia", "position", "velocity", "offset")
)
# ... and in the error state / covariance
_E_ATT, _E_RATE, _E_INERTIA, _E_POS, _E_VEL, _E_OFFSET = (
    LAYOUT.err(b) for b in ("attitude", "rate", "inertia", "position", "velocity", "offset")
)
_X_TRANS = slice(_X_POS.start, _X_VEL.stop)  # [r, v]: the Hill model's state
_E_TRANS = slice(_E_POS.start, _E_VEL.stop)
_E_ROT = slice(_E_ATT.start, _E_INERTIA.stop)  # [dtheta, domega, dl]: rotational_F's block
assert _X_POS.stop == _X_VEL.start and _E_POS.stop == _E_VEL.start
assert _E_ATT.stop == _E_RATE.start and _E_RATE.stop == _E_INERTIA.start

_E = np.zeros((5, 3, 3))  # dI/dl_j, I = [[1, l2, l3], [l2, l0, l4], [l3, l4, l1]]
_E[0, 1, 1] = _E[1, 2, 2] = 1.0
_E[2, 0, 1] = _E[2, 1, 0] = 1.0
_E[3, 0, 2] = _E[3, 2, 0] = 1.0
_E[4, 1, 2] = _E[4, 2, 1] = 1.0


class DepthTuning(BaseModel):
    """``estimator.tuning`` keys of ekf-depth (Yu 2019 Sec. 4 values as defaults)."""

    model_config = ConfigDict(extra="forbid")
    P0_sigma_position_m: float = Field(
        1.0, gt=0, description="initial 1-sigma of the position r (m; Yu 2019 Sec. 4)"
    )
    P0_sigma_velocity_m_s: float = Field(
        0.1, gt=0, description="initial 1-sigma of the velocity v (m/s)"
    )
    P0_sigma_offset_m: float = Field(
        0.1, gt=0, description="initial 1-sigma of the mass-centre offset b (m)"
    )
    P0_sigma_attitude_rad: float = Field(0.1, gt=0, description="initial attitude 1-sigma (rad)")
    P0_sigma_rate_rad_s: float = Field(
        0.01, gt=0, description="initial 1-sigma of the rate (rad/s); the filter starts at rate 0"
    )
    P0_sigma_inertia: float | Literal["inertia_init"] = Field(
        "inertia_init",
        description="initial 1-sigma of each inertia ratio; 'inertia_init': the one that "
        "matches the initial guess, P0_sigma_inertia_given or P0_sigma_inertia_sphere",
    )
    P0_sigma_inertia_given: float = Field(
        0.1,
        gt=0,
        description="with P0_sigma_inertia 'inertia_init' and inertia_init 'given' (Yu 2019 "
        "Sec. 4: a guess near the truth)",
    )
    P0_sigma_inertia_sphere: float = Field(
        0.5,
        gt=0,
        description="with P0_sigma_inertia 'inertia_init' and inertia_init 'sphere' (a sphere "
        "is 0.3-0.5 off a typical satellite's ratios)",
    )
    Q_diag: float = Field(1e-12, ge=0, description="process noise of the 6 disturbances")
    plane_threshold_m: float | Literal["range_noise"] = Field(
        "range_noise",
        description="inlier distance of the RANSAC plane fits (m); 'range_noise': "
        "plane_threshold_sigmas x the sensor's range_noise_m, at least plane_threshold_min_m",
    )
    plane_threshold_sigmas: float = Field(
        3.0, gt=0, description="with plane_threshold_m 'range_noise': the threshold in sigmas"
    )
    plane_threshold_min_m: float = Field(
        1e-3, gt=0, description="with plane_threshold_m 'range_noise': its floor (m)"
    )
    gate_probability: float = Field(
        0.9999,
        gt=0,
        lt=1,
        description="NIS gate per fix (6 dof); rejections are counted as gated_out (off "
        "without the multi-solution fix)",
    )
    inertia_init: Literal["sphere", "given"] = Field(
        "sphere",
        description="initial inertia ratios: 'sphere' (1, 1, 0, 0, 0: nothing known) or "
        "'given' (inertia_init_ratios, a prior the user states)",
    )
    inertia_init_ratios: list[float] = Field(
        [1.0, 1.0, 0.0, 0.0, 0.0],
        min_length=5,
        max_length=5,
        description="with inertia_init 'given': [Iyy/Ixx, Izz/Ixx, Ixy/Ixx, Ixz/Ixx, Iyz/Ixx]",
    )
    inertia_init_perturb: bool = Field(
        False,
        description="add an error drawn from P0 to the given ratios (Yu 2019's protocol: its "
        "initial state is 'the truth corrupted by initial errors'; the yu2019 recipe gives the "
        "true ratios with this on)",
    )
    position_noise_scale: float = Field(
        4.0,
        gt=0,
        description="variance multiplier on each fix's first-order centroid covariance: the "
        "centroid errors of a ray-cast scan are about 2x that variance across the short side "
        "(0.03x along the long side, 1.1x along the normal) and correlated from scan to scan "
        "(lag-1 0.5-0.8 at 1 Hz); 4 makes the translation consistent on the yu2019 runs "
        "(docs/results/yu2019.md)",
    )
    attitude_noise_scale: float = Field(
        1.5,
        gt=0,
        description="variance multiplier on each fix's first-order attitude covariance "
        "(measured 0.6, 1.7 and 0.02x that variance about the three axes, uncorrelated)",
    )
    consider_unexcited_ratios: bool = Field(
        True,
        description="Schmidt (consider) update for the inertia ratios whose effect on the "
        "dynamics the rate's own noise could produce (a spin about a principal axis): beyond "
        "Yu 2019, the EKF otherwise gains spurious information on them",
    )
    multi_solution_fix: bool = Field(
        True,
        description="resolve each rectangle's symmetric cases against the prediction "
        "(Yu 2019 eq. 21-25); false reproduces the paper's Fig. 9 (180-degree jumps)",
    )

    @field_validator("P0_sigma_inertia", "plane_threshold_m", mode="before")
    @classmethod
    def _number_or_rule(cls, v: Any, info: ValidationInfo) -> Any:
        """A positive number, or the rule named by the default (``null``, the former default,
        means the rule too)."""
        assert info.field_name is not None  # a field validator's info names its field
        rule = cls.model_fields[info.field_name].default
        if v is None or v == rule:
            return rule
        try:
            number = float("nan") if isinstance(v, bool) else float(v)
        except (TypeError, ValueError):
            number = float("nan")
        if not number > 0:
            raise ValueError(f"a positive number or '{rule}', got {v!r}")
        return number


def inertia_matrix(l: Array) -> Array:
    """Yu 2019 eq. 29, normalised by Ixx."""
    return np.array([[1.0, l[2], l[3]], [l[2], l[0], l[4]], [l[3], l[4], l[1]]])


def physical_inertia(l: Array) -> bool:
    """True when the ratios of eq. 29 give a positive definite inertia (all principal moments
    above 1e-3 of Ixx); with a zero or negative moment the Euler equations explode."""
    if not np.all(np.isfinite(l)):
        return False
    return bool(np.linalg.eigvalsh(inertia_matrix(l))[0] > 1e-3)


def euler_full(w: Array, l: Array) -> Array:
    """Yu 2019 eq. 28: ``omega' = I^-1 (-omega x I omega)``."""
    I = inertia_matrix(l)
    # cast: numpy's stubs type linalg results of float input as floating[Any] (float64 here)
    return cast(Array, np.linalg.solve(I, -np.cross(w, I @ w)))


def rotational_F(w: Array, l: Array) -> Array:
    """(11, 11) error dynamics of [dtheta, domega, dl] (Hamilton error, cf. Hu eq. 29)."""
    I = inertia_matrix(l)
    Iinv = np.linalg.inv(I)
    wdot = Iinv @ (-np.cross(w, I @ w))
    F = np.zeros((_E_ROT.stop, _E_ROT.stop))
    F[_E_ATT, _E_ATT] = -rot.skew(w)
    F[_E_ATT, _E_RATE] = -np.eye(3)
    F[_E_RATE, _E_RATE] = Iinv @ (rot.skew(I @ w) - rot.skew(w) @ I)
    for j in range(5):
        F[_E_RATE, _E_INERTIA.start + j] = Iinv @ (-np.cross(w, _E[j] @ w) - _E[j] @ wdot)
    return F


def _inertia_columns(w: Array, l: Array) -> Array:
    """(3, 5) ``d omega' / d l_j`` of Yu 2019 eq. 28 at rate ``w`` (the columns of
    :func:`rotational_F` for the ratios)."""
    return rotational_F(w, l)[_E_RATE, _E_INERTIA]


def unexcited_ratios(w: Array, l: Array, P_w: Array, k: float = 4.0) -> NDArray[np.bool_]:
    """Ratios whose effect on the dynamics is not distinguishable from the rate's own noise:
    ``|c_j|^2 < k tr(J_j P_w J_j^T)`` with ``c_j = d omega' / d l_j`` and
    ``J_j = d c_j / d omega``.  About a principal axis the columns of Iyy, Izz and Ixy are
    only what the estimated rate's noise makes of them (the truth's are zero): updating those
    ratios would be information from nothing."""
    C = _inertia_columns(w, l)
    h = 1e-6 * max(float(np.linalg.norm(w)), 1e-6)
    J = np.stack(
        [
            (_inertia_columns(w + h * e, l) - _inertia_columns(w - h * e, l)) / (2 * h)
            for e in np.eye(3)
        ],
        axis=2,
    )  # (3, 5, 3): the columns are quadratic in omega, so this is exact up to rounding
    noise = np.einsum("ijk,kl,ijl->j", J, P_w, J)
    return np.sum(C * C, axis=0) <= k * noise


def _propagate(x: Array, P: Array, dt: float, n: float, q_c: float) -> tuple[Array, Array]:
    """Predict over ``dt``: RK4 of the attitude and rate (Yu 2019 eq. 28 with the quaternion
    kinematics), the Hill model (eq. 26-27) for ``[r, v]``, and ``P`` through the discretised
    error dynamics (series of Hu 2024 eq. 38-39)."""
    q, w, l = x[_X_ATT], x[_X_RATE], x[_X_INERTIA]

    def f(q_, w_):
        return rot.quat_derivative(q_, w_), euler_full(w_, l)

    q_new, w_new = rk4_step(f, (q, w), dt)
    x = x.copy()
    x[_X_ATT] = q_new / np.linalg.norm(q_new)
    x[_X_RATE] = w_new
    Phr, Qr = discretise(rotational_F(w, l), _Qc_rot(q_c), dt)
    Pht, Qt = cw_discrete(n, q_c, dt)
    x[_X_TRANS] = Pht @ x[_X_TRANS]
    Phi = np.eye(LAYOUT.dim)
    Phi[_E_ROT, _E_ROT] = Phr
    Phi[_E_TRANS, _E_TRANS] = Pht
    Qk = np.zeros((LAYOUT.dim, LAYOUT.dim))
    Qk[_E_ROT, _E_ROT] = Qr
    Qk[_E_TRANS, _E_TRANS] = Qt
    return x, Phi @ P @ Phi.T + Qk


def _Qc_rot(q_c: float) -> Array:
    Q = np.zeros((_E_ROT.stop, _E_ROT.stop))
    Q[_E_RATE, _E_RATE] = q_c * np.eye(3)  # Yu 2019: w2 = disturbing torque / Ixx
    return Q


def _P0(tun: DepthTuning) -> Array:
    """Yu 2019 Sec. 4 initial covariance."""
    sigma = np.empty(LAYOUT.dim)
    sigma[_E_ATT] = tun.P0_sigma_attitude_rad
    sigma[_E_RATE] = tun.P0_sigma_rate_rad_s
    sigma[_E_INERTIA] = _sigma_inertia(tun)
    sigma[_E_POS] = tun.P0_sigma_position_m
    sigma[_E_VEL] = tun.P0_sigma_velocity_m_s
    sigma[_E_OFFSET] = tun.P0_sigma_offset_m
    return np.diag(sigma**2)


def _initial_inertia(tun: DepthTuning, rng: np.random.Generator) -> Array:
    """Initial inertia ratios (Yu 2019 eq. 29): a sphere, or the given ratios (optionally
    with an error drawn from P0, Yu's protocol).  The filter's frame is one of the model's
    symmetric frames, which for half turns leaves the diagonal ratios unchanged (and the
    products of inertia, zero for a principal frame, too)."""
    if tun.inertia_init == "sphere":
        return np.array([1.0, 1.0, 0.0, 0.0, 0.0])
    given = np.asarray(tun.inertia_init_ratios, float)
    if not tun.inertia_init_perturb:
        return given
    return given + _sigma_inertia(tun) * rng.normal(size=5)


def _sigma_inertia(tun: DepthTuning) -> float:
    """P0 sigma of the ratios: as given, else the one that matches the initial guess."""
    if tun.P0_sigma_inertia != "inertia_init":
        return tun.P0_sigma_inertia
    if tun.inertia_init == "given":
        return tun.P0_sigma_inertia_given
    return tun.P0_sigma_inertia_sphere


def plane_threshold(tun: DepthTuning, range_noise_m: float) -> float:
    """Inlier distance (m) of the RANSAC plane fits: as given, else ``plane_threshold_sigmas``
    times the sensor's range noise, at least ``plane_threshold_min_m``."""
    if tun.plane_threshold_m != "range_noise":
        return tun.plane_threshold_m
    return max(tun.plane_threshold_sigmas * range_noise_m, tun.plane_threshold_min_m)


def fix_covariance(fx, sigma: float) -> tuple[Array, Array]:
    """First-order covariances (in the rectangle frame P: short, long, normal) of one fix from
    n points uniform on an a x b rectangle with normal noise sigma: eigenvector perturbation of
    the distribution matrix (eq. 4-5) and the sampling error of the centroid (eq. 3).
    ``Var J_ij = E[d_i^2 d_j^2] / n``; a rotation about axis k moves the eigenvectors i, j by
    ``J_ij / (lambda_i - lambda_j)``."""
    b, a = fx.sides_m
    n = max(fx.n_points, 3)
    lb, la, ls = b**2 / 12 + sigma**2, a**2 / 12 + sigma**2, sigma**2
    var_normal_tilt_long = la * ls / n / max(la - ls, 1e-12) ** 2  # about the short axis
    var_normal_tilt_short = lb * ls / n / max(lb - ls, 1e-12) ** 2  # about the long axis
    var_in_plane = la * lb / n / max(la - lb, 1e-3 * la) ** 2  # about the normal
    cov_att = np.diag([var_normal_tilt_long, var_normal_tilt_short, var_in_plane])
    cov_pos = np.diag([lb / n, la / n, ls / n])
    return cov_att, cov_pos


def _only_model_symmetric(fix, syms: list[Array]) -> bool:
    """True when all the candidate poses of one rectangle differ by symmetries of the model
    (then starting from any of them is as good as any other: the attitude is defined only up
    to those symmetries anyway)."""
    R0 = fix.candidates[0][0] if fix.candidates else fix.R_SM
    return all(any(np.allclose(R0.T @ R, G, atol=1e-6) for G in syms) for R, _ in fix.candidates)


def measurement(x: Array, R_LI: Array) -> tuple[Array, Array]:
    """Model origin in L, ``p_ML = r - R_LT b``, and its Jacobian (3, LAYOUT.dim = 20)."""
    R_LT = R_LI @ rot.quat_to_matrix(x[_X_ATT]).T
    b = x[_X_OFFSET]
    y = x[_X_POS] - R_LT @ b
    H = np.zeros((3, LAYOUT.dim))
    # R_LT = R_LI R_TI^T with R_TI = Exp(dtheta) R_hat: R_LT b ~ R_hat_LT (b + [b x] dtheta),
    # so dy/dtheta = -R_LT [b x]
    H[:, _E_ATT] = -R_LT @ rot.skew(b)
    H[:, _E_POS] = np.eye(3)
    H[:, _E_OFFSET] = -R_LT
    return y, H


class DepthEKF:
    name = "ekf-depth"
    consumes: tuple[str, ...] = (DEPTH_CLOUDS,)  # the measurement types it runs on
    needs = "depth point clouds (depth sensor) and a target model with known rectangles"
    description = "Yu 2019: RANSAC rectangles -> coarse pose -> EKF with mass-centre offset"

    def check(self, scenario: Any) -> None:
        scenario = context_from_scenario(scenario)  # never the target's truth
        if scenario.sensor.kind != "depth":
            raise InputError(
                f"ekf-depth needs a depth sensor; scenario {scenario.name} has a "
                f"{scenario.sensor.kind} sensor"
            )
        base_parse_tuning(scenario.estimator.tuning, DepthTuning)

    def run(self, scenario: Any, meas: Any, rng: np.random.Generator) -> EstimateHistory:
        scenario = context_from_scenario(scenario)  # never the target's truth
        self.check(scenario)
        tun = base_parse_tuning(scenario.estimator.tuning, DepthTuning)
        from tumblenav.target_model import from_config

        if scenario.target_model is None:
            raise InputError(
                "ekf-depth needs the target's geometry model (Yu 2019 recognises its "
                "rectangles): give target.model in the scenario"
            )
        steps = DepthSteps(
            model=from_config(scenario.target_model),
            meas=meas,
            tun=tun,
            sigma=scenario.sensor.range_noise_m,
            n_orbit=scenario.chaser.orbit.mean_motion_rad_s if scenario.chaser.orbit else 0.0,
            rng=rng,
        )
        r = fold(steps, meas.t)
        skipped = {
            "no_rectangle": 0,
            "gated_out": 0,
            "ambiguous_start": 0,
            "nonphysical_inertia": 0,
            **r.skipped,
        }
        return EstimateHistory(
            t=meas.t,
            x=r.x,
            P=r.P,
            layout=LAYOUT,
            nis=r.nis,
            nis_dof=r.nis_dof,
            skipped=skipped,
            info={"convention": "yu2019", "symmetries": steps.symmetries},  # evaluation
        )


@dataclass(frozen=True)
class DepthSteps:
    """Yu 2019's EKF as stateless steps on one run's point clouds, folded by
    :func:`tumblenav.estimators.base.fold`: the plane front end turns each scan into pose
    fixes (with the predicted attitude for the multi-solution fix, eq. 21-25), the filter
    starts from the first scan with an unambiguous fix (Sec. 4) and updates with each fix
    (eq. 34-41). ``rng`` is the run's random stream (RANSAC, the initial inertia error),
    drawn in the order of the epochs."""

    model: Any
    meas: Any
    tun: DepthTuning
    sigma: float
    n_orbit: float
    rng: np.random.Generator
    layout: StateLayout = LAYOUT

    @functools.cached_property
    def symmetries(self) -> list[Array]:
        return model_symmetries(self.model.rectangles)

    @functools.cached_property
    def _frames(self) -> tuple[Array, Array]:
        return rot.quat_to_matrix(self.meas.q_CL), rot.quat_to_matrix(self.meas.q_LI)

    def _fixes(self, k: int, x: Array | None) -> list:
        """Epoch ``k``'s pose fixes (Yu 2019 Sec. 2-3), with the predicted attitude ``x``."""
        R_CL, R_LI = self._frames
        pts = self.meas.points[k][self.meas.observed[k]]
        R_SM_pred = None
        if x is not None and self.tun.multi_solution_fix:
            R_SM_pred = R_CL[k] @ R_LI[k] @ rot.quat_to_matrix(x[_X_ATT]).T
        thr = plane_threshold(self.tun, self.sigma)
        return pose_fixes(pts, self.model, thr, self.rng, self.sigma, R_SM_pred)[0]

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        """Yu 2019 Sec. 4: start from the first observation, once a scan holds a fix that
        is not ambiguous (one rectangle alone leaves its four symmetric cases and faces of
        equal size undecided: wait for a scan with two or more, Sec. 2.3)."""
        fixes = self._fixes(k, None)
        if not fixes:
            return None, StepInfo(skipped={"no_rectangle": 1})
        if len(fixes) == 1 and not _only_model_symmetric(fixes[0], self.symmetries):
            return None, StepInfo(skipped={"ambiguous_start": 1})
        R_CL, R_LI = self._frames
        R_LS = R_CL[k].T
        R_SM0, p0 = consistent_start(fixes)
        x = np.zeros(LAYOUT.nominal_dim)
        x[_X_ATT] = rot.matrix_to_quat((R_LI[k].T @ R_LS @ R_SM0).T)
        x[_X_INERTIA] = _initial_inertia(self.tun, self.rng)
        x[_X_POS] = R_LS @ p0
        return Belief(float(self.meas.t[k]), x, _P0(self.tun), LAYOUT), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        x, P = _propagate(belief.x, belief.P, t - belief.t, self.n_orbit, self.tun.Q_diag)
        return Belief(t, x, P, LAYOUT)

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        """Each fix of epoch ``k`` (Yu 2019 eq. 34-41), gated by its NIS; the start epoch's
        fixes made the start."""
        if started:
            return belief, StepInfo()
        tun = self.tun
        x, P = belief.x, belief.P
        fixes = self._fixes(k, x)
        skipped = {"no_rectangle": 0 if fixes else 1, "gated_out": 0, "nonphysical_inertia": 0}
        R_CL, R_LI = self._frames
        R_LS = R_CL[k].T
        nis, dof = 0.0, 0
        for fx in fixes:
            q_meas = rot.matrix_to_quat((R_LI[k].T @ R_LS @ fx.R_SM).T)  # R_TI = R_MS R_SL R_LI
            p_ML = R_LS @ fx.p_MinS
            cov_att, cov_pos = fix_covariance(fx, self.sigma)
            cov_att = tun.attitude_noise_scale * cov_att
            cov_pos = tun.position_noise_scale * cov_pos
            R_LP = R_LS @ fx.R_SM @ fx.R_MP if fx.R_MP is not None else np.eye(3)
            R_TP = fx.R_MP if fx.R_MP is not None else np.eye(3)
            y, Hp = measurement(x, R_LI[k])
            H_att = np.zeros((3, LAYOUT.dim))
            H_att[:, _E_ATT] = np.eye(3)
            H = np.vstack([H_att, Hp])
            nu = np.r_[rot.boxminus(q_meas, x[_X_ATT]), p_ML - y]
            R = np.zeros((6, 6))
            R[:3, :3] = R_TP @ cov_att @ R_TP.T
            R[3:, 3:] = R_LP @ cov_pos @ R_LP.T
            S = H @ P @ H.T + R
            d2 = nu @ np.linalg.solve(S, nu)
            if tun.multi_solution_fix and d2 > chi2.ppf(tun.gate_probability, 6):
                # NIS gate (rejections counted); off without the fix, to show its jumps
                skipped["gated_out"] += 1
                continue
            K = np.linalg.solve(S, H @ P).T
            if tun.consider_unexcited_ratios:
                # Schmidt (consider) update for the ratios the motion does not excite: no
                # gain, so no information from nothing; their covariance and its coupling to
                # the rate stay, and the Joseph form below is exact for any gain
                unexcited = unexcited_ratios(x[_X_RATE], x[_X_INERTIA], P[_E_RATE, _E_RATE])
                K[_E_INERTIA][unexcited] = 0.0
            A = np.eye(LAYOUT.dim) - K @ H
            P = A @ P @ A.T + K @ R @ K.T  # Joseph form
            x_new = LAYOUT.boxplus(x, K @ nu)
            if not physical_inertia(x_new[_X_INERTIA]):
                # a step that makes the inertia not positive definite would let the Euler
                # equations explode: keep the ratios where they were, take the rest, and
                # count it
                x_new[_X_INERTIA] = x[_X_INERTIA]
                skipped["nonphysical_inertia"] += 1
            x = x_new
            nis += d2
            dof += 6
        info = StepInfo(nis=nis if dof else float("nan"), dof=dof, skipped=skipped)
        return Belief(belief.t, x, P, LAYOUT), info

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P


register("ekf-depth")(DepthEKF)
