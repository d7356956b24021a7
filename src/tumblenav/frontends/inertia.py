"""Inertia identification in G and the principal frame T (Hu 2024 Sec. 3, eq. 8-14 and 17).

Model (Hu 2024 eq. 8-11, corrected)
-----------------------------------
For a torque-free rigid target the angular momentum ``h_I`` is constant in the inertial frame.
Expressed in the photogrammetric frame G (:mod:`tumblenav.frontends.photogrammetric`)::

    I_G omega_G(t) = R_GI(t) h_I

Only the ratios of the inertia can be observed (the equation is homogeneous in
``(I_G, h_I)``); dividing by ``I_xx`` gives ``I_bar = I_G / I_xx`` (eq. 9, ``I_bar_xx = 1``)
and ``H = h_I / I_xx`` (rad/s)::

    I_bar omega_G(t) = R_GI(t) H                                           (eq. 10)

The extracted eq. 10 reads ``T_bar I_bar omega = R H``; the stray ``T_bar`` is an artefact and
``H`` there is the *normalised* momentum.  The unknowns are ``X = [l; H]`` (8,), with
``l = [I_yy, I_zz, I_xy, I_xz, I_yz] / I_xx``; the extracted text lists ``I_zy`` as the third
entry, which must be ``I_xy`` (``I_zy = I_yz`` is already the fifth).  Moving the known
``I_bar_xx = 1`` term to the right-hand side, row by row (``w = omega_G``, ``R = R_GI``)::

    x:  I_xy w_y + I_xz w_z                       - (R H)_x = -w_x
    y:  I_yy w_y + I_xy w_x + I_yz w_z            - (R H)_y =  0
    z:  I_zz w_z + I_xz w_x + I_yz w_y            - (R H)_z =  0

i.e. ``a(t) X = b(t)`` (eq. 11) with ::

    a(t) = [[ 0,   0,   w_y, w_z, 0  ] | -R(t) ]      b(t) = [-w_x, 0, 0]^T    (eq. 12)
           [[ w_y, 0,   w_x, 0,   w_z] |       ]
           [[ 0,   w_z, 0,   w_x, w_y] |       ]

The extracted eq. 12 puts ``-R`` on the middle row only; it is the full 3 x 3 block on the
right of all three rows.  Stacking epochs gives eq. 13-14, ``X = (A^T A)^{-1} A^T B``.

Principal frame (Hu 2024 eq. 17, DPACF)
---------------------------------------
``R_TG I_bar R_GT = diag(lambda_1, lambda_2, lambda_3)`` with ``R_GT = [r1 r2 r3]`` (the extracted
eq. 17 mangles the sub/superscripts).  The eigenvalues are ordered
``lambda_1 > lambda_2 > lambda_3`` (``x_T`` = axis of the largest moment, ``z_T`` of the smallest)
and the signs are fixed by two rules, see :func:`principal_frame`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special, stats

Array = NDArray[np.float64]

__all__ = [
    "InertiaAccumulator",
    "InertiaEstimate",
    "InertiaIdentification",
    "accumulate",
    "identify_inertia",
    "inertia_design",
    "inertia_ratios",
    "principal_frame",
    "principal_moments",
    "solve",
]

N_UNKNOWNS = 8
SIGN_TOL = 1e-9
"""|component| below which a deciding eigenvector component counts as zero (see principal_frame)."""

# Condition numbers (of the column-equilibrated design matrix) beyond this leave the
# normal equations numerically singular in double precision: the estimate is NaN.
_MAX_COND = 1.0 / np.sqrt(np.finfo(float).eps)


def _readonly(a: Array) -> Array:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def inertia_design(omega_G: ArrayLike, R_GI: ArrayLike) -> tuple[Array, Array]:
    """Rows ``a(t)`` (3 x 8) and ``b(t)`` (3,) of Hu 2024 eq. 11-12 at each epoch.

    Parameters
    ----------
    omega_G : array_like, shape (..., 3)
        Angular rate of G relative to I, expressed in G (rad/s).
    R_GI : array_like, shape (..., 3, 3)
        Attitude of G relative to I (maps inertial into G).

    Returns
    -------
    a : numpy.ndarray, shape (..., 3, 8)
        Columns ``[I_yy, I_zz, I_xy, I_xz, I_yz | H_x, H_y, H_z]`` (normalised by ``I_xx``).
    b : numpy.ndarray, shape (..., 3)
        ``[-w_x, 0, 0]`` (rad/s).
    """
    w = np.asarray(omega_G, dtype=float)
    R = np.asarray(R_GI, dtype=float)
    lead = np.broadcast_shapes(w.shape[:-1], R.shape[:-2])
    w = np.broadcast_to(w, lead + (3,))
    R = np.broadcast_to(R, lead + (3, 3))
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    z = np.zeros(lead)
    # Hu 2024 eq. 12, with the -R_GI block spanning all three rows.
    a_l = np.stack(
        [
            np.stack([z, z, wy, wz, z], -1),
            np.stack([wy, z, wx, z, wz], -1),
            np.stack([z, wz, z, wx, wy], -1),
        ],
        -2,
    )
    a = np.concatenate([a_l, -R], axis=-1)
    b = np.stack([-wx, z, z], -1)
    return a, b


@dataclass(frozen=True)
class InertiaEstimate:
    """Identified normalised inertia and angular momentum (Hu 2024 eq. 13).

    Attributes
    ----------
    I_bar_G : numpy.ndarray, shape (3, 3)
        Inertia in G divided by ``I_xx`` (eq. 9; dimensionless, ``I_bar_G[0, 0] == 1``).
    H_I : numpy.ndarray, shape (3,)
        Angular momentum in the inertial frame divided by ``I_xx`` (rad/s).
    residual_rms : float
        RMS of the equation residuals ``a X - b`` over all rows (rad/s).  At the level of the
        rate noise for a rigid, torque-free target; much larger flags torques or bad rates.
    condition_number : float
        2-norm condition number of the column-equilibrated design matrix ``A``.  ``inf`` (and
        NaN estimates) while the problem is not identifiable, e.g. with fewer than 3 epochs or
        while the rate direction has not moved in G (pure spin about a principal axis).
        Values above ~1e4 mean the estimate is dominated by noise.
    n_epochs : float
        Number of epochs (effective number under a forgetting factor).
    """

    I_bar_G: Array
    H_I: Array
    residual_rms: float
    condition_number: float
    n_epochs: float

    @property
    def l(self) -> Array:  # noqa: E743 - the paper's name
        """Inertia ratio vector ``[I_yy, I_zz, I_xy, I_xz, I_yz] / I_xx`` of Hu 2024."""
        I = self.I_bar_G
        return np.array([I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])

    @property
    def is_physical(self) -> bool:
        """True if ``I_bar_G`` is positive definite and its moments obey the triangle rule."""
        if not np.all(np.isfinite(self.I_bar_G)):
            return False
        lam = np.linalg.eigvalsh(self.I_bar_G)
        return bool(lam[0] > 0.0 and lam[2] <= lam[0] + lam[1] + 1e-9 * lam[2])


def _unpack(X: Array) -> tuple[Array, Array]:
    l_ = X[:5]
    I_bar = np.array(
        [[1.0, l_[2], l_[3]], [l_[2], l_[0], l_[4]], [l_[3], l_[4], l_[1]]], dtype=float
    )
    return I_bar, X[5:].copy()


def _nan_estimate(n_epochs: float, residual: float = np.nan) -> InertiaEstimate:
    return InertiaEstimate(
        I_bar_G=_readonly(np.full((3, 3), np.nan)),
        H_I=_readonly(np.full(3, np.nan)),
        residual_rms=float(residual),
        condition_number=float(np.inf),
        n_epochs=float(n_epochs),
    )


def identify_inertia(
    omega_G: ArrayLike, R_GI: ArrayLike, weights: ArrayLike | None = None
) -> InertiaEstimate:
    """Batch least squares of Hu 2024 eq. 13-14 over all epochs.

    Solves ``min_X sum_k w_k |a(t_k) X - b(t_k)|^2`` with an SVD-based solver on the
    column-equilibrated stacked matrix (more accurate than forming ``A^T A``).

    Parameters
    ----------
    omega_G : array_like, shape (n, 3)
        Rate of G relative to I in G (rad/s), e.g. from
        :func:`tumblenav.frontends.photogrammetric.rate_from_attitudes`.
    R_GI : array_like, shape (n, 3, 3)
        Attitude of G relative to I at the same epochs.
    weights : array_like, shape (n,), optional
        Non-negative per-epoch weights (e.g. inverse rate variance).  Default: equal.

    Returns
    -------
    InertiaEstimate
        NaN estimate with ``condition_number = inf`` when not identifiable.
    """
    a, b = inertia_design(omega_G, R_GI)
    a = a.reshape(-1, 3, N_UNKNOWNS)
    b = b.reshape(-1, 3)
    n = a.shape[0]
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).reshape(n)
    use = (w > 0.0) & np.all(np.isfinite(a), axis=(1, 2)) & np.all(np.isfinite(b), axis=1)
    a, b, w = a[use], b[use], w[use]
    if 3 * len(a) < N_UNKNOWNS:
        return _nan_estimate(len(a))
    sw = np.sqrt(w)[:, None]
    A = (a * sw[..., None]).reshape(-1, N_UNKNOWNS)
    B = (b * sw).reshape(-1)
    col = np.linalg.norm(A, axis=0)
    if not np.all(col > 0.0):
        return _nan_estimate(len(a))
    As = A / col
    sv = np.linalg.svd(As, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0.0 else float(np.inf)
    if not cond < _MAX_COND:
        return _nan_estimate(len(a))
    Xs, *_ = np.linalg.lstsq(As, B, rcond=None)
    X = Xs / col
    r = A @ X - B
    rms = float(np.sqrt(np.sum(r**2) / (3.0 * np.sum(w))))
    I_bar, H = _unpack(X)
    return InertiaEstimate(_readonly(I_bar), _readonly(H), rms, cond, float(len(a)))


@dataclass(frozen=True)
class InertiaAccumulator:
    """Normal equations of Hu 2024 eq. 13 accumulated epoch by epoch (immutable).

    ``N = sum_k w_k a_k^T a_k`` (8 x 8), ``r = sum_k w_k a_k^T b_k`` (8,),
    ``bb = sum_k w_k b_k^T b_k`` and ``weight = sum_k w_k``.  Memory and cost per frame are
    constant, so it can run online; :func:`solve` gives the estimate at any time.  Start from
    ``InertiaAccumulator()`` (or pass ``None`` to :func:`accumulate`).
    """

    N: Array = field(default_factory=lambda: _readonly(np.zeros((N_UNKNOWNS, N_UNKNOWNS))))
    r: Array = field(default_factory=lambda: _readonly(np.zeros(N_UNKNOWNS)))
    bb: float = 0.0
    weight: float = 0.0
    n_epochs: float = 0.0


def accumulate(
    state: InertiaAccumulator | None,
    omega_G: ArrayLike,
    R_GI: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    forgetting: float = 1.0,
) -> InertiaAccumulator:
    """Add one epoch (or a batch of epochs) to the normal equations; returns a new state.

    Parameters
    ----------
    state : InertiaAccumulator or None
        Previous state (``None``: start empty).
    omega_G : array_like, shape (3,) or (n, 3)
        Rate of G relative to I in G (rad/s).
    R_GI : array_like, shape (3, 3) or (n, 3, 3)
        Attitude of G relative to I.
    weights : float or array_like, shape (n,), optional
        Per-epoch weights (default 1).
    forgetting : float, in (0, 1]
        The previous state is multiplied by ``forgetting`` before the new epochs are added
        (exponential forgetting for a slowly changing momentum, e.g. after a torque).
        ``1`` (default) reproduces the batch solution exactly.

    Returns
    -------
    InertiaAccumulator
    """
    if not 0.0 < forgetting <= 1.0:
        raise ValueError(f"forgetting must be in (0, 1], got {forgetting}")
    state = InertiaAccumulator() if state is None else state
    a, b = inertia_design(omega_G, R_GI)
    a = a.reshape(-1, 3, N_UNKNOWNS)
    b = b.reshape(-1, 3)
    n = a.shape[0]
    w = np.ones(n) if weights is None else np.broadcast_to(np.asarray(weights, float), (n,))
    ok = (w > 0.0) & np.all(np.isfinite(a), axis=(1, 2)) & np.all(np.isfinite(b), axis=1)
    a, b, w = a[ok], b[ok], w[ok]
    N = forgetting * state.N + np.einsum("k,kri,krj->ij", w, a, a)
    r = forgetting * state.r + np.einsum("k,kri,kr->i", w, a, b)
    bb = forgetting * state.bb + float(np.einsum("k,kr,kr->", w, b, b))
    return InertiaAccumulator(
        N=_readonly(N),
        r=_readonly(r),
        bb=bb,
        weight=forgetting * state.weight + float(w.sum()),
        n_epochs=forgetting * state.n_epochs + float(len(a)),
    )


def solve(state: InertiaAccumulator) -> InertiaEstimate:
    """Estimate from accumulated normal equations (Hu 2024 eq. 13).

    ``X = N^{-1} r`` solved on the Jacobi-equilibrated system ``S N S`` with
    ``S = diag(N)^{-1/2}``; the reported condition number is that of the equilibrated design
    matrix, ``sqrt(cond(S N S))``, comparable with :func:`identify_inertia`.  The residual is
    ``sqrt((bb - 2 X.r + X.N X) / (3 weight))`` (clipped at 0; it loses about half the digits
    to cancellation, so it floors near 1e-8 |omega| with exact data).
    """
    if 3 * state.n_epochs < N_UNKNOWNS or state.weight <= 0.0:
        return _nan_estimate(state.n_epochs)
    d = np.diag(state.N)
    if not np.all(d > 0.0):
        return _nan_estimate(state.n_epochs)
    s = 1.0 / np.sqrt(d)
    Ns = state.N * s[:, None] * s[None, :]
    lam = np.linalg.eigvalsh(Ns)
    cond = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0.0 else float(np.inf)
    if not cond < _MAX_COND:
        return _nan_estimate(state.n_epochs)
    X = s * np.linalg.solve(Ns, s * state.r)
    sse = state.bb - 2.0 * X @ state.r + X @ state.N @ X
    rms = float(np.sqrt(max(float(sse), 0.0) / (3.0 * state.weight)))
    I_bar, H = _unpack(X)
    return InertiaEstimate(_readonly(I_bar), _readonly(H), rms, cond, float(state.n_epochs))


class InertiaIdentification:
    """Online wrapper: ``ident.update(omega_G, R_GI)`` each frame, ``ident.estimate()`` anytime.

    Holds an :class:`InertiaAccumulator`; equivalent to folding :func:`accumulate` over the
    frames and calling :func:`solve`.  ``InertiaIdentification.batch`` is
    :func:`identify_inertia`.
    """

    batch = staticmethod(identify_inertia)

    def __init__(self, forgetting: float = 1.0) -> None:
        self.forgetting = forgetting
        self.state = InertiaAccumulator()

    def update(
        self, omega_G: ArrayLike, R_GI: ArrayLike, weights: ArrayLike | None = None
    ) -> InertiaAccumulator:
        """Add epoch(s); returns the new accumulator state."""
        self.state = accumulate(self.state, omega_G, R_GI, weights, forgetting=self.forgetting)
        return self.state

    def estimate(self) -> InertiaEstimate:
        """Current least-squares estimate (:func:`solve`)."""
        return solve(self.state)


def principal_moments(inertia_G: ArrayLike, normalize: bool = True) -> Array:
    """Principal moments sorted ``lambda_1 >= lambda_2 >= lambda_3`` (Hu 2024 eq. 17).

    Parameters
    ----------
    inertia_G : array_like, shape (..., 3, 3)
        Symmetric inertia (any scale, e.g. ``I_bar_G``).
    normalize : bool
        Divide by ``lambda_1`` (default), so ``lambda_1 = 1``.  Any normalisation leaves Hu's
        inertia ratios (eq. 19, :func:`inertia_ratios`) unchanged.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        Moments along ``x_T, y_T, z_T`` of :func:`principal_frame`.
    """
    I = np.asarray(inertia_G, dtype=float)
    lam = np.linalg.eigvalsh(0.5 * (I + np.swapaxes(I, -1, -2)))[..., ::-1]
    return lam / lam[..., :1] if normalize else lam


def inertia_ratios(moments: ArrayLike) -> Array:
    """Hu 2024 eq. 19: ``p = [(I_y - I_z)/I_x, (I_z - I_x)/I_y, (I_x - I_y)/I_z]``.

    ``moments`` (..., 3) are ``(I_x, I_y, I_z)`` of the principal frame (scale-free).
    """
    m = np.asarray(moments, dtype=float)
    Ix, Iy, Iz = m[..., 0], m[..., 1], m[..., 2]
    return np.stack([(Iy - Iz) / Ix, (Iz - Ix) / Iy, (Ix - Iy) / Iz], axis=-1)


def _sign_first_significant(v: Array, tol: float) -> Array:
    """+1/-1 making the first component of v (x, y, z order) with |.| > tol positive."""
    big = np.abs(v) > tol
    first = np.argmax(big, axis=-1)  # 0 if none is big (then v[0] decides, whatever it is)
    comp = np.take_along_axis(v, first[..., None], axis=-1)[..., 0]
    return np.where(comp < 0.0, -1.0, 1.0)


def principal_frame(inertia_G: ArrayLike) -> Array:
    """Unique principal frame T of an inertia matrix given in G: ``R_GT`` (Hu 2024 eq. 17).

    ``R_GT = [r1 r2 r3]`` (columns are T's axes expressed in G) diagonalises the inertia,
    ``R_GT^T I_G R_GT = diag(lambda_1, lambda_2, lambda_3)``, with the DPACF rules:

    1. Order ``lambda_1 > lambda_2 > lambda_3``: ``x_T`` is the axis of the largest moment,
       ``z_T`` of the smallest (Hu 2024).
    2. Sign of ``r1``: ``r1 . x_G > 0`` (``x_T`` acute with ``x_G``; Hu 2024).  Degenerate
       case: if ``|r1_x| <= SIGN_TOL`` (1e-9) the paper's rule is undefined; the first
       component of ``r1`` (in the order y, z) with magnitude above ``SIGN_TOL`` is made
       positive instead.
    3. Sign of ``r2`` (our second rule; the paper's two rules leave a 180-degree ambiguity
       about ``x_T``): the component of ``r2`` with the *largest magnitude* is made positive
       (exact magnitude ties go to the first G axis, x before y before z).  Unlike a rule on
       a fixed component (e.g. ``r2 . y_G > 0``), the deciding component is never close to
       zero: it is at least ``1/sqrt(3)`` in magnitude, so noise cannot flip its sign.  The
       rule switches only where two components of opposite sign have (nearly) equal
       magnitude; a fixed-component rule would instead switch whenever ``r2`` crosses a
       coordinate plane, which happens e.g. whenever ``r1`` is near ``x_G`` (then ``r2_x ~ 0``).
    4. ``r3 = r1 x r2``, so ``R_GT`` is a proper rotation (det = +1).

    The result is invariant to a positive scaling of the inertia.  When two moments are
    (nearly) equal (axisymmetric target) the corresponding axes are not defined by the
    inertia and the result within that plane is arbitrary (but still a proper rotation).

    Parameters
    ----------
    inertia_G : array_like, shape (..., 3, 3)
        Symmetric inertia expressed in G (any positive scale, e.g. ``I_bar_G``); it is
        symmetrised before the eigen-decomposition.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        ``R_GT``.

    Raises
    ------
    ValueError
        If the inertia contains NaN or inf.
    """
    I = np.asarray(inertia_G, dtype=float)
    if not np.all(np.isfinite(I)):
        raise ValueError("inertia contains NaN or inf: principal frame undefined")
    I = 0.5 * (I + np.swapaxes(I, -1, -2))
    _, vec = np.linalg.eigh(I)  # ascending eigenvalues
    r1 = vec[..., :, 2]
    r2 = vec[..., :, 1]
    r1 = r1 * _sign_first_significant(r1, SIGN_TOL)[..., None]
    k = np.argmax(np.abs(r2), axis=-1)
    s2 = np.take_along_axis(r2, k[..., None], axis=-1)
    r2 = np.where(s2 < 0.0, -r2, r2)
    r3 = np.cross(r1, r2)
    return np.stack([r1, r2, r3], axis=-1)


def _bivariate_normal_cdf(h: Array, k: Array, rho: Array) -> Array:
    """``P(Y1 < h, Y2 < k)`` for standard normals with correlation ``rho``, for ``h, k <= 0``,
    vectorised through Owen's T function (Owen 1956, eq. 2.1; scipy has no vectorised
    bivariate normal CDF)."""
    h = np.minimum(h, -1e-12)
    k = np.minimum(k, -1e-12)
    rho = np.clip(rho, -1 + 1e-12, 1 - 1e-12)
    s = np.sqrt(1.0 - rho * rho)
    out = (
        0.5 * stats.norm.cdf(h)
        + 0.5 * stats.norm.cdf(k)
        - special.owens_t(h, (k - rho * h) / (h * s))
        - special.owens_t(k, (h - rho * k) / (k * s))
    )
    return np.clip(out, 0.0, np.minimum(stats.norm.cdf(h), stats.norm.cdf(k)))


def branch_statistics(R_GT: ArrayLike, cov_frame: ArrayLike) -> tuple[Array, Array, Array]:
    """Probability that the *true* inertia's DPACF frame is the half turn of ``R_GT`` about
    T's x, y or z axis: (..., 3) (beyond the paper).

    :func:`principal_frame` is unique for a given inertia, but its sign rules are
    discontinuous: when the identified axes lie within their error of a rule's boundary, the
    true inertia may select the frame turned by 180 degrees. With the frame error ``u`` (in
    T, covariance ``C = cov_frame``; the true axes are ``r_i + r_i x (R_GT u)`` to first
    order), each rule's margin moves by a linear function ``a^T u`` of ``u``:

    * rule 2 (``r1 . x_G > 0``): margin ``|r1_x|``, ``a = R_TG (x_G x r1)`` (times the
      sign of ``r1_x``); a flip turns r1 and r3: the half turn about y_T;
    * rule 3 (largest component of ``r2`` positive, index k): for each component j of the
      opposite sign, margin ``|r2_k| - |r2_j|``, ``a = s_k R_TG ((e_k + e_j) x r2)``; r2
      flips if any of these margins crosses zero (about x_T);
    * both rules: about z_T, from the joint Gaussian of the two margins (rule 3 through its
      most likely j).

    Returns ``p = [p(only rule 3), p(only rule 2), p(both)]`` (about x_T, y_T, z_T), and for
    each turn the mean (..., 3, 3) and covariance (..., 3, 3, 3) of ``u`` given it (a normal
    truncated beyond the rule's margin; for both rules the sum of the two shifts, an
    approximation); zeros where the frame or its covariance is not finite. Tested against
    sampling (tests/test_frontends.py).
    """
    R = np.asarray(R_GT, dtype=float)
    C = np.asarray(cov_frame, dtype=float)
    ok = np.all(np.isfinite(R), axis=(-1, -2)) & np.all(np.isfinite(C), axis=(-1, -2))
    R = np.where(ok[..., None, None], R, np.eye(3))
    C = np.where(ok[..., None, None], C, 0.0)
    R_TG = np.swapaxes(R, -1, -2)
    r1, r2 = R[..., :, 0], R[..., :, 1]

    def gradient(axis_G: Array) -> tuple[Array, Array]:  # a = R_TG axis_G, and its sigma
        a = (R_TG @ axis_G[..., None])[..., 0]
        return a, np.sqrt(np.maximum(np.einsum("...i,...ij,...j->...", a, C, a), 0.0))

    def standardised(margin: Array, sd: Array) -> Array:  # -margin / sd, -inf if sd = 0
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(sd > 0, -np.abs(margin) / np.where(sd > 0, sd, 1.0), -np.inf)

    ex = np.broadcast_to(np.array([1.0, 0.0, 0.0]), r1.shape)
    a1, sd1 = gradient(np.cross(ex, r1))
    a1 = a1 * np.where(r1[..., 0] < 0, -1.0, 1.0)[..., None]
    h = standardised(r1[..., 0], sd1)
    p1 = stats.norm.cdf(h)
    k = np.argmax(np.abs(r2), axis=-1)
    rk = np.take_along_axis(r2, k[..., None], axis=-1)[..., 0]
    sk = np.where(rk < 0, -1.0, 1.0)
    keep = np.ones_like(p1)
    best_p = np.zeros_like(p1)
    best_a = np.zeros_like(a1)
    best_z = np.full_like(p1, -np.inf)
    eye = np.eye(3)
    for j in range(3):
        opposite = (k != j) & (r2[..., j] * rk < 0)
        aj, sdj = gradient(np.cross(eye[k] + eye[j], r2))
        zj = standardised(np.abs(rk) - np.abs(r2[..., j]), sdj)
        pj = np.where(opposite, stats.norm.cdf(zj), 0.0)
        keep = keep * (1.0 - pj)
        better = pj > best_p
        best_p = np.where(better, pj, best_p)
        best_z = np.where(better, zj, best_z)
        with np.errstate(divide="ignore", invalid="ignore"):
            unit = sk[..., None] * aj / np.where(sdj > 0, sdj, 1.0)[..., None]
        best_a = np.where(better[..., None], unit, best_a)
    p2 = 1.0 - keep
    both = np.zeros_like(p1)
    joint = (p1 > 1e-9) & (best_p > 1e-9)
    if joint.any():
        with np.errstate(divide="ignore", invalid="ignore"):
            u1 = a1[joint] / sd1[joint][:, None]
        rho = np.einsum("...i,...ij,...j->...", u1, C[joint], best_a[joint])
        both[joint] = _bivariate_normal_cdf(h[joint], best_z[joint], rho)
    both = np.minimum(both, np.minimum(p1, p2))
    out = np.stack([p2 - both, p1 - both, both], axis=-1)
    p = np.where(ok[..., None], np.clip(out, 0.0, 1.0), 0.0)
    # Conditioned on a rule's flip, u is a normal truncated beyond the margin: with the unit
    # gradient g (z = g^T u ~ N(0, 1), flip iff z < h), E[u | flip] = -C g lambda and
    # Cov[u | flip] = C - C g g^T C (h lambda + lambda^2), lambda = phi(h) / Phi(h).
    with np.errstate(divide="ignore", invalid="ignore"):
        g1 = np.where((sd1 > 0)[..., None], a1 / np.where(sd1 > 0, sd1, 1.0)[..., None], 0.0)

    def truncated(g: Array, hh: Array) -> tuple[Array, Array]:
        hh = np.maximum(hh, -1e6)
        lam = np.exp(stats.norm.logpdf(hh) - special.log_ndtr(hh))
        Cg = (C @ g[..., None])[..., 0]
        mean = -Cg * lam[..., None]
        shrink = (hh * lam + lam * lam)[..., None, None] * (Cg[..., :, None] * Cg[..., None, :])
        return mean, shrink

    m1, s1 = truncated(g1, h)
    m2, s2 = truncated(best_a, best_z)
    mu = np.stack([m2, m1, m1 + m2], axis=-2)  # (..., 3 turns, 3)
    S = np.stack([C - s2, C - s1, C - s1 - s2], axis=-3)  # (..., 3 turns, 3, 3)
    mu = np.where(ok[..., None, None], np.nan_to_num(mu), 0.0)
    S = np.where(ok[..., None, None, None], np.nan_to_num(S), 0.0)
    return p, mu, S


def branch_probabilities(R_GT: ArrayLike, cov_frame: ArrayLike) -> Array:
    """The probabilities of :func:`branch_statistics` alone, (..., 3)."""
    return branch_statistics(R_GT, cov_frame)[0]
