"""The truth in each estimator's own state convention and frame: what an estimate is compared
with. Estimators never see the truth; each says in ``history.info["convention"]`` how its state
is defined, and this module expresses the simulated truth the same way (principal-frame
choices, symmetries, inertia parametrisations).

Conventions:

- ``hu2024``: Hu 2024's state in the run's DPACF principal frame T' (defined by the run's own
  photogrammetric frame G: ``info["template_G"]``, ``info["known"]``): :func:`canonical_frame`.
- ``kabir2025``: Kabir 2025's ``[omega_TI_T, q_TI, k1, k2, p_T]`` in the scenario's T.
- ``yu2019``: Yu 2019's state in the symmetric frame of the target model the filter started in
  (``info["symmetries"]``).
- anything else (a plugin): the generic blocks (attitude q_TI, rate omega_TI_T, position r_L,
  velocity v_L, features in T, offset in T) in the scenario's T; other blocks are NaN (not
  evaluated). A plugin with its own convention registers it with :func:`register_alignment`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.estimators.base import EstimateHistory, StateLayout
from tumblenav.frontends.inertia import inertia_ratios, principal_frame

Array = NDArray[np.float64]

_ALIGNMENTS: dict[str, Callable[[Any, EstimateHistory], Array]] = {}


def register_alignment(
    convention: str,
) -> Callable[[Callable[[Any, EstimateHistory], Array]], Callable[[Any, EstimateHistory], Array]]:
    """Decorator: ``fn(truth, history) -> (n, nominal_dim)`` for histories whose
    ``info["convention"]`` is ``convention``."""

    def deco(
        fn: Callable[[Any, EstimateHistory], Array],
    ) -> Callable[[Any, EstimateHistory], Array]:
        _ALIGNMENTS[convention] = fn
        return fn

    return deco


def truth_state(truth: Any, history: EstimateHistory) -> Array:
    """The true nominal state (n, nominal_dim) in the history's convention and frame, so that
    ``history.layout.boxminus(truth_state, history.x)`` is the estimation error."""
    fn = _ALIGNMENTS.get(history.info.get("convention", ""), generic_truth_state)
    return fn(truth, history)


def generic_truth_state(truth: Any, history: EstimateHistory) -> Array:
    """The standard blocks in the scenario's T (see the module docstring); NaN elsewhere."""
    lay = history.layout
    x = np.full((len(truth.t), lay.nominal_dim), np.nan)
    known = {
        "attitude": truth.q_TI,
        "rate": truth.omega_TI_T,
        "position": truth.r_L,
        "velocity": truth.v_L,
        "features": np.tile(np.asarray(truth.features_T, float).ravel(), (len(truth.t), 1)),
        "offset": np.tile(np.asarray(truth.mass_centre_offset_T, float), (len(truth.t), 1)),
    }
    for b in lay.blocks:
        v = known.get(b.name)
        if v is not None and v.shape[-1] == b.nominal_size:
            x[:, lay.nom(b.name)] = v
    return x


# --- Hu 2024 -------------------------------------------------------------------------------


def canonical_frame(template_G: Array, known: NDArray[np.bool_], truth: Any) -> Array:
    """``R_T'T``: the DPACF principal frame T' that this run's G defines, from the truth.

    G is fixed to the target by the template (the features' G coordinates); aligning the
    template with the true feature positions in T gives ``R_GT``; the true inertia in G then
    has the DPACF frame ``R_GT'`` (Hu 2024 eq. 17) and ``R_T'T = R_GT'^T R_GT``. When the
    scenario's T is itself principal (diagonal inertia) the two share principal axes and
    ``R_T'T`` is snapped to the nearest signed permutation (det +1).
    """
    g = template_G[known]
    f = truth.features_T[known]
    H = (f - f.mean(0)).T @ (g - g.mean(0))
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R_GT = Vt.T @ D @ U.T
    I_T = np.asarray(truth.inertia_T, dtype=float)
    R_GTc = principal_frame(R_GT @ I_T @ R_GT.T)
    M = R_GTc.T @ R_GT
    if np.allclose(I_T, np.diag(np.diag(I_T)), rtol=0, atol=1e-12 * np.abs(I_T).max()):
        # T is principal too: the two frames differ by a signed permutation exactly (the
        # template's noise only perturbs M slightly), so snap to it
        snap = np.zeros((3, 3))
        for i in range(3):
            j = int(np.argmax(np.abs(M[i])))
            snap[i, j] = np.sign(M[i, j])
        return snap
    # the scenario's T is not principal (full inertia tensor): keep the rotation itself
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def truth_in_frame(truth: Any, R_TcT: Array, lay: StateLayout) -> Array:
    """The true state (n, nominal_dim) of Hu 2024's layout expressed in the frame
    T' = R_T'T T."""
    n = len(truth.t)
    x = np.zeros((n, lay.nominal_dim))
    qc = rot.matrix_to_quat(R_TcT)
    x[:, lay.nom("attitude")] = rot.quat_multiply(qc, truth.q_TI)
    x[:, lay.nom("rate")] = truth.omega_TI_T @ R_TcT.T
    moments = np.diag(R_TcT @ truth.inertia_T @ R_TcT.T)
    x[:, lay.nom("inertia")] = inertia_ratios(moments)
    x[:, lay.nom("position")] = truth.r_L
    x[:, lay.nom("velocity")] = truth.v_L
    x[:, lay.nom("features")] = (truth.features_T @ R_TcT.T).ravel()
    return x


@register_alignment("hu2024")
def hu_truth_state(truth: Any, history: EstimateHistory) -> Array:
    R = canonical_frame(history.info["template_G"], history.info["known"], truth)
    return truth_in_frame(truth, R, history.layout)


# --- Kabir 2025 ----------------------------------------------------------------------------


def kabir_truth_state_of(truth: Any) -> Array:
    """The truth (n, 9 + 3N) in Kabir 2025's state: ``[omega_TI_T, q_TI, k1, k2, p]`` with
    ``k1 = log(I1/I2)``, ``k2 = log(I3/I2)`` (eq. 7)."""
    I = np.diag(np.asarray(truth.inertia_T, dtype=float))
    n = len(truth.t)
    k = np.array([np.log(I[0] / I[1]), np.log(I[2] / I[1])])
    f = np.asarray(truth.features_T, dtype=float).ravel()
    return np.concatenate(
        [truth.omega_TI_T, truth.q_TI, np.tile(k, (n, 1)), np.tile(f, (n, 1))], axis=1
    )


@register_alignment("kabir2025")
def kabir_truth_state(truth: Any, history: EstimateHistory) -> Array:
    return kabir_truth_state_of(truth)


# --- Yu 2019 -------------------------------------------------------------------------------


@register_alignment("yu2019")
def yu_truth_state(truth: Any, history: EstimateHistory) -> Array:
    """The truth in the estimator's frame. Rectangles alone fix the attitude only up to the
    model's own symmetries (for the procedural satellite: half turns about its axes), so
    the truth is expressed in the symmetric frame the filter started in (chosen once per
    run, at the first estimate); later jumps between symmetric frames count as errors."""
    lay = history.layout
    G = np.eye(3)
    syms = history.info.get("symmetries") or [np.eye(3)]
    sq = lay.nom("attitude")
    first = np.flatnonzero(np.all(np.isfinite(history.x), axis=1))
    if len(first):
        k = first[0]
        R_est = rot.quat_to_matrix(history.x[k, sq])
        R_true = rot.quat_to_matrix(truth.q_TI[k])
        G = max(syms, key=lambda S: np.sum(R_est * (S @ R_true)))
    x = np.zeros((len(truth.t), lay.nominal_dim))
    I = G @ truth.inertia_T @ G.T
    I = I / I[0, 0]
    x[:, sq] = rot.quat_multiply(rot.matrix_to_quat(G), truth.q_TI)
    x[:, lay.nom("rate")] = truth.omega_TI_T @ G.T
    x[:, lay.nom("inertia")] = [I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
    x[:, lay.nom("position")] = truth.r_L
    x[:, lay.nom("velocity")] = truth.v_L
    x[:, lay.nom("offset")] = truth.mass_centre_offset_T @ G.T
    return x


# --- Chang 2021 ----------------------------------------------------------------------------


@register_alignment("chang2021")
def chang_truth_state(truth: Any, history: EstimateHistory) -> Array:
    """The truth in ekf-pose's frame That, defined at epoch ``k0 = info["frame_epoch"]`` by
    ``R_ThatL(k0) = info["R_ThatL_k0"]`` (the identity): ``R_ThatT = R_ThatL(k0) R_LT(k0)``
    (constant, body-fixed), attitude ``q_ThatL(t) = R_ThatT R_TL(t)``, rate relative to L
    ``omega_ThatL_That = R_ThatT (omega_TI_T - R_TL omega_LI_L)``, the mass centre's ``r_L``,
    ``v_L``, and (``map: registered``, whose layout has the block) the offset ``b = R_ThatL(k0)
    (r_L(k0) - info["map_origin_L_k0"])`` (the mass centre about the estimator's feature map
    origin). NaN before the estimator has a frame."""
    from tumblenav.frames import lvlh_rate

    lay = history.layout
    n = len(truth.t)
    x = np.full((n, lay.nominal_dim), np.nan)
    k0 = history.info.get("frame_epoch")
    if k0 is None:
        return x
    R_ThatL0 = np.asarray(history.info["R_ThatL_k0"], dtype=float)
    R_LT = truth.R_LT
    R_ThatT = R_ThatL0 @ R_LT[k0]
    R_TL = np.swapaxes(R_LT, -1, -2)
    if np.any(np.linalg.norm(truth.chaser_r_I, axis=-1) > 0):
        w_LI_L = lvlh_rate(truth.chaser_r_I, truth.chaser_v_I)
    else:  # no orbit: L = I
        w_LI_L = np.zeros((n, 3))
    w_TL_T = truth.omega_TI_T - np.einsum("tij,tj->ti", R_TL, w_LI_L)
    x[:, lay.nom("attitude")] = rot.matrix_to_quat(R_ThatT @ R_TL)
    x[:, lay.nom("rate")] = w_TL_T @ R_ThatT.T
    x[:, lay.nom("position")] = truth.r_L
    x[:, lay.nom("velocity")] = truth.v_L
    if "offset" in lay.names():  # map 'registered' only (map 'state' has no map origin)
        origin = np.asarray(history.info["map_origin_L_k0"], dtype=float)
        x[:, lay.nom("offset")] = R_ThatL0 @ (truth.r_L[k0] - origin)
    return x
