"""Chang 2021 Sec. 2.1 in tumblenav's conventions: state, dynamics, error-state Jacobian
(eq. 1-25) and the discrete propagation of ``ekf-pose``.

State (Chang 2021 eq. 1, with the chaser frame c = L, the chaser's LVLH frame)::

    x = [q_ThatL (4), omega_ThatL_That (3), r_L (3), v_L (3), b (3)]     (13 + 3)
    dx = [dtheta (3), domega (3), dr (3), dv (3), db (3)]                (12 + 3, eq. 5)

The first 12 error states are Chang's (eq. 5). ``b`` (tumblenav's, the standard ``offset``
block) is where the mass centre sits about the origin of the estimator's feature map, in That:
Chang registers each feature about the mass centre (eq. 30's ``r_i^t``) from a truth-based
start (Sec. 4.2); without the truth the start window leaves the mass centre uncertain along
the rotation axis, and a registration error that the 12 states cannot hold would make the
filter claim a position accuracy it does not have. By default ``b`` is a Schmidt (consider)
state: never updated (Chang's fixed registration), its uncertainty carried in the
covariance; ``mass_centre: estimated`` lets the filter learn it.

* ``That`` is the estimator's own target body frame, fixed to the target and defined at its
  first usable epoch k0 by ``R_ThatL(k0) = I`` (see :mod:`.init`); its origin is the estimated
  mass centre. ``q_ThatL`` maps L into That (Chang's ``q_ct`` / ``A(q) = R_c^t``, written as a
  Hamilton quaternion); ``omega_ThatL_That`` is the target's rate relative to L, in That
  (Chang's ``omega_tc^t``). ``r_L``, ``v_L``: the mass centre relative to the chaser, in L,
  velocity as seen from L (Chang's ``rho``, ``rho_dot``).
* Attitude error: tumblenav's left error ``q = exp(dtheta) (x) q_hat`` (:mod:`tumblenav.
  rotations`), ``R = Exp(dtheta) R_hat ~ (I + [dtheta x]) R_hat``. Chang's eq. 9 writes
  ``R = (I - [da x]) R_hat`` (Shuster), i.e. ``da = -dtheta``.
* L rotates w.r.t. I at ``omega_LI_L = [0, -n, 0]`` (frames.lvlh_rate: ``y_L`` is the negative
  orbit normal; Chang's printed ``[0, 0, -n]`` is a sign slip in its own Hill frame, notes
  Sec. 0.4). The chaser is "LVLH-pointing and torque-free" (eq. 21): its term of eq. 3
  vanishes and ``omega_LI_L`` is constant.

Dynamics (eq. 2-4, in this convention)::

    dq_ThatL/dt = -1/2 [omega; 0] (x) q_ThatL                     (eq. 2, Hamilton form)
    omega_ti = omega + a,     a = R_ThatL omega_LI_L
    domega/dt = I^-1 (-omega_ti x I omega_ti) + omega x a          (eq. 3 = eq. 14, T^t = 0)
    d[r; v]/dt = A_CW [r; v]                                        (eq. 4: CW in our L)

Error dynamics (derived here, every block checked against central differences in
tests/test_chang2021_estimator.py)::

    dtheta' = -[omega x] dtheta - domega                                          (eq. 8)
    domega' = F_wq dtheta + F_ww domega                                           (eq. 10)
    F_wq = { I^-1 ([omega_ti x] I - [(I omega_ti) x]) - [omega x] } [a x]         (eq. 23)
    F_ww = I^-1 ([(I omega_ti) x] - [omega_ti x] I) - [a x]                       (eq. 24)

Eq. 23 as printed is ``2 I^-1 [-(I w_ti)x + (w_ti x) I][(R w_ci)x] - 2 [w_tc x][(R w_ci)x]``:
the finite differences say the factor is wrong. In tumblenav's left error the correct
``F_wq`` is **1/2 x the printed matrix**; in the paper's own eq. 9 error ``da = -dtheta`` it is
**-1/2 x printed** (as the project notes derive). The printed factor 2 is what one gets by
differentiating with respect to the quaternion's vector part ``dq_v = da/2``. Eq. 8's signs
are the paper's once ``da = -dtheta``; eq. 24 is correct as printed.

Process noise (eq. 25): white torque noise drives ``domega`` (``I^-1 w_a``; here directly a
rate random walk of spectral density ``q_w``, rad^2/s^3) and a white acceleration drives
``dv`` (``q_a``, m^2/s^3); ``Phi`` and ``Q_d`` by :func:`tumblenav.dynamics.integrators.
discretise` on the 15x15 ``F`` (eq. 13, zero rows for ``b``). The nominal state is propagated by RK4 (attitude and
rate) and the closed-form CW transition (position and velocity).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import discretise, rk4_step
from tumblenav.dynamics.relative_orbit import cw_stm, hill_matrix
from tumblenav.estimators.base import Block, StateLayout

Array = NDArray[np.float64]

LAYOUT = StateLayout(
    (
        Block("attitude", "quat", 3),  # q_ThatL
        Block("rate", "vector", 3),  # omega_ThatL_That
        Block("position", "vector", 3),  # r_L
        Block("velocity", "vector", 3),  # v_L
        Block("offset", "vector", 3),  # b: mass centre about the feature map's origin, in That
    )
)
_NAMES = ("attitude", "rate", "position", "velocity", "offset")
X_ATT, X_RATE, X_POS, X_VEL, X_OFF = (LAYOUT.nom(n) for n in _NAMES)
E_ATT, E_RATE, E_POS, E_VEL, E_OFF = (LAYOUT.err(n) for n in _NAMES)
DIM = LAYOUT.dim  # 15

# ekf-pose's estimated inertia (map: state; tumblenav's): J = I + D(j), D symmetric and
# traceless (the scale is not observable), j = (a, b, d, e, f),
# D = [[a, d, e], [d, b, f], [e, f, -a - b]]: D(j) = sum_p j_p INERTIA_BASIS[p]
INERTIA_BASIS = np.zeros((5, 3, 3))
INERTIA_BASIS[0, 0, 0], INERTIA_BASIS[0, 2, 2] = 1.0, -1.0
INERTIA_BASIS[1, 1, 1], INERTIA_BASIS[1, 2, 2] = 1.0, -1.0
for _i, (_r, _c) in enumerate(((0, 1), (0, 2), (1, 2))):
    INERTIA_BASIS[2 + _i, _r, _c] = INERTIA_BASIS[2 + _i, _c, _r] = 1.0


def omega_LI_L(n: float) -> Array:
    """Rate of L w.r.t. I, in L, for a circular orbit of mean motion ``n`` (rad/s)."""
    return np.array([0.0, -float(n), 0.0])


def rate_derivative(q_ThatL: Array, omega: Array, inertia: Array, n: float) -> Array:
    """Chang 2021 eq. 3 (= eq. 14) with T^t = 0 and the chaser term of eq. 21 zero:
    ``domega/dt = I^-1 (-w_ti x I w_ti) + omega x (R_ThatL omega_LI_L)``."""
    a = rot.quat_to_matrix(q_ThatL) @ omega_LI_L(n)
    w_ti = omega + a
    Iw = inertia @ w_ti
    return np.linalg.solve(inertia, -np.cross(w_ti, Iw)) + np.cross(omega, a)


def error_jacobian(x: Array, inertia: Array, n: float) -> Array:
    """``F`` (15, 15) of the error dynamics at ``x`` (Chang 2021 eq. 13 with eq. 8, 23, 24 in
    the left error; see the module docstring for the corrected eq. 23)."""
    q, w = x[X_ATT], x[X_RATE]
    a = rot.quat_to_matrix(q) @ omega_LI_L(n)
    w_ti = w + a
    Ii = np.linalg.inv(inertia)
    S_w, S_a, S_ti = rot.skew(w), rot.skew(a), rot.skew(w_ti)
    S_Iw = rot.skew(inertia @ w_ti)
    F = np.zeros((DIM, DIM))  # the offset is constant in That: its rows are zero
    F[E_ATT, E_ATT] = -S_w  # Chang 2021 eq. 8 (da = -dtheta)
    F[E_ATT, E_RATE] = -np.eye(3)
    F[E_RATE, E_ATT] = (
        Ii @ (S_ti @ inertia - S_Iw) - S_w
    ) @ S_a  # eq. 23, corrected: 1/2 x printed
    F[E_RATE, E_RATE] = Ii @ (S_Iw - S_ti @ inertia) - S_a  # eq. 24
    F[E_POS.start : E_VEL.stop, E_POS.start : E_VEL.stop] = hill_matrix(n)  # eq. 11/13: CW in our L
    return F


def attitude_rhs(inertia: Array, n: float):
    """``(q, omega) -> (dq/dt, domega/dt)`` of eq. 2-3 for :func:`rk4_step`."""

    def f(q: Array, w: Array) -> tuple[Array, Array]:
        return rot.quat_derivative(q, w), rate_derivative(q, w, inertia, n)

    return f


def propagate_mean(x: Array, dt: float, inertia: Array, n: float) -> Array:
    """Nominal state after ``dt``: RK4 on eq. 2-3 (one step per call; the filter calls it at
    the frame rate), closed-form CW on eq. 4."""
    out = np.empty_like(x)
    q, w = rk4_step(attitude_rhs(inertia, n), (x[X_ATT], x[X_RATE]), dt)
    out[X_ATT] = rot.quat_normalize(q)
    out[X_RATE] = w
    out[X_POS.start : X_VEL.stop] = cw_stm(n, dt) @ x[X_POS.start : X_VEL.stop]
    out[X_OFF] = x[X_OFF]
    return out


def process_noise_density(q_rate: float | Array, q_accel: float) -> Array:
    """Continuous ``G Q G^T`` (15, 15) of eq. 25: ``q_rate`` on the rate (rad^2/s^3; one
    value per axis, or (3, 3) in That), ``q_accel`` on the velocity (m^2/s^3)."""
    Qc = np.zeros((DIM, DIM))
    Qc[E_RATE, E_RATE] = q_rate * np.eye(3) if np.ndim(q_rate) == 0 else q_rate
    Qc[E_VEL, E_VEL] = q_accel * np.eye(3)
    return Qc


def propagate(
    x: Array,
    P: Array,
    dt: float,
    inertia: Array,
    n: float,
    q_rate: float | Array,
    q_accel: float,
) -> tuple[Array, Array]:
    """EKF prediction over ``dt``: the mean by :func:`propagate_mean`, the covariance by
    ``Phi P Phi^T + Q_d`` with ``(Phi, Q_d)`` from :func:`discretise` (Chang 2021 eq. 13, 25;
    the Jacobian at the start of the step)."""
    if dt <= 0.0:
        return x, P
    F = error_jacobian(x, inertia, n)
    Phi, Qd = discretise(F, process_noise_density(q_rate, q_accel), dt)
    x1 = propagate_mean(x, dt, inertia, n)
    P1 = Phi @ P @ Phi.T + Qd
    return x1, 0.5 * (P1 + P1.T)
