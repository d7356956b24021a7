"""Yu 2019's filter model: the state layout, the rigid-body dynamics with the full inertia\nratios and the mass-centre offset (eq. 28-33), propagation, the start covariance and the\nfix measurement (eq. 34-41)."""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.dynamics.integrators import discretise, rk4_step
from tumblenav.dynamics.relative_orbit import cw_discrete
from tumblenav.estimators.base import (
    Block,
    StateLayout,
)
from tumblenav.estimators.yu2019.tuning import DepthTuning, _sigma_inertia

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


SLOW_PER_RECTANGLE = 6  # the slow errors of each rectangle's fixes (fixes.COMPONENTS)


def filter_layout(n_rectangles: int, range_bias: bool = False) -> StateLayout:
    """LAYOUT and, after it (tumblenav, beyond Yu 2019; :mod:`.filter`): the fixes' common
    bias along the line of sight (``range_bias``: ``fix_range_bias``, one state), and the
    slowly varying errors of each model rectangle's fixes (``fix_errors``,
    ``SLOW_PER_RECTANGLE`` per rectangle in the model's order), all normalised to unit
    variance. The estimate reports LAYOUT only (the marginal of these)."""
    blocks = list(LAYOUT.blocks)
    if range_bias:
        blocks.append(Block("fix_range_bias", "vector", 1))
    if n_rectangles:
        blocks.append(Block("fix_errors", "vector", SLOW_PER_RECTANGLE * n_rectangles))
    return StateLayout(tuple(blocks))


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


def inertia_matrix(l: Array) -> Array:
    """Yu 2019 eq. 29, normalised by Ixx."""
    return np.array([[1.0, l[2], l[3]], [l[2], l[0], l[4]], [l[3], l[4], l[1]]])


def physical_inertia(l: Array) -> bool:
    """True when the ratios of eq. 29 give a physical inertia: positive definite (all
    principal moments above 1e-3 of Ixx; with a zero or negative moment the Euler equations
    explode) and the principal moments obey the triangle inequality (the two smaller sum to
    at least the largest, as for any rigid body: the scenario checks the same of the truth)."""
    if not np.all(np.isfinite(l)):
        return False
    m = np.linalg.eigvalsh(inertia_matrix(l))
    return bool(m[0] > 1e-3 and m[0] + m[1] >= m[2] * (1 - 1e-9))


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


def spin_axis_fixed(
    w: Array,
    l: Array,
    unexcited: NDArray[np.bool_],
    P_w: Array | None = None,
    max_nutation: float = 0.05,
) -> bool:
    """True for a spin whose axis stays put in T (tumblenav default): three ratios unexcited
    (:func:`unexcited_ratios`: a spin about a principal axis), or the axis turning in T
    (eq. 28's ``omega'``) at below ``max_nutation`` of the spin, ``max_nutation |omega|^2``,
    plus 3 sigma of what the uncertainty makes of ``omega'``: ``P_w`` the rate's (3, 3)
    covariance, or the (8, 8) covariance of the rate and the ratios (a guessed inertia whose
    products of inertia are not yet known predicts a nutation the motion need not have)."""
    wn = float(np.linalg.norm(w))
    if wn == 0.0 or not physical_inertia(l):
        return False
    if unexcited.sum() >= 3:
        return True
    wdot = euler_full(w, l)
    noise = 0.0
    if P_w is not None:
        F = rotational_F(w, l)
        J = F[_E_RATE, _E_RATE] if len(P_w) == 3 else F[_E_RATE, _E_RATE.start : _E_INERTIA.stop]
        noise = float(np.trace(J @ P_w @ J.T))
    return bool(wdot @ wdot < (max_nutation * wn**2) ** 2 + 9.0 * noise)


def _propagate(
    x: Array, P: Array, dt: float, n: float, q_c: float, q_t: float | None = None
) -> tuple[Array, Array]:
    """Predict over ``dt``: RK4 of the attitude and rate (Yu 2019 eq. 28 with the quaternion
    kinematics), the Hill model (eq. 26-27) for ``[r, v]``, and ``P`` through the discretised
    error dynamics (series of Hu 2024 eq. 38-39). With ``q_t`` None: Yu's single Q, ``q_c`` on
    every rate axis and on the mass centre's acceleration; otherwise the scenario's process
    noise, ``q_c`` the rotational density (an isotropic torque, :func:`_Qc_rot` at the
    estimated ratios) and ``q_t`` the translational one (m^2/s^3)."""
    q, w, l = x[_X_ATT], x[_X_RATE], x[_X_INERTIA]

    def f(q_, w_):
        return rot.quat_derivative(q_, w_), euler_full(w_, l)

    q_new, w_new = rk4_step(f, (q, w), dt)
    x = x.copy()
    x[_X_ATT] = q_new / np.linalg.norm(q_new)
    x[_X_RATE] = w_new
    Qc = _Qc_rot(q_c) if q_t is None else _Qc_rot(q_c, l)
    Phr, Qr = discretise(rotational_F(w, l), Qc, dt)
    Pht, Qt = cw_discrete(n, q_c if q_t is None else q_t, dt)
    x[_X_TRANS] = Pht @ x[_X_TRANS]
    # states beyond LAYOUT (the fixes' slowly varying errors, filter.py) are constant here:
    # they decay when their rectangle is seen again (exact for states that neither drive nor
    # are driven by the others)
    Phi = np.eye(len(P))
    Phi[_E_ROT, _E_ROT] = Phr
    Phi[_E_TRANS, _E_TRANS] = Pht
    Qk = np.zeros_like(P)
    Qk[_E_ROT, _E_ROT] = Qr
    Qk[_E_TRANS, _E_TRANS] = Qt
    return x, Phi @ P @ Phi.T + Qk


def _Qc_rot(q_c: float, l: Array | None = None) -> Array:
    """Spectral density of ``[dtheta, domega, dl]``. Without ``l``: ``q_c`` on every rate
    axis (Yu 2019's single Q: w2 = disturbing torque / Ixx). With the ratios ``l`` (eq. 29):
    an isotropic torque whose angular acceleration about the largest moment has density
    ``q_c``, i.e. ``q_c I_max^2 I^-2`` in T (the scenario's process noise,
    :mod:`tumblenav.dynamics.disturbances`; Hu 2024 eq. 22's J)."""
    Q = np.zeros((_E_ROT.stop, _E_ROT.stop))
    if l is None or not physical_inertia(l):
        Q[_E_RATE, _E_RATE] = q_c * np.eye(3)
        return Q
    lam, V = np.linalg.eigh(inertia_matrix(l))
    Q[_E_RATE, _E_RATE] = q_c * (V * (lam[-1] / lam) ** 2) @ V.T
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
    # a draw that is no rigid body (physical_inertia: e.g. the two smaller moments no longer
    # summing to the largest) would freeze the ratios there: drawn again (tumblenav default)
    for _ in range(100):
        draw = given + _sigma_inertia(tun) * rng.normal(size=5)
        if physical_inertia(draw):
            return draw
    return given


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


# Levi-Civita symbol: _LEVI[i, j, k] = epsilon_ijk ([a x] b = cross(a, b), cross_i = e_ijk a_j b_k)
_LEVI = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI[_i, _j, _k], _LEVI[_i, _k, _j] = 1.0, -1.0


def measurement_second_order(x: Array, P: Array, R_LI: Array) -> tuple[Array, Array]:
    """The second-order terms of :func:`measurement` (the Gaussian second-order filter, Gelb
    1974 Sec. 6.1; beyond Yu 2019): their mean ``m`` (3,) and covariance ``C`` (3, 3) in L
    under the error covariance ``P`` of ``(dtheta, db)``.

    With ``R_LT = R_hat_LT Exp(-dtheta)`` the origin is ``r - R_hat_LT (b_hat + db - [dtheta
    x] b_hat - [dtheta x] db + 1/2 [dtheta x]^2 b_hat + ...)``: beyond :func:`measurement`'s
    first order, ``R_hat_LT w`` with ``w_i = e^T A_i e`` over ``e = (dtheta, db)``: the
    bilinear ``[dtheta x] db`` (``A_i``'s off-diagonal blocks ``e_ijk / 2``) and ``-1/2
    [dtheta x]^2 b_hat`` (``A_i``'s attitude block ``-(e_i b^T + b e_i^T) / 4 + b_i I / 2``).
    For Gaussian ``e``: ``E w_i = tr(A_i P)``, ``Cov(w_i, w_j) = 2 tr(A_i P A_j P)``.

    Why (issue 18): at the start the attitude is known to 0.1 rad (Yu's P0), the rate to 0.01
    rad/s and the offset to 0.1 m, so the neglected ``[dtheta x] db`` moves the origin by ~1 cm
    in the first scans; with a 1 mm range noise the first-order updates took it as
    information, and the translation and offset locked 0.1 m off at a 1-sigma of 2 mm
    (yu2019 at 1 mm: NEES/dof 230 over 10 runs; over runs 0-2 6.7 at 3 mm, 1.9 at 5 mm). Once the attitude and rate
    are known (a few scans) these terms vanish."""
    R_LT = R_LI @ rot.quat_to_matrix(x[_X_ATT]).T
    b = x[_X_OFFSET]
    ix = np.r_[np.arange(_E_ATT.start, _E_ATT.stop), np.arange(_E_OFFSET.start, _E_OFFSET.stop)]
    Ps = P[np.ix_(ix, ix)]
    A = np.zeros((3, 6, 6))
    A[:, :3, 3:] = 0.5 * _LEVI
    A[:, 3:, :3] = 0.5 * np.swapaxes(_LEVI, -1, -2)
    eye = np.eye(3)
    for i in range(3):
        A[i, :3, :3] = -0.25 * (np.outer(eye[i], b) + np.outer(b, eye[i])) + 0.5 * b[i] * eye
    AP = A @ Ps  # (3, 6, 6)
    m = np.trace(AP, axis1=-2, axis2=-1)
    C = 2.0 * np.einsum("iab,jba->ij", AP, AP)
    return R_LT @ m, R_LT @ C @ R_LT.T
