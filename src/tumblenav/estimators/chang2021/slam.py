"""ekf-pose with the feature map in the state (``map: state``, tumblenav's; beyond Chang 2021).

Why (Chang 2021 eq. 30 is circular without the truth): eq. 30 measures the mass centre as
``rho_0 = mean(rho_i - R_LThat r_i)`` with ``r_i`` registered when first seen *from the current
estimate*, ``r_i = R_ThatL (rho_i - r_hat)``. The measurement then reproduces the estimate it
was registered with, and the filter takes that as new information: its mass centre stays where
the start put it, with a covariance that shrinks at every epoch (``map: registered``, measured
in :mod:`.tuning`). Chang sidesteps it by starting from the truth (Sec. 4.2).

Here, as in Hu 2024's filter (:mod:`tumblenav.estimators.hu2024.model`), each live feature's
position about the mass centre in That, ``s_i``, is a state, and each triangulated feature is a
measurement of its own::

    x = [q_ThatL, omega_ThatL_That, r_L, v_L | j | s_1 ... s_m]   (13 + 5 + 3m; error 17 + 3m)
    rho_i = r + R_LThat s_i + n_i,    n_i ~ N(0, Sigma_i)   (triangulation, at the prediction)
    H_i = [R_LThat [s_i x], 0, I, 0 | ... R_LThat (column of s_i) ...]   (left error)

(``R_LThat = R_hat_LThat Exp(-dtheta) ~ R_hat_LThat (I - [dtheta x])``, so ``d rho/d dtheta =
R_hat_LThat [s x]``). The mass centre is then what the data say it is: the point the features
rotate about while it follows CW; the rotation makes the common shift of ``r`` and the ``s_i``
observable, so nothing is measured twice.

* Pose block: propagated as in :mod:`.model` (eq. 2-4, CW with white acceleration); the
  features are constant in That (no process noise: the target is rigid; the walk of sliding
  tracks below is added at the update), ``P_px = Phi P_px``.
* Inertia (``inertia: estimated``, the default; tumblenav's, issue 18): Chang 2021 takes the
  inertia as known; here the tensor in That, normalised to a mean moment of 1 (the scale is
  unobservable), is ``J = I + D(j)`` with ``D`` symmetric and traceless, and its five
  parameters ``j`` follow the pose in ``P`` (rows 12-16, before the features; the mean travels
  in the memo as the map does). They start at the sphere (``j = 0``) with a 1-sigma of
  ``inertia_sigma`` (by default 0.15, or 0.05 where one epoch fixes the attitude poorly: :meth:`StateSteps.inertia_sigma_at`) each, have no process noise (a rigid body), and enter eq. 3 through
  ``d(domega/dt)/dj`` (:func:`euler_inertia_jacobian`). Why: with a sphere, the nutation
  (a deterministic drift of the body rate) is a random walk to the filter, the rate is
  conservative and the errors it leaves are taken up by the mass centre (chang_inertia per
  block over runs 0-5: rate NEES/dof 0.36, position 1.9, velocity 1.7; estimated: 1.13,
  0.98, 1.09; with the truth's inertia given: 1.01, 1.23, 1.23 on runs 0, 3, 4). With
  ``sphere`` the parameters keep a zero covariance (``given``: the tuning's tensor).
* New tracks: ``s_new = R_hat_ThatL (rho_new - r_hat)``, ``J = ds/dx = [-[s x], 0,
  -R_hat_ThatL, 0]`` (pose columns), covariance ``J P J^T + R_hat_ThatL Sigma R_hat_LThat``,
  cross-covariance ``J P`` (augmentation of the full joint covariance).
* Tracks that slide (image tracks: the tracks' ``slide_px2_per_frame``; tumblenav's, issue
  18): each map point walks by that much across the line of sight per frame
  (:meth:`StateSteps.map_walk`), so the map follows the LK tracks' slide over the surface
  instead of holding their later sightings to the first ones. Off for point tracks.
* The rotation of That stays unobservable (``invariant_errors``; tumblenav's, issue 18): That
  is defined by the start (attitude exact at k0), and no measurement can tell a rotation
  ``dphi`` of it with the map and the rate turned along (the gauge direction, errors
  ``dtheta = dphi``, ``domega = -[omega x] dphi``, ``dj = Gamma dphi``, ``ds_i = -[s_i x]
  dphi``: :func:`gauge_direction`). The linearised filter must not either, or its attitude
  grows confident while the map and the attitude drift together. Its Jacobians at the
  current estimate see no gauge (``H N = 0``); the plain EKF loses it between steps: the
  update moves the rate and the map, so the gauge direction the next propagation keeps is not
  the one the update could not see, and the gap reads as attitude information (Huang,
  Mourikis & Roumeliotis 2008 for EKF-SLAM). Here the covariance is propagated in errors in
  which the gauge is ``dtheta`` alone (``dx' = T dx``, :func:`gauge_discretise`: exact for
  any linearisation point, since ``F N = dN/dt``) and re-expressed at each update's estimate
  (:func:`regauge`), as an invariant EKF does (Barrau & Bonnabel 2015, "An EKF-SLAM algorithm
  with consistency properties", arXiv:1510.06263). The start replay keeps the first-estimate
  Jacobians (its passes relinearise them at the previous pass's map). With ``inertia:
  given`` (a fixed non-spherical tensor) a rotation of That changes the dynamics, there is no
  gauge, and the plain EKF runs.
* Tracks not observed at an epoch are marginalised (their rows and columns removed); at most
  ``max_map_features`` are kept, the longest tracked first (age so far, causal).
* Per-feature chi-square gate (``feature_gate_probability``, 3 dof; ``template_gate_probability``
  for template tracks, :func:`tuning_for_tracks`): a rejected feature is
  counted (``rejected``, ``skipped['gated_out']``) and removed from the state (its track is
  suspect: a bad match or drift). Joseph-form update, symmetrised.
* Slips (``slip_probability``; tumblenav's, Chang 2021 has none): before the update each
  map track's innovation is compared with its residual after the last epoch's step
  (:func:`slip_test`: a jump test against the epoch's own tracks, robust scale); a track that
  jumped to another surface point (image tracks: 2.3 % of the frame-to-frame increments
  exceed 1 px and 80 % of those persist) is re-anchored: its map point is dropped and the
  track augmented again from the current frame as a new feature (``skipped['slips']``), so
  the jump moves neither the pose nor the other features. The gate below, sized for the
  stated noise, passes such jumps when the stated noise covers the tracks' slow slide.
* Divergence: an epoch is *wild* when fewer than half of the map's observed features pass the
  gate (the predicted attitude and position explain less than half the data; no update is
  made then); ``divergence_epochs`` wild epochs in a row stop the run (``StepInfo(diverged=
  True)``) rather than let it re-register features from a wrong pose.
* Start: Chang's q-method (eq. 27-28) and eq. 29 over the first ``init_frames`` frames
  (:func:`.init.start`: attitude defined at k0, rate line, mass centre from the CW fit with a
  prior of ``prior_mass_centre_sigma_m`` about the first features' centroid, whose full
  uncertainty the start keeps); the start epoch's features are then augmented from it.

The belief's ``x`` is the 13-component pose (the reported layout :data:`LAYOUT_POSE`), its
``P`` the joint (12 + 3m) covariance; the map (track ids and ``s_i``) travels in the memo
(:class:`MapMemo`); :meth:`StateSteps.report` returns the pose block of ``P``.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular
from scipy.stats import chi2

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import discretise
from tumblenav.dynamics.relative_orbit import cw_stm
from tumblenav.estimators.base import Belief, Block, StateLayout, StepInfo
from tumblenav.estimators.chang2021.batch import BatchStart, fit_window
from tumblenav.estimators.chang2021.filter import TrackSteps
from tumblenav.estimators.chang2021.init import Start
from tumblenav.estimators.chang2021.measurements import (
    FeatureTracks,
    pixel_variance,
    point_covariance,
    slide_covariance,
    track_noise_ratio,
)
from tumblenav.estimators.chang2021.model import (
    INERTIA_BASIS,
    error_jacobian,
    omega_LI_L,
    process_noise_density,
    propagate_mean,
    rate_derivative,
)
from tumblenav.estimators.chang2021.qmethod import start_attitude_sigma_deg
from tumblenav.estimators.chang2021.tuning import PoseTuning

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

LAYOUT_POSE = StateLayout(
    (
        Block("attitude", "quat", 3),  # q_ThatL
        Block("rate", "vector", 3),  # omega_ThatL_That
        Block("position", "vector", 3),  # r_L: the mass centre
        Block("velocity", "vector", 3),  # v_L
    )
)
NP = 12  # pose error dimension
NX = 13  # pose nominal dimension
NI = 5  # inertia parameters (inertia: estimated; zero covariance otherwise)
# their prior 1-sigma with inertia_sigma 'auto' (StateSteps.inertia_sigma_at)
INERTIA_SIGMA_WIDE = 0.15
INERTIA_SIGMA_NARROW = 0.05
NA = NP + NI  # where the features start in P
_J = slice(NP, NA)
_J_BASIS = INERTIA_BASIS  # J = I + D(j) (model.INERTIA_BASIS)
_J_MIN = 0.05  # smallest principal moment kept (of a mean moment 1)
_A, _W, _R, _V = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
_MAX_SIGMA = 1e6


@dataclass(frozen=True)
class MapMemo:
    """The map that travels with the belief: ``ids`` (m,) track indices (the feature axis of
    the measurements), ``s`` (m, 3) their positions about the mass centre in That (the state's
    feature block, rows in the order of ``P``'s), the start, and ``wild`` (consecutive wild
    epochs, see the module docstring)."""

    ids: IntArray
    s: Array
    s0: Array
    start: Start
    wild: int = 0
    check: tuple[int, Array, Array] | None = None  # last check epoch, q_ThatL, P_att there
    fails: int = 0  # failed divergence checks in a row
    resid: tuple[int, Array] | None = None  # epoch, post-step residuals (m, 3) (slip test)
    j: Array = dataclasses.field(default_factory=lambda: np.zeros(NI))  # inertia parameters


def inertia_of(j: Array) -> Array:
    """The inertia (3, 3) in That, normalised to a mean moment of 1, of the parameters ``j``."""
    return np.eye(3) + np.einsum("p,pij->ij", j, _J_BASIS)


def inertia_params(J: Array) -> Array:
    """``j`` of a symmetric positive-definite ``J`` (3, 3) (normalised first), its principal
    moments kept at or above ``_J_MIN`` of their mean: the estimate stays a body's."""
    lam, V = np.linalg.eigh(0.5 * (J + J.T))
    for _ in range(20):  # the floor is relative to the mean, which the floor raises
        floor = _J_MIN * max(float(np.mean(lam)), 1e-12)
        if lam.min() >= floor * (1.0 - 1e-9):
            break
        lam = np.maximum(lam, floor)
    J = (V * lam) @ V.T
    J = 3.0 * J / np.trace(J)
    return np.array([J[0, 0] - 1.0, J[1, 1] - 1.0, J[0, 1], J[0, 2], J[1, 2]])


def euler_inertia_jacobian(q_ThatL: Array, omega: Array, j: Array, n: float) -> Array:
    """``d(domega/dt) / dj`` (3, 5) of Chang 2021 eq. 3 (``rate_derivative``) over the inertia
    parameters: with ``g = J^-1 (-w_ti x J w_ti)``, ``J g = -w_ti x J w_ti`` differentiates to
    ``dg = J^-1 (-w_ti x (E_p w_ti) - E_p g)`` for the basis matrix ``E_p`` of ``j_p``
    (tumblenav's; checked against central differences in the tests)."""
    J = inertia_of(j)
    a = rot.quat_to_matrix(q_ThatL) @ omega_LI_L(n)
    w_ti = omega + a
    g = np.linalg.solve(J, -np.cross(w_ti, J @ w_ti))
    Ew = _J_BASIS @ w_ti  # (5, 3)
    rhs = -np.cross(w_ti, Ew) - _J_BASIS @ g  # (5, 3)
    return np.asarray(np.linalg.solve(J, rhs.T), dtype=float)


def inertia_gauge(J: Array) -> Array:
    """``Gamma`` (5, 3): the inertia parameters' change ``dj = Gamma dphi`` when That turns by
    ``dphi`` (vectors in That ``v -> Exp(dphi) v``, so ``J -> J + [dphi x] J - J [dphi x]``;
    the commutator is symmetric and traceless, a change of ``j``)."""
    G = np.empty((NI, 3))
    for c in range(3):
        S = rot.skew(np.eye(3)[c])
        D = S @ J - J @ S
        G[:, c] = (D[0, 0], D[1, 1], D[0, 1], D[0, 2], D[1, 2])
    return G


def gauge_transform(omega: Array, J: Array | None) -> Array:
    """``T`` (17, 17): pose and inertia errors ``dx`` -> gauge-aligned errors ``T dx`` in which
    a rotation ``dphi`` of That (the map's frame, unobservable) is ``dtheta = dphi`` alone:
    ``domega' = domega + [omega x] dtheta``, ``dj' = dj - Gamma(J) dtheta`` (``J`` None: the
    inertia is not a state). The features' part, ``ds' = ds + [s x] dtheta``, is applied where
    needed (module docstring, :func:`regauge`)."""
    T = np.eye(NA)
    T[_W, _A] = rot.skew(omega)
    if J is not None:
        T[_J, _A] = -inertia_gauge(J)
    return T


def gauge_inverse(T: Array) -> Array:
    """``T^-1`` of :func:`gauge_transform` (its off-diagonal blocks negated: they only read
    ``dtheta``, which ``T`` leaves as it is)."""
    return 2.0 * np.eye(NA) - T


def gauge_discretise(
    F: Array, Qc: Array, dt: float, rates: tuple[Array, Array, Array], J: Array | None
) -> tuple[Array, Array]:
    """``(Phi, Q_d)`` of the pose-and-inertia errors (17, 17) over ``dt``, discretised in the
    gauge-aligned errors ``dx' = T dx`` (:func:`gauge_transform`) and brought back: ``F' = T F
    T^-1 + dT/dt`` (``T`` reads the rate, whose derivative is Euler's), ``Phi = T_b^-1
    expm(F' dt) T_a``. A rotation of That, ``dx' = (dphi, 0, ...)``, is a null vector of
    ``F'`` at any linearisation point (``F N = dN/dt``, the dynamics' symmetry), so ``Phi``
    takes the gauge direction at the step's start exactly to the one at its end; a plain
    ``expm(F dt)`` (``F`` at the start) misses it by O(dt^2) a step. ``rates``: the rate at the
    start, its derivative there, the rate at the end; ``J`` the inertia (None when it is not
    a state). The noise drives the rate and velocity, which ``T`` leaves as they are."""
    w_a, wdot_a, w_b = rates
    Ta = gauge_transform(w_a, J)
    Tdot = np.zeros((NA, NA))
    Tdot[_W, _A] = rot.skew(wdot_a)
    Phi_g, Qd_g = discretise(Ta @ F @ gauge_inverse(Ta) + Tdot, Qc, dt)
    Tb_inv = gauge_inverse(gauge_transform(w_b, J))
    return Tb_inv @ Phi_g @ Ta, Tb_inv @ Qd_g @ Tb_inv.T


def regauge(
    P: Array,
    before: tuple[Array, Array, Array],
    after: tuple[Array, Array, Array],
    inertia_estimated: bool,
) -> Array:
    """The joint covariance of the errors about ``before`` (pose ``x``, inertia ``j``, map
    ``s`` (m, 3)) re-expressed about ``after`` (an update's estimate) in the same gauge-aligned
    errors: ``A = T(after)^-1 T(before)``, ``P -> A P A^T``; ``A`` adds ``[omega_b - omega_a
    x] dtheta`` to the rate error, ``(Gamma(J_a) - Gamma(J_b)) dtheta`` to the inertia's and
    ``[s_b - s_a x] dtheta`` to each feature's. The reset of an invariant EKF (Barrau &
    Bonnabel 2015): the plain EKF's identity reset leaves the variance along the old gauge
    direction, which the update could not change, to the new one, which it could have."""
    (xb, jb, sb), (xa, ja, sa) = before, after
    E = np.zeros((P.shape[0], 3))  # A = I + E [the attitude rows]
    E[_W] = rot.skew(xb[4:7] - xa[4:7])
    if inertia_estimated:
        E[_J] = inertia_gauge(inertia_of(ja)) - inertia_gauge(inertia_of(jb))
    E[NA:] = rot.skew(sb - sa).reshape(-1, 3)
    EP = E @ P[_A, :]
    P = P + EP + EP.T + E @ P[_A, _A] @ E.T
    return 0.5 * (P + P.T)


def gauge_direction(x: Array, j: Array | None, s: Array) -> Array:
    """``N`` (17 + 3m, 3): the errors of a rotation ``dphi`` of That at the estimate (pose
    ``x``, inertia ``j`` (None: not a state), map ``s`` (m, 3)): ``dtheta = dphi``, ``domega =
    -[omega x] dphi``, ``dj = Gamma(J) dphi``, ``ds_i = -[s_i x] dphi`` (no measurement sees
    it: :func:`measurement_jacobian` ``N = 0``)."""
    N = np.zeros((NA + 3 * len(s), 3))
    N[_A] = np.eye(3)
    N[_W] = -rot.skew(x[4:7])
    if j is not None:
        N[_J] = inertia_gauge(inertia_of(j))
    N[NA:] = -rot.skew(s).reshape(-1, 3)
    return N


def shift_direction(x: Array, s: Array) -> Array:
    """``N`` (17 + 3m, 3): the errors of a shift ``delta`` (That) of the map ``s`` (m, 3) with
    the mass centre moved against it at the pose ``x``: ``ds_i = delta``, ``dr = -R_LThat
    delta``, ``dv = -R_LThat [omega x] delta`` (its rate of change); no single epoch's
    measurement sees it (:func:`measurement_jacobian` ``N = 0``), only the target's turn
    does (:func:`absorbed_walk`)."""
    R_LT = rot.quat_to_matrix(x[0:4]).T
    N = np.zeros((NA + 3 * len(s), 3))
    N[_R] = -R_LT
    N[_V] = -R_LT @ rot.skew(x[4:7])
    N[NA:] = np.tile(np.eye(3), (len(s), 1))
    return N


def absorbed_walk(x: Array, tt: Array, Phi1: Array, walk: list[Array]) -> tuple[Array, Array]:
    """Covariances (3, 3) of the map's common rotation and common shift that the process
    noise's walk over a start window leaves in ekf-pose's torque-free batch fit
    (:func:`.batch.fit_window`); ``x`` the fit's end state (13), ``walk`` the walk's error
    covariances (17, 17) at the times ``tt`` (s) from k0 (zero there), ``Phi1`` the error
    transition between them (``Cov(dx_i, dx_j) = Phi1^(j-i) walk_i`` for ``j >= i``). The fit
    takes the attitude's walk ``dtheta(t)`` (zero at k0, where That is defined) as a line ``c
    + b t``: ``b`` into the rate, ``c`` into the map, a rotation of it with the attitude (the
    gauge direction); and the mass centre's walk ``dr(t)`` (L) as ``a + b' t + R_LThat(t)
    delta``: ``a, b'`` into its r0, v0, ``delta`` a shift of the map in That with the mass
    centre moved against it. Least squares on the window's epochs weighted alike, the
    attitude over the window at the end rate ``R_LThat(t) = R_LThat(T) Exp(omega (t - T))``;
    the shift's covariance at most the walk's at the window's end (its largest eigenvalue,
    on each axis; below) (tumblenav's, issue 18; ``tests/test_chang2021_estimator.py``
    checks both against simulated walks)."""
    n = len(tt)
    X = np.stack([np.ones(n), tt], axis=1)
    w = np.linalg.solve(X.T @ X, X.T)[0]  # c = sum_i w_i dtheta_i
    T = float(tt[-1])
    R_i = rot.quat_to_matrix(x[0:4]).T @ rot.exp_map(np.outer(tt - T, x[4:7]))  # R_LThat(t_i)
    Xs = np.zeros((n, 3, 9))
    Xs[:, :, 0:3] = np.eye(3)
    Xs[:, :, 3:6] = tt[:, None, None] * np.eye(3)
    Xs[:, :, 6:9] = R_i
    W = np.einsum("ij,nkj->nik", np.linalg.pinv(np.einsum("nki,nkj->ij", Xs, Xs)), Xs)
    W = W[:, 6:9, :]  # delta = sum_i W_i dr_i
    G_rot = np.zeros((3, 3))
    G_shift = np.zeros((3, 3))
    for i in range(n):
        C = walk[i]
        for j in range(i, n):
            both = 1.0 if j == i else 2.0  # (the pair (j, i) too: symmetrised below)
            G_rot += both * w[i] * w[j] * C[_A, _A]
            G_shift += both * W[j] @ C[_R, _R] @ W[i].T
            C = Phi1 @ C
    G_shift = 0.5 * (G_shift + G_shift.T)
    # Where the window turns the target too little to tell a shift of the map from the mass
    # centre's line, the regression is ill-conditioned and ``delta`` takes an arbitrary share
    # (its covariance grows as the inverse fourth power of the turn): no more of the walk
    # than the walk has at the window's end on any axis, the fit's own covariance carrying
    # the ambiguity (a session check: 0.05 rad/s over 20 s gave 2.8 times the end walk, 1e-3
    # rad/s 1.7e7). Each eigenvalue is clipped (not the whole scaled down), so that where
    # every axis is ill-conditioned the result is the cap itself, not the ill-conditioned
    # directions.
    cap = float(np.linalg.eigvalsh(walk[-1][_R, _R]).max())
    lam, V = np.linalg.eigh(G_shift)
    if lam.max() > cap:
        G_shift = (V * np.minimum(lam, cap)) @ V.T
    return 0.5 * (G_rot + G_rot.T), G_shift


def predicted_features(x: Array, s: Array) -> Array:
    """The measurement model ``rho_i = r + R_LThat s_i`` (m, 3) of the map points ``s`` (m,
    3) at the pose ``x`` (module docstring)."""
    return x[7:10] + s @ rot.quat_to_matrix(x[0:4])


def measurement_jacobian(q_ThatL: Array, s: Array) -> tuple[Array, Array]:
    """Pose columns ``d rho_i / d [dtheta, domega, dr, dv]`` (m, 3, 12) and the feature
    block ``d rho_i / d s_i`` (3, 3) of ``rho_i = r + R_LThat s_i`` (left error)."""
    R_LT = rot.quat_to_matrix(q_ThatL).T
    Hp = np.zeros((len(s), 3, NP))
    Hp[:, :, _A] = R_LT @ rot.skew(s)
    Hp[:, :, _R] = np.eye(3)
    return Hp, R_LT


def augmentation_jacobian(q_ThatL: Array, s: Array) -> tuple[Array, Array]:
    """``s = R_ThatL (rho - r)``: pose columns ``ds/d[dtheta, domega, dr, dv]`` (m, 3, 12)
    at ``s`` (m, 3), and ``ds/d rho`` (3, 3)."""
    R_TL = rot.quat_to_matrix(q_ThatL)
    J = np.zeros((len(s), 3, NP))
    J[:, :, _A] = -rot.skew(s)
    J[:, :, _R] = -R_TL
    return J, R_TL


def augment(x: Array, P: Array, s_map: Array, rho: Array, Sigma: Array) -> tuple[Array, Array]:
    """Append features observed at ``rho`` (a, 3) in L with covariances ``Sigma`` (a, 3, 3)
    to the map ``s_map`` (m, 3) and the joint covariance ``P`` (12 + 3m): returns the new map
    and covariance (12 + 3(m + a))."""
    a = len(rho)
    if a == 0:
        return s_map, P
    R_TL = rot.quat_to_matrix(x[0:4])
    s_new = (rho - x[7:10]) @ R_TL.T
    J, _ = augmentation_jacobian(x[0:4], s_new)
    J = J.reshape(3 * a, NP)
    D = P.shape[0]
    Pnx = J @ P[:NP, :]  # (3a, D): cross-covariance with the whole state
    Pnn = Pnx[:, :NP] @ J.T
    Sig_T = R_TL @ Sigma @ R_TL.T  # (a, 3, 3)
    idx = np.arange(3 * a).reshape(a, 3)
    Pnn[idx[:, :, None], idx[:, None, :]] += Sig_T
    out = np.empty((D + 3 * a, D + 3 * a))
    out[:D, :D] = P
    out[D:, :D] = Pnx
    out[:D, D:] = Pnx.T
    out[D:, D:] = 0.5 * (Pnn + Pnn.T)
    return np.vstack([s_map, s_new]), out


def _keep(P: Array, s: Array, keep: NDArray[np.bool_]) -> tuple[Array, Array]:
    """Marginalise the features where ``keep`` is False (their rows and columns go); ``s``
    (m, ...) the per-feature rows that go with them."""
    if keep.all():
        return P, s
    rows = np.concatenate(
        [np.arange(NA), (NA + 3 * np.flatnonzero(keep)[:, None] + np.arange(3)).ravel()]
    )
    return P[np.ix_(rows, rows)], s[keep]


def _for_tracks(default: float, template: float | None, track_ratio: float) -> float:
    """``template`` for tracks stated more precise after their first sighting (``track_ratio``,
    the tracked over the first sightings' noise variance, below 1: a template tracker), else
    ``default``."""
    return float(template) if template is not None and track_ratio < 1.0 else float(default)


def slip_quantile(tun: PoseTuning, track_ratio: float) -> float | None:
    """The slip test's chi-square quantile: ``tun.template_slip_probability`` for template
    tracks (:func:`_for_tracks`), else ``tun.slip_probability``; None (no slip test) when
    ``slip_probability`` is None."""
    if tun.slip_probability is None:
        return None
    return _for_tracks(tun.slip_probability, tun.template_slip_probability, track_ratio)


def gate_quantile(tun: PoseTuning, track_ratio: float) -> float:
    """The per-feature gate's chi-square quantile: ``tun.template_gate_probability`` for
    template tracks (:func:`_for_tracks`), else ``tun.feature_gate_probability``."""
    return _for_tracks(tun.feature_gate_probability, tun.template_gate_probability, track_ratio)


def tuning_for_tracks(tun: PoseTuning, meas) -> PoseTuning:
    """``tun`` with the slip test's and the per-feature gate's quantiles and the batch
    start's noise ratio resolved for these tracks (:func:`slip_quantile`,
    :func:`gate_quantile`, ``template_batch_noise_ratio`` by :func:`_for_tracks`, at the
    tracks' :func:`.measurements.track_noise_ratio`), once per run: the start, the batch fit,
    the updates and the registered map's pose fixes then read ``slip_probability``,
    ``feature_gate_probability`` and ``batch_noise_ratio`` as they apply."""
    r = track_noise_ratio(meas)
    return tun.model_copy(
        update={
            "slip_probability": slip_quantile(tun, r),
            "feature_gate_probability": gate_quantile(tun, r),
            "batch_noise_ratio": _for_tracks(
                tun.batch_noise_ratio, tun.template_batch_noise_ratio, r
            ),
        }
    )


def slip_test(e: Array, C: Array, probability: float, min_features: int = 10) -> NDArray[np.bool_]:
    """Which tracks slipped (jumped to another surface point) between two epochs: ``e`` (m, 3)
    each track's innovation now minus its residual after the last epoch's step (the measured
    displacement of the point less the displacement the filter's propagation predicts, so a
    bias the track has carried so far cancels and a jump shows whole), ``C`` (m, 3, 3) its
    covariance's shape (the triangulation covariances of both epochs). A jump of unknown size
    at a known epoch: the generalised likelihood ratio test of Willsky & Jones (1976, IEEE
    TAC 21(1), 108-112) reduces over a one-sample window to ``d_i^2 = e_i^T C_i^-1 e_i``
    against chi-square (3 dof). The scale of ``C`` is not trusted (the stated pixel noise
    covers the tracks' slow slide, several times their frame-to-frame noise), so it is
    estimated from the epoch's tracks, robustly (median of ``d^2`` over the chi-square
    median, as a MAD: Rousseeuw & Croux 1993): a slip is a track ``probability`` out of the
    epoch's own distribution. Fewer than ``min_features`` tracks: none flagged."""
    m = len(e)
    if m < min_features:
        return np.zeros(m, bool)
    d2 = np.einsum("mi,mij,mj->m", e, np.linalg.inv(C), e)
    c = float(np.median(d2)) / chi2.ppf(0.5, 3)
    if not (np.isfinite(c) and c > 0.0):
        return np.zeros(m, bool)
    return np.asarray(d2 > c * chi2.ppf(probability, 3))


def _collinear(rho: Array) -> bool:
    """The points (m, 3) lie on a line (or a point): their scatter has two null directions."""
    ev = np.linalg.eigvalsh(np.cov(rho.T))
    return not ev[1] > 1e-6 * max(ev[2], 1e-300)


def increment_check(
    tracks: FeatureTracks,
    a: int,
    k: int,
    q_a: Array,
    P_a: Array,
    q_k: Array,
    P_k: Array,
    floor_rad: float,
    min_features: int = 3,
) -> float | None:
    """Squared Mahalanobis distance (3 dof) between the filter's attitude increment from epoch
    ``a`` to ``k`` (``R_LThat(a) R_ThatL(k)``, from its estimates ``q_a``, ``q_k`` with
    covariances ``P_a``, ``P_k``: left errors in That) and the one the raw tracks say:
    Davenport's q-method (Chang 2021 eq. 27-28) on the features triangulated at both epochs,
    about their weighted centroids (``rho_i(a) - c_a = R_LThat(a) R_ThatL(k) (rho_i(k) -
    c_k)``), with its first-order covariance. No map and no filter state enter the measured
    increment, so a filter whose rate or attitude has run away cannot explain it away. The
    covariance is the sum of the q-method's, ``R_LThat(a) (P_a + P_k) R_ThatL(a)`` (the
    filter's, without the cross-covariance of the two epochs: larger than the truth when they
    are positively correlated, as a smoothly propagated attitude is) and ``floor_rad^2 I``;
    the q-method's part at least the two epochs' :func:`.qmethod.epoch_attitude_sigma`
    squared on each axis across the line of sight.
    None when fewer than ``min_features`` features span the interval or they are collinear."""
    from tumblenav.estimators.chang2021.qmethod import (
        epoch_attitude_sigma,
        q_method,
        q_method_covariance,
    )

    c = np.flatnonzero(tracks.ok_p[a] & tracks.ok_p[k])
    if len(c) < min_features:
        return None
    Sa, Sk = tracks.P[a, c], tracks.P[k, c]
    w = 3.0 / (np.trace(Sa, axis1=-2, axis2=-1) + np.trace(Sk, axis1=-2, axis2=-1))
    A = tracks.p[a, c] - w @ tracks.p[a, c] / w.sum()
    B = tracks.p[k, c] - w @ tracks.p[k, c] / w.sum()
    if _collinear(A):
        return None
    q, _ = q_method(A, B, w)  # A ~ R(q) B: R(q) = R_LThat(a) R_ThatL(k)
    R_m = rot.quat_to_matrix(q)
    P_m, _ = q_method_covariance(q, B, w, Sa + R_m @ Sk @ R_m.T)
    # across the line of sight, at least what the two epochs' depth noise says
    # (qmethod.epoch_attitude_sigma): the first-order covariance takes the lever arms from the
    # noisy points and, where the depth noise is as large as the target, reads it as a larger
    # target (2.2-8.6 deg per axis at Chang's printed 59 m against one epoch's ~15; there the
    # check failed runs whose attitude was right: 18 of 20 point-track runs stopped as diverged
    # with the batch start, seventeenth session)
    los = tracks.p[a, c].mean(axis=0)
    los = los / np.linalg.norm(los)
    M = np.eye(3) - np.outer(los, los)
    var_e = epoch_attitude_sigma(tracks.p[a, c], Sa) ** 2
    var_e += epoch_attitude_sigma(tracks.p[k, c], Sk) ** 2
    if np.isfinite(var_e):  # each axis across the line of sight raised to var_e
        B = np.linalg.svd(M)[0][:, :2]  # a basis of the plane
        lam, V = np.linalg.eigh(B.T @ P_m @ B)
        P_m = P_m + B @ V @ np.diag(np.maximum(0.0, var_e - lam)) @ V.T @ B.T
    R_LT_a = rot.quat_to_matrix(q_a).T
    D_f = R_LT_a @ rot.quat_to_matrix(q_k)  # the filter's increment
    S = P_m + R_LT_a @ (P_a + P_k) @ R_LT_a.T + floor_rad**2 * np.eye(3)
    d = rot.log_map(R_m @ D_f.T)
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(d))):
        return None
    return float(d @ np.linalg.solve(S, d))


@dataclass(frozen=True)
class StateSteps(TrackSteps):
    """ekf-pose with the feature map in the state, folded by
    :func:`tumblenav.estimators.base.fold` (module docstring)."""

    layout: StateLayout = LAYOUT_POSE

    @functools.cached_property
    def s2(self) -> float:
        """The tracks' pixel noise variance (px^2)."""
        return pixel_variance(self.meas)

    @functools.cached_property
    def track_ratio(self) -> float:
        """The tracked sightings' noise variance over the first sightings'
        (:func:`.measurements.track_noise_ratio`): an update weights a sighting by it, the
        map's augmentation by the first sighting's noise."""
        return track_noise_ratio(self.meas)

    @functools.cached_property
    def slide2(self) -> float:
        """The tracks' stated slide over the surface, px^2 per frame (0 for tracks that do not
        slide, such as simulated corners)."""
        return float(getattr(self.meas, "slide_px2_per_frame", 0.0))

    def map_walk(self, k: int, pred: Array, R_LT: Array) -> Array | None:
        """(m, 3, 3): the map points' random walk over one frame in That, or None when the
        tracks do not slide: the tracks' stated slide (``slide_px2_per_frame`` px^2 in each of
        u and v) across the left camera's line of sight at the predicted points
        (:func:`.measurements.slide_covariance`), rotated into That (tumblenav's, issue 18;
        Chang 2021 takes the map as rigid).

        Why: an LK track follows a rotating patch's texture, not the surface point it started
        on, and slides over the surface as it ages; a map point that stays where its first
        sightings put it then holds every later sighting to a point the track has left, and the
        slide (slow, common to a track's sightings) reads as pose information that white
        noise of the stated size does not cover. The walk lets each map point follow its track
        and bounds what a track's long history can tell. Measured on chang2021_close rendered
        images (runs 0, 1, 3, 7 of the campaign's seeds, window 40-120 s, a session script
        running ekf-pose on their cached tracks): NEES/dof per block attitude / rate /
        position / velocity / all 4.07 / 3.88 / 3.95 / 1.94 / 3.50 without, 0.54 / 0.64 /
        1.04 / 0.75 / 1.03 with the front end's 0.006 px^2 per frame, attitude RMS per axis
        0.11 / 0.12 / 0.17 -> 0.10 / 0.07 / 0.15 deg. Tried: the walk spread as
        :func:`.measurements.point_covariance` spreads pixel noise (mostly in depth; 0.008:
        all 1.15, 0.019: 0.81); no walk but each sighting's variance grown with its frames
        since its map point was anchored, noise^2 + (0.025 a)^2 (1.74: the position kept
        accumulating what the slides correlate). With point tracks (no slide) the walk is
        off; stated where the tracks do not slide it costs accuracy (a session check, point
        tracks at 0.1 px: attitude 0.032 -> 0.079 deg)."""
        if self.slide2 == 0.0:
            return None
        S = slide_covariance(pred, self.meas.q_CL[k], self.meas.rig, self.slide2)
        return np.einsum("ji,mjk,kl->mil", R_LT, S, R_LT)  # R_ThatL S R_LThat

    @functools.cached_property
    def age(self) -> IntArray:
        """(n, N): epochs each track has been observed in a row up to and including k."""
        ok = self.tracks.ok_p
        a = np.zeros(ok.shape, np.int64)
        run = np.zeros(ok.shape[1], np.int64)
        for k in range(ok.shape[0]):
            run = np.where(ok[k], run + 1, 0)
            a[k] = run
        return a

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        """The start (:func:`.init.start`, Chang's q-method and eq. 29 over the window), then
        the start epoch's features augmented from it."""
        s, info = self.start_at(k)
        if s is None:
            return None, info
        x = s.x[:NX].copy()
        P = s.P[:NP, :NP].copy()
        # The start's CW fit treats the window's map origins as independent (they are not: the
        # map is built from its own poses) and its r, v covariance has the rotating-offset
        # structure only; the filter starts from a plain prior instead: the mass centre within
        # prior_mass_centre_sigma_m of the fit on each axis, its velocity within |omega| times
        # that (the offset rotating with the target), uncorrelated.
        sig = self.tun.prior_mass_centre_sigma_m
        w = float(np.linalg.norm(x[4:7]))
        P[6:12, :] = 0.0
        P[:, 6:12] = 0.0
        P[_R, _R] = (s.P[_R, _R].trace() / 3 + sig**2) * np.eye(3)
        P[_V, _V] = (s.P[_V, _V].trace() / 3 + (w * sig) ** 2) * np.eye(3)
        if self.tun.start_fit == "batch":
            return self._batch(s, x, P)
        if self.tun.start_replay:
            return self._replay(s, x, P)
        P = self._with_inertia(P, s)
        ids, s_map, P = self._augment(x, P, np.zeros(0, np.int64), np.zeros((0, 6)), k)
        memo = MapMemo(ids, s_map[:, :3], s_map[:, 3:], s)
        return Belief(float(self.meas.t[k]), x, P, LAYOUT_POSE, memo), StepInfo()

    def _batch(self, s: Start, x_end: Array, P_end: Array) -> tuple[Belief | None, StepInfo]:
        """The start as a batch fit of the window (``start_fit: batch``,
        :func:`.batch.fit_window`) from the window's rate line at k0 and its mass-centre fit
        carried back to k0. The fit takes the window's motion as torque-free: where the
        scenario's process noise turns the attitude over the window by less than the fit
        resolves (:meth:`_window_noise` at most ``batch_noise_ratio``) its solution and
        covariance are the first belief; elsewhere the replay (:meth:`_replay`, which carries
        Q) runs from the fit's rate, mass centre and map (its first-estimate Jacobians there)
        instead of the q-method's and the first triangulations. Where the fit finds no
        solution (:func:`.batch.fit_window` None) the replay starts as without it."""
        tt = self.meas.t
        omega0 = s.omega_k0 if s.omega_k0 is not None else x_end[4:7]
        rv0 = cw_stm(self.n_orbit, float(tt[s.k0] - tt[s.k])) @ x_end[7:13]
        fit = fit_window(
            self.tracks,
            tt,
            s.k0,
            s.k,
            omega0,
            rv0,
            self.n_orbit,
            estimate_inertia=self.tun.inertia == "estimated",
            inertia_sigma=self.inertia_sigma_at(s),
            centre_sigma=self.tun.prior_mass_centre_sigma_m,
            noise_scale=self.tun.measurement_noise_scale * self.track_ratio,
            first_noise_scale=1.0,
            gate_probability=self.tun.feature_gate_probability,
            max_features=self.tun.max_map_features,
            j_fixed=None if self.tun.inertia == "estimated" else inertia_params(self.inertia),
            covariance_at=self._covariance_at if self._fit_at_predicted else None,
        )
        if fit is None:  # no solution: the replay as before
            return self._replay(s, x_end, P_end)
        ratio, P_fit = self._window_noise(fit, float(tt[s.k] - tt[s.k0]))
        cost = fit.cost / max(fit.dof, 1)
        s_fit = dataclasses.replace(s, fit="batch", fit_cost=cost, fit_noise_ratio=ratio)
        if ratio <= self.tun.batch_noise_ratio and self.slide2 == 0.0:  # (sliding tracks:
            # the fit's map is rigid, the replay carries their walk)
            return self._fit_belief(s_fit, fit, P_fit), StepInfo()
        lin = np.full((self.tracks.p.shape[1], 3), np.nan)
        lin[fit.window_ids] = fit.window_s
        x_fit = x_end.copy()
        x_fit[7:13] = cw_stm(self.n_orbit, float(tt[s.k] - tt[s.k0])) @ fit.rv0
        b, info = self._replay(
            dataclasses.replace(s_fit, omega_k0=fit.omega0, fit="batch+replay"), x_fit, P_end, lin
        )
        # (tracks that slide or are held by a template tracker: their slips are the replay's
        # slip test's to handle, the rigid fit only gates sightings; chang2021_close rendered
        # images, cached run 5: the fit refused the replay and the run ended at NEES/dof 510)
        point_tracks = self.slide2 == 0.0 and self.track_ratio >= 1.0
        if point_tracks and (b is None or self._replay_refused(b, fit, P_fit)):
            s_fit = dataclasses.replace(s_fit, fit="batch (replay refused)")
            return self._fit_belief(s_fit, fit, P_fit), StepInfo()
        return b, info

    def _fit_belief(self, s: Start, fit: BatchStart, P_fit: Array) -> Belief:
        """The batch fit as the first belief: its solution with the covariance ``P_fit``
        (:meth:`_window_noise`: the fit's own with what the window's process noise does to
        it)."""
        P = P_fit.copy()
        if self.tun.inertia != "estimated":
            P[_J, :] = 0.0
            P[:, _J] = 0.0
        # as the replay's last step leaves them: the divergence check's first epoch and the
        # slip test's residuals at the start epoch
        check = (s.k, fit.x[0:4].copy(), P[_A, _A].copy()) if self.tun.check_lag_frames else None
        resid = None
        if self.tun.slip_probability is not None:
            resid = (s.k, self.tracks.p[s.k, fit.ids] - predicted_features(fit.x, fit.s))
        memo = MapMemo(fit.ids, fit.s, fit.s.copy(), s, check=check, resid=resid, j=fit.j)
        return Belief(float(self.meas.t[s.k]), fit.x, P, LAYOUT_POSE, memo)

    def _replay_refused(self, b: Belief, fit: BatchStart, P_fit: Array) -> bool:
        """Whether the replay's end attitude departs from the batch fit's beyond their
        covariances (the fit's with the window's process noise, ``P_fit``, plus the replay's;
        both in That, defined at k0 alike; the two share their data, so the sum is a loose
        bound):
        chi-square (3 dof) beyond ``replay_gate_probability``. Why (tumblenav, issue 18): at
        range the replay can end degrees off with a 1-sigma of a tenth of one (chang_range40,
        40 m with disturbances, run 3: 3 deg at 0.1 deg, NEES/dof 69 over the run), where the
        fit plus the window's Q holds (run 3 with the fit as the first belief: 1.08)."""
        d = rot.log_map(rot.quat_to_matrix(fit.x[0:4]) @ rot.quat_to_matrix(b.x[0:4]).T)
        C = P_fit[_A, _A] + b.P[_A, _A]
        return float(d @ np.linalg.solve(C, d)) > chi2.ppf(self.tun.replay_gate_probability, 3)

    @property
    def _fit_at_predicted(self) -> bool:
        """Whether the batch start weights its sightings at their predicted points: with
        ``noise_at: predicted``, for point tracks (``track_ratio`` 1). Not for a template
        tracker's (measured, not understood; nineteenth session): on the built-in chang2021 at
        59 m on images, cached runs 0 / 1, the fit's window-noise ratio went 0.52 -> 1.46 on run
        0, which the replay then started (NEES/dof 112 -> 389; run 1 155 -> 173)."""
        return self.tun.noise_at == "predicted" and self.track_ratio >= 1.0

    def _covariance_at(self, p_L: Array, k: IntArray) -> Array:
        """The triangulation covariance (at the first sightings' noise) of points at ``p_L``
        (M, 3) seen at the epochs ``k`` (M,): the batch start's weights at its predicted
        points (``noise_at: predicted``, as the updates')."""
        return point_covariance(p_L, self.meas.q_CL[k], self.meas.rig, self.s2)

    def _window_noise(self, fit: BatchStart, T: float) -> tuple[float, Array]:
        """What the scenario's process noise over the window ``T`` (s) does to the torque-free
        fit: the largest eigenvalue of ``P_fit^-1 Q`` on the attitude (``Q`` the noise's
        covariance over ``T`` at the fit's end state, :func:`tumblenav.dynamics.integrators.
        discretise`: against what the fit resolves), and the fit's covariance (12 + 5 + 3m)
        with it: ``Q`` on the end state (the end attitude is no longer a function of the
        rate), and what the fit absorbs of the noise's walk over the window into its map
        (:func:`absorbed_walk`), as a rotation of That (the gauge direction,
        :func:`gauge_direction`) and as a shift of the map against the mass centre
        (:func:`shift_direction`).
        Why (tumblenav, issue 18, twentieth session): with ``Q`` alone, the fit as the first
        belief on chang_range40 (40 m, truth disturbed; window-noise ratio 18-41) gave
        NEES/dof 1.30 over 20 runs, its attitude 0.07 at the start and 2.5 ten seconds later
        (the filter re-fixed the attitude to a map whose rotation the fit had over-trusted);
        with both terms 1.04 (attitude 0.88, position 1.25 per block), chang_paper runs 0-9
        7.37 -> 1.61 (position 23 -> 3.4)."""
        x16 = np.concatenate([fit.x, np.zeros(3)])
        J = inertia_of(fit.j) if self.tun.inertia == "estimated" else self.inertia
        F = np.zeros((NA, NA))
        F[:NP, :NP] = error_jacobian(x16, J, self.n_orbit)[:NP, :NP]
        Qc = np.zeros((NA, NA))
        Qc[:NP, :NP] = process_noise_density(self.rate_noise(x16, J), self.q_accel)[:NP, :NP]
        # in steps of at most 1 s (one Van Loan step over the whole window loses Q's
        # positivity: eigenvalues down to -1e-7 on chang_paper, and the update's Cholesky fails)
        # and at least 2 (absorbed_walk's regression of the shift needs three epochs)
        steps = max(2, int(np.ceil(T)))
        Phi1, Q1 = discretise(F, Qc, T / steps)
        walk = [np.zeros((NA, NA))]  # the walk's covariance at each step from k0 (zero there)
        for _ in range(steps):
            walk.append(Phi1 @ walk[-1] @ Phi1.T + Q1)
        Qd = 0.5 * (walk[-1] + walk[-1].T)
        ev = np.linalg.eigvals(np.linalg.solve(fit.P[_A, _A], Qd[_A, _A]))
        G_rot, G_shift = absorbed_walk(fit.x, np.linspace(0.0, T, steps + 1), Phi1, walk)
        N = gauge_direction(fit.x, fit.j if self.tun.inertia == "estimated" else None, fit.s)
        Ns = shift_direction(fit.x, fit.s)
        P = fit.P.copy()
        P[:NA, :NA] += Qd
        P += N @ G_rot @ N.T + Ns @ G_shift @ Ns.T
        return float(np.max(np.real(ev))), 0.5 * (P + P.T)

    def _replay(
        self, s: Start, x_end: Array, P_end: Array, lin0: Array | None = None
    ) -> tuple[Belief | None, StepInfo]:
        """The filter run over the start window from k0, where That is defined (attitude
        identity, exact), with the window's rate and mass-centre fit (propagated back to k0)
        as a loose prior: the start's attitude is then the filter's over the window, not the
        window's last q-method fix (whose error the unobservable attitude gauge would keep).

        Each pass after the first is relinearised (an iterated filter, as Gauss-Newton
        relinearises a batch): the mass centre starts from the previous pass's, and with
        ``replay_relinearise_map`` each map point's first-estimate Jacobian (``fej``: the
        attitude columns ``R_LThat [s]x``) is evaluated at the previous pass's estimate of that
        point, not at its first triangulation. Why (tumblenav, issue 18): FEJ keeps the
        attitude gauge unobservable, but at the first triangulation's error (at 20 m with 0.5
        px ~0.2 m in depth against ~1 m lever arms) the gain spreads each innovation with the
        wrong lever arms, and the window's attitude came out over-confident: chang_range20,
        20 runs, window 40-100 s (``python benchmarks/block_nees.py
        docs/results/scenarios/consistency/chang_range20.yaml ekf-pose --seeds 0,...,19``):
        attitude block 1.91, all 1.43 with 3 plain passes (run 13's start 0.2 deg off at
        ~3 sigma); relinearised 1.10 / 1.12 with 3 passes, 1.07 / 1.06 with 4, 1.05 / 1.03
        with 5. The point covariance of the augmentation evaluated at the previous pass's
        points as well: no change (1.12 with 3 passes), not kept."""
        tt = self.meas.t
        k0, k1 = s.k0, s.k
        if s.fit == "window":
            s = dataclasses.replace(s, fit="replay")
        x = x_end.copy()
        x[0:4] = rot.IDENTITY
        Phi = cw_stm(self.n_orbit, float(tt[k0] - tt[k1]))
        x[7:13] = Phi @ x_end[7:13]
        P = np.zeros((NP, NP))
        P[_A, _A] = 1e-12 * np.eye(3)
        P[_W, _W] = P_end[_W, _W] * self.tun.start_rate_inflation
        if s.omega_k0 is not None and s.P_omega_k0 is not None:
            # the rate line's value at k0, not at the window's end: the body rate of a
            # non-spherical target drifts over the window (Euler; ~10 deg of axis in 20 s on
            # chang2021_close), and the end value at k0 starts the replay off its axis
            x[4:7] = s.omega_k0
            P[_W, _W] = s.P_omega_k0 * self.tun.start_rate_inflation
        P[_R, _R] = P_end[_R, _R]
        P[_V, _V] = P_end[_V, _V]
        P0 = self._with_inertia(P, s)
        b: Belief | None = None
        lin = lin0
        for _ in range(self.tun.start_passes):
            if b is not None:  # relinearise: the last pass's mass centre at k1, back to k0
                x[7:13] = Phi @ b.x[7:13]
            ids, s_map, P = self._augment(x, P0, np.zeros(0, np.int64), np.zeros((0, 6)), k0, lin)
            memo = MapMemo(ids, s_map[:, :3], s_map[:, 3:], s)
            b = Belief(float(tt[k0]), x.copy(), P, LAYOUT_POSE, memo)
            nxt = np.full((self.tracks.p.shape[1], 3), np.nan)
            for k in range(k0 + 1, k1 + 1):
                b, info = self.update(self.predict(b, float(tt[k])), k, False, lin)
                if info.diverged:
                    return None, StepInfo(skipped={"initialising": 1})
                nxt[b.memo.ids] = b.memo.s
            if self.tun.replay_relinearise_map:
                lin = nxt
        assert b is not None
        return self._release_axis(b), StepInfo()

    def _with_inertia(self, P: Array, s: Start) -> Array:
        """The pose covariance (12, 12) with the inertia parameters' prior (17, 17): with
        inertia 'estimated' each of the five has the variance :meth:`inertia_sigma_at`^2
        about the sphere (moments that differ by that fraction), else zero (not estimated)."""
        out = np.zeros((NA, NA))
        out[:NP, :NP] = P
        if self.tun.inertia == "estimated":
            out[_J, _J] = self.inertia_sigma_at(s) ** 2 * np.eye(NI)
        return out

    def inertia_sigma_at(self, s: Start) -> float:
        """The inertia parameters' prior 1-sigma for the start ``s``: the tuning's
        ``inertia_sigma``; with 'auto', INERTIA_SIGMA_WIDE where one epoch's features fix the
        attitude to within ``epoch_attitude_warn_deg`` over the start window
        (:func:`.qmethod.start_attitude_sigma_deg`), else INERTIA_SIGMA_NARROW (the nutation
        the inertia is learnt from is then buried in the tracks' errors; tuning.py says what
        was measured)."""
        v = self.tun.inertia_sigma
        if v != "auto":
            return float(v)
        sig = start_attitude_sigma_deg(self.tracks, s.k0, s.k)
        ok = np.isfinite(sig) and sig <= self.tun.epoch_attitude_warn_deg
        return INERTIA_SIGMA_WIDE if ok else INERTIA_SIGMA_NARROW

    def inertia_matrix(self, memo: MapMemo) -> Array:
        """The dynamics' inertia: the estimate (inertia 'estimated') or the tuning's."""
        if self.tun.inertia == "estimated":
            return inertia_of(memo.j)
        return self.inertia

    def _release_axis(self, b: Belief) -> Belief:
        """The mass centre along the rotation axis gets its prior's variance back
        (``prior_mass_centre_sigma_m``; tumblenav default): one window's rotation about a
        (nearly) fixed axis does not observe a shift of the mass centre along it (``r + d u``,
        ``s_i - d u`` fit every feature), but the filter, linearised at a jittering attitude,
        claims it does: on a spherical target (no nutation) the replay took the along-axis
        sigma from 0.71 m to 0.04 m while the error stayed 0.94 m. The direction ``N`` (``dr =
        u_L``, ``ds_i = -u_T``) gets ``sigma^2 N N^T``; what the target's nutation really tells
        comes back in the run."""
        if not self.tun.release_axis:
            return b
        x, memo = b.x, b.memo
        w = x[4:7]
        nw = float(np.linalg.norm(w))
        if not nw > 0.0:
            return b
        u_T = w / nw
        N = np.zeros(b.P.shape[0])
        N[_R] = rot.quat_to_matrix(x[0:4]).T @ u_T
        N[NA:] = np.tile(-u_T, len(memo.ids))
        P = b.P + self.tun.prior_mass_centre_sigma_m**2 * np.outer(N, N)
        return Belief(b.t, x, P, LAYOUT_POSE, memo)

    def invariant(self, memo: MapMemo, t: float) -> bool:
        """Whether the step at time ``t`` runs in the gauge-aligned errors
        (``invariant_errors``): after the start window only. The start replay keeps the
        first-estimate Jacobians, which its passes relinearise at the previous pass's map (a
        Gauss-Newton on the window that the current estimate's Jacobians cannot do: on
        Chang's printed 59 m with point tracks, runs 0-1, the replay in the gauge-aligned
        errors ends 5-8 deg off against 0.4-0.8 deg)."""
        # with a given non-spherical inertia a rotation of That changes the dynamics: no gauge
        given = self.tun.inertia == "given"
        return self.tun.invariant_errors and not given and t > float(self.meas.t[memo.start.k])

    def predict(self, belief: Belief, t: float) -> Belief:
        dt = t - belief.t
        if dt <= 0.0:
            return belief
        x16 = np.concatenate([belief.x, np.zeros(3)])
        J = self.inertia_matrix(belief.memo)
        q_rate = self.rate_noise(x16, J)
        F = np.zeros((NA, NA))
        F[:NP, :NP] = error_jacobian(x16, J, self.n_orbit)[:NP, :NP]
        if self.tun.inertia == "estimated":
            F[_W, _J] = euler_inertia_jacobian(x16[0:4], x16[4:7], belief.memo.j, self.n_orbit)
        Qc = np.zeros((NA, NA))
        Qc[:NP, :NP] = process_noise_density(q_rate, self.q_accel)[:NP, :NP]
        x = propagate_mean(x16, dt, J, self.n_orbit)[:NX]
        if self.invariant(belief.memo, t):
            Jg = J if self.tun.inertia == "estimated" else None
            wdot = rate_derivative(x16[0:4], x16[4:7], J, self.n_orbit)
            Phi, Qd = gauge_discretise(F, Qc, dt, (x16[4:7], wdot, x[4:7]), Jg)
        else:
            Phi, Qd = discretise(F, Qc, dt)
        P = belief.P.copy()
        P[:NA, :] = Phi @ P[:NA, :]
        P[:, :NA] = P[:, :NA] @ Phi.T
        P[:NA, :NA] += Qd
        return Belief(t, x, 0.5 * (P + P.T), LAYOUT_POSE, belief.memo)

    def _augment(
        self, x: Array, P: Array, ids: IntArray, s_map: Array, k: int, lin: Array | None = None
    ) -> tuple[IntArray, Array, Array]:
        """Fill the free slots (``max_map_features``) with the observed tracks not in the
        map, the longest tracked so far first."""
        free = self.tun.max_map_features - len(ids)
        if free <= 0:
            return ids, s_map, P
        tr = self.tracks
        obs = np.flatnonzero(tr.ok_p[k])
        cand = obs[~np.isin(obs, ids)]
        if len(cand) == 0:
            return ids, s_map, P
        order = np.argsort(-self.age[k, cand], kind="stable")
        new = cand[order[:free]]
        s3, P = augment(x, P, s_map[:, :3], tr.p[k, new], tr.P[k, new])
        s_new = s3[len(ids) :]
        s_first = s_new.copy()  # the first estimate, where the attitude columns are evaluated
        if lin is not None:  # the start replay's later passes: the previous pass's map
            good = np.all(np.isfinite(lin[new]), axis=1)
            s_first[good] = lin[new][good]
        s_map = np.vstack([s_map, np.hstack([s_new, s_first])])  # current and first estimates
        return np.concatenate([ids, new]), s_map, P

    def update(
        self, belief: Belief, k: int, started: bool, lin: Array | None = None
    ) -> tuple[Belief, StepInfo]:
        x, P, memo = belief.x, belief.P, belief.memo
        ids, s_map = memo.ids, np.hstack([memo.s, memo.s0])  # (m, 6): current, first
        j = memo.j
        if started:
            return belief, StepInfo()
        tr, tun = self.tracks, self.tun
        skipped: dict[str, int] = {}
        # tracks that ended (not observed now): marginalised
        seen = tr.ok_p[k, ids]
        P, s_map = _keep(P, s_map, seen)
        ids = ids[seen]
        slips = 0
        if tun.slip_probability is not None and memo.resid is not None:
            # slipped tracks are re-anchored: dropped here, re-augmented from this frame below
            kp, res = memo.resid
            e = tr.p[k, ids] - predicted_features(x, s_map[:, :3]) - res[seen]
            # (at the first sightings' noise: the test scales by the epoch's own tracks, so the
            # tracked noise's ratio, track_ratio, would change nothing)
            slip = slip_test(e, tr.P[k, ids] + tr.P[kp, ids], tun.slip_probability)
            slips = int(slip.sum())
            if slips:
                skipped["slips"] = slips
                P, s_map = _keep(P, s_map, ~slip)
                ids = ids[~slip]
        nis, dof, rejected, wild = float("nan"), 0, 0, memo.wild
        m = len(ids)
        if m == 0:
            skipped["no_features" if not tr.ok_p[k].any() else "too_few_features"] = 1
        elif m < tun.min_features:
            skipped["too_few_features"] = 1
        elif _collinear(tr.p[k, ids]):
            skipped["degenerate_geometry"] = 1  # the points do not fix a rotation: no update
            return Belief(
                belief.t,
                x,
                P,
                LAYOUT_POSE,
                MapMemo(
                    ids,
                    s_map[:, :3],
                    s_map[:, 3:],
                    memo.start,
                    wild,
                    memo.check,
                    memo.fails,
                    None,
                    j,
                ),
            ), StepInfo(skipped=skipped)
        else:
            D = P.shape[0]
            # first-estimate Jacobian (FEJ) of the attitude columns, see the module docstring
            inv = self.invariant(memo, float(self.meas.t[k]))
            fej = tun.fej and not inv
            Hp, R_LT = measurement_jacobian(x[0:4], s_map[:, 3:] if fej else s_map[:, :3])
            pred = predicted_features(x, s_map[:, :3])
            nu = tr.p[k, ids] - pred  # (m, 3)
            Sig = tr.P[k, ids]
            if tun.noise_at == "predicted":  # not leaning to the points measured too near
                Sig_p = point_covariance(pred, self.meas.q_CL[k], self.meas.rig, self.s2)
                Sig = np.where(np.isfinite(Sig_p), Sig_p, Sig)
            Sig = tun.measurement_noise_scale * self.track_ratio * Sig
            fcols = NA + 3 * np.arange(m)[:, None] + np.arange(3)  # (m, 3) feature columns
            walk = self.map_walk(k, pred, R_LT)
            if walk is not None:  # the map points follow their tracks' slide (map_walk)
                P = P.copy()
                P[fcols[:, :, None], fcols[:, None, :]] += walk
            H = np.zeros((3 * m, D))
            H[:, :NP] = Hp.reshape(3 * m, NP)
            rows = np.arange(3 * m).reshape(m, 3)
            H[rows[:, :, None], fcols[:, None, :]] = R_LT
            # H P and H P H^T from H's blocks (pose columns, one R_LThat per feature; the
            # features fill P from NA on, H is zero in the inertia columns): the dense
            # products cost 3m D^2 and 9m^2 D
            HP = H[:, :NP] @ P[:NP, :] + np.einsum(
                "ij,mjd->mid", R_LT, P[NA:].reshape(m, 3, D)
            ).reshape(3 * m, D)
            S_all = HP[:, :NP] @ H[:, :NP].T + np.einsum(
                "amj,kj->amk", HP[:, NA:].reshape(3 * m, m, 3), R_LT
            ).reshape(3 * m, 3 * m)  # per-feature blocks: H_i P H_i^T
            S_blk = S_all[rows[:, :, None], rows[:, None, :]] + Sig  # (m, 3, 3)
            d2 = np.einsum("mi,mij,mj->m", nu, np.linalg.inv(S_blk), nu)
            ok = d2 <= chi2.ppf(tun.feature_gate_probability, 3)
            rejected = int(m - ok.sum())
            if rejected:
                skipped["gated_out"] = rejected
            if ok.sum() < 0.5 * m:
                wild += 1  # the prediction explains less than half the map: no update
                skipped["wild_epoch"] = 1
                if wild >= tun.divergence_epochs:
                    return belief, StepInfo(diverged=True, skipped=skipped | {"diverged": 1})
            else:
                wild = 0
                r_ok = rows[ok].ravel()
                Hk, nuk = H[r_ok], nu[ok].ravel()
                Rk = np.zeros((len(r_ok), len(r_ok)))
                ro = np.arange(len(r_ok)).reshape(-1, 3)
                Rk[ro[:, :, None], ro[:, None, :]] = Sig[ok]
                Sk = S_all[np.ix_(r_ok, r_ok)] + Rk
                L = np.linalg.cholesky(Sk)
                Kt = solve_triangular(  # S^-1 H P = K^T
                    L,
                    solve_triangular(L, HP[r_ok], lower=True, check_finite=False),
                    lower=True,
                    trans="T",
                    check_finite=False,
                )  # check_finite off: a non-finite state ends as diverged below, not in a raise
                K = Kt.T
                A = np.eye(D) - K @ Hk
                P = A @ P @ A.T + K @ Rk @ K.T  # Joseph form
                P = 0.5 * (P + P.T)
                dx = K @ nuk
                x_prior, j_prior, s_prior = x, j, s_map[:, :3].copy()
                x = LAYOUT_POSE.boxplus(x, dx[:NP])
                if tun.inertia == "estimated":
                    j = inertia_params(inertia_of(j + dx[_J]))
                s_map[:, :3] += dx[NA:].reshape(m, 3)
                if inv:
                    P = regauge(
                        P,
                        (x_prior, j_prior, s_prior),
                        (x, j, s_map[:, :3]),
                        tun.inertia == "estimated",
                    )
                w = solve_triangular(L, nuk, lower=True, check_finite=False)
                nis, dof = float(w @ w), len(nuk)
                # rejected features leave the state (suspect tracks)
                P, s_map = _keep(P, s_map, ok)
                ids = ids[ok]
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))) or (
            P.shape[0] and np.max(np.diag(P)) > _MAX_SIGMA**2
        ):
            return belief, StepInfo(diverged=True, skipped={"diverged": 1})
        check, fails = memo.check, memo.fails
        lag = tun.check_lag_frames
        if lag and k >= memo.start.k:  # after the start window (not in the replay)
            if check is not None and k - check[0] >= lag:
                d2 = increment_check(
                    tr,
                    check[0],
                    k,
                    check[1],
                    check[2],
                    x[0:4],
                    P[_A, _A],
                    np.radians(tun.check_floor_deg),
                    tun.min_features,
                )
                if d2 is not None:
                    fails = fails + 1 if d2 > chi2.ppf(tun.check_gate_probability, 3) else 0
                    if fails:
                        skipped["failed_checks"] = 1
                    if fails >= tun.check_fails:
                        return belief, StepInfo(diverged=True, skipped=skipped | {"diverged": 1})
                check = None
            if check is None:
                check = (k, x[0:4].copy(), P[_A, _A].copy())
        ids, s_map, P = self._augment(x, P, ids, s_map, k, lin)
        resid = None
        if tun.slip_probability is not None:
            resid = (k, tr.p[k, ids] - predicted_features(x, s_map[:, :3]))
        return Belief(
            belief.t,
            x,
            P,
            LAYOUT_POSE,
            MapMemo(ids, s_map[:, :3], s_map[:, 3:], memo.start, wild, check, fails, resid, j),
        ), (StepInfo(nis=nis, dof=dof, rejected=rejected, skipped=skipped))

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P[:NP, :NP]
