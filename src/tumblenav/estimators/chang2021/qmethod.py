"""Davenport's q-method (Chang 2021 eq. 27-28) in tumblenav's convention, and its covariance.

Wahba's problem as used here: find the rotation ``R_AB`` that minimises

.. math:: \\sum_i w_i \\lVert a_i - R_{AB} b_i \\rVert^2

for vectors ``b_i`` given in B and ``a_i`` in A (``scipy.spatial.transform.Rotation.
align_vectors(a, b, weights)`` solves the same problem and is the test oracle).

Convention trap (Chang 2021 eq. 27, notes Sec. 0.7): the paper's Davenport matrix is written
for the scalar-last **JPL/Shuster** quaternion, whose attitude matrix ``A(q)`` is the transpose
of the Hamilton matrix of the same four numbers. For tumblenav's Hamilton ``q_AB`` (``R_AB =
quat_to_matrix(q_AB)``) the profile matrix is ``B = sum_i w_i a_i b_i^T`` and

.. math::

    K = \\begin{bmatrix} B + B^T - \\operatorname{tr}(B) I_3 & z \\\\ z^T & \\operatorname{tr}(B)
    \\end{bmatrix}, \\qquad z = [B_{32} - B_{23},\\; B_{13} - B_{31},\\; B_{21} - B_{12}]^T

(eq. 27 with ``z`` of the opposite sign: Shuster's ``z`` belongs to ``B^T``), so that
``q^T K q = tr(R(q)^T B)``; the optimal ``q_AB`` is the eigenvector of the largest eigenvalue
(eq. 28), found with ``numpy.linalg.eigh`` on the symmetric 4x4 ``K``.

Covariance (first order, for the left error ``R_AB = Exp(dtheta) R_hat_AB``, ``dtheta`` in A):
with ``c_i = R_hat b_i`` and residual noise ``n_i = a_i - R b_i`` of covariance ``N_i``, the
normal equations of the weighted least squares give ``dtheta = -H^-1 sum_i w_i [c_i x]^T n_i``
with ``H = sum_i w_i [c_i x]^T [c_i x]``, hence the sandwich

.. math:: P_\\theta = H^{-1} \\Big(\\sum_i w_i^2 [c_i\\times]^T N_i [c_i\\times]\\Big) H^{-1},

which with ``w_i = 1/sigma_i^2`` and isotropic ``N_i = sigma_i^2 I`` is the Fisher bound
``(sum_i (|c_i|^2 I - c_i c_i^T)/sigma_i^2)^-1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tumblenav import rotations as rot

Array = NDArray[np.float64]

__all__ = ["QMethodResult", "davenport_matrix", "q_method", "q_method_covariance"]


def davenport_matrix(a: ArrayLike, b: ArrayLike, w: ArrayLike | None = None) -> Array:
    """Davenport's ``K`` (..., 4, 4) for the Hamilton ``q_AB`` (module docstring; Chang 2021
    eq. 27 with the sign of ``z`` for the Hamilton product).

    Parameters
    ----------
    a, b : (..., N, 3)
        Vectors in A and in B (any length; the weights multiply their products).
    w : (..., N), optional
        Non-negative weights (Chang's ``sigma_i``; default 1).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ww = np.ones(a.shape[:-1]) if w is None else np.asarray(w, dtype=float)
    B = np.einsum("...n,...ni,...nj->...ij", ww, a, b)  # Chang 2021 eq. 27: B = sum w a b^T
    tr = np.trace(B, axis1=-2, axis2=-1)
    z = np.stack(
        [B[..., 2, 1] - B[..., 1, 2], B[..., 0, 2] - B[..., 2, 0], B[..., 1, 0] - B[..., 0, 1]],
        axis=-1,
    )
    K = np.zeros(B.shape[:-2] + (4, 4))
    K[..., :3, :3] = B + np.swapaxes(B, -1, -2) - tr[..., None, None] * np.eye(3)
    K[..., :3, 3] = z
    K[..., 3, :3] = z
    K[..., 3, 3] = tr
    return K


def q_method(a: ArrayLike, b: ArrayLike, w: ArrayLike | None = None) -> tuple[Array, Array]:
    """The optimal ``q_AB`` (..., 4) (scalar part >= 0) and the eigenvalues of ``K`` (..., 4),
    ascending (``lambda_max`` last; ``lambda_max - lambda_3`` small means a nearly
    undetermined rotation, e.g. collinear vectors). Chang 2021 eq. 28."""
    K = davenport_matrix(a, b, w)
    lam, V = np.linalg.eigh(K)
    q = rot.quat_normalize(V[..., :, 3])
    return q, lam


@dataclass(frozen=True)
class QMethodResult:
    """A q-method attitude fix: ``q_AB``, its covariance ``P`` (3x3, rad^2, left error in A),
    the information matrix ``H`` of the fit and the weighted residual sum (``loss``)."""

    q_AB: Array
    P: Array
    H: Array
    loss: float


def q_method_covariance(
    q_AB: ArrayLike, b: ArrayLike, w: ArrayLike, N: ArrayLike
) -> tuple[Array, Array]:
    """First-order covariance (3, 3) of the q-method attitude (sandwich, module docstring) and
    the information ``H``.

    Parameters
    ----------
    q_AB : (4,)
        The estimate.
    b : (M, 3)
        The vectors in B.
    w : (M,)
        The weights used in the fit.
    N : (M, 3, 3)
        Covariance of each residual ``a_i - R_AB b_i`` (in A; m^2 for positions).
    """
    c = np.asarray(b, dtype=float) @ rot.quat_to_matrix(q_AB).T  # c_i = R b_i
    w = np.asarray(w, dtype=float)
    S = rot.skew(c)  # (M, 3, 3) [c_i x]
    St = np.swapaxes(S, -1, -2)
    H = np.einsum("m,mij,mjk->ik", w, St, S)
    M = np.einsum("m,mij,mjk,mkl->il", w**2, St, np.asarray(N, dtype=float), S)
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:  # the vectors do not fix the rotation (all collinear)
        return np.full((3, 3), np.inf), H
    P = Hi @ M @ Hi
    return 0.5 * (P + P.T), H


def epoch_attitude_sigma(p: ArrayLike, P: ArrayLike) -> float:
    """1-sigma (rad) of one epoch's attitude about the axes across the line of sight, from its
    triangulated features ``p`` (M, 3) in the chaser's frame with covariances ``P`` (M, 3, 3):
    a turn ``dtheta`` about such an axis moves a feature along the line of sight by its lever
    arm across the line of sight times ``dtheta``, which stereo measures with its depth noise,
    so ``sigma = sigma_depth / sqrt(sum_i l_i^2 / 2)`` (``l_i``: the lever arm in the plane
    across the line of sight, about the features' centroid; /2: half of it lies along the
    turn's axis; ``sigma_depth``: the features' RMS 1-sigma along the line of sight). The
    lever arms come from the lateral coordinates, which stereo measures well: the q-method's
    own first-order covariance (:func:`q_method_covariance`) takes them from the noisy points,
    and where the depth noise is as large as the target it reads the noise as a larger target
    (3.3 deg at 59 m with 0.5 px and 1.5 deg with 1.5 px). ``inf`` for fewer than three
    points. What one epoch's features say about the attitude: an EKF linearised about its
    estimate needs this to be small (a few degrees)."""
    p = np.asarray(p, dtype=float)
    P = np.asarray(P, dtype=float)
    if len(p) < 3:
        return float("inf")
    c = p.mean(axis=0)
    los = c / np.linalg.norm(c)  # the line of sight to the features
    d = p - c
    lat = d - np.outer(d @ los, los)
    lever2 = float(np.sum(lat**2)) / 2.0
    var_depth = float(np.mean(np.einsum("i,mij,j->m", los, P, los)))
    if not lever2 > 0.0:
        return float("inf")
    return float(np.sqrt(var_depth / lever2))


def start_attitude_sigma_deg(tracks, k0: int, k1: int) -> float:
    """Median over the start window's epochs ``k0 .. k1`` of one epoch's attitude 1-sigma
    (deg, about the axes across the line of sight; :func:`epoch_attitude_sigma`) from
    ``tracks`` (:class:`.measurements.FeatureTracks`: ``p``, ``P``, ``ok_p``)."""
    sig = [
        epoch_attitude_sigma(tracks.p[k, tracks.ok_p[k]], tracks.P[k, tracks.ok_p[k]])
        for k in range(k0, k1 + 1)
    ]
    return float(np.degrees(np.median(sig))) if sig else float("nan")
