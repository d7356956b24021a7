"""The truth in each estimator's own state convention and frame: what an estimate is compared
with. Estimators never see the truth; each says in ``history.info["convention"]`` how its state
is defined, and this module expresses the simulated truth the same way (principal-frame
choices, symmetries, inertia parametrisations).

Conventions:

- ``hu2024``: Hu 2024's state in the run's DPACF principal frame T' (defined by the run's own
  photogrammetric frame G: ``info["template_G"]``, ``info["known"]``): :func:`canonical_frame`.
- ``kabir2025``: Kabir 2025's ``[omega_TI_T, q_TI, k1, k2, p_T]`` in the scenario's T.
- ``yu2019``: Yu 2019's state in the scenario's T (the model symmetries: below).
- ``chang2021``: ekf-pose's frame That, fixed at its first estimate (no symmetry).
- anything else (a plugin): the generic blocks (attitude q_TI, rate omega_TI_T, position r_L,
  velocity v_L, features in T, offset in T) in the scenario's T; other blocks are NaN (not
  evaluated). A plugin with its own convention registers it with :func:`register_alignment`
  (or :func:`register_frame_alignment` to take part in the symmetries).

Symmetries, handled here once for every estimator (:func:`align`). An estimate may be the
truth seen in a *symmetric frame* ``T_G = G T`` of the convention's own frame (``G`` a proper
rotation): physically the same motion, e.g. a principal frame with two axes relabelled, or the
target model's own symmetry. The estimator says which frames are legitimate in
``history.info``:

- ``info["symmetries"]``: an explicit list of 3x3 rotations (Yu 2019: the model's rectangle
  symmetries, :func:`tumblenav.frontends.depth_pose.model_symmetries`);
- ``info["symmetry"]``: a named group, ``"principal_axes"`` (the 24 proper signed permutations
  of the principal axes: a principal frame whose axes are relabelled, with the inertia
  parameters relabelled with them) or ``"half_turns"`` (identity and the half turns about the
  three axes: the sign choices of a principal frame);
- nothing: the convention's frame only.

The frame is chosen once per run, so that a later jump between symmetric frames counts as an
error (``info["symmetry_reference"]``):

- ``"first"`` (the default for an explicit list): the frame nearest the estimate at its first
  epoch, i.e. the frame the filter started in (Yu 2019's rectangle fix at start);
- ``"run"`` (the default for a named group): the frame the estimate lies nearest to, within
  :data:`BRANCH_MAX_DEG`, at the most epochs, if that is at least :data:`BRANCH_MIN_FRACTION`
  of its epochs and more than the convention's own frame; else the convention's own frame. A
  filter that starts from an arbitrary frame and converges to a principal one (Kabir 2025's
  triangulated start: ``q_TI = identity``) is on no branch at its first epoch.

The truth is then expressed in ``T_G`` (attitude ``q(G) (x) q``, rate ``G omega``, features and
offset ``G f``, inertia ``G I G^T`` in the convention's parameters), and the run records its
*branch*: ``"nominal"`` for the convention's own frame, else a short name
(:func:`branch_name`, e.g. ``"x<->y (y,x,-z)"``, ``"half turn z"``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.estimators.base import EstimateHistory, StateLayout
from tumblenav.evaluation.metrics import NOMINAL
from tumblenav.frontends.inertia import inertia_ratios, principal_frame

Array = NDArray[np.float64]

# a convention's truth in the symmetric frame G of its own frame (None: its own frame)
FrameFn = Callable[[Any, EstimateHistory, "Array | None"], Array]

_ALIGNMENTS: dict[str, FrameFn] = {}
_SYMMETRIC: set[str] = set()  # conventions whose function takes a symmetric frame G

BRANCH_MAX_DEG = 45.0  # tumblenav default: an estimate within 45 deg of a symmetric frame is
# on it (proper signed permutations are >= 90 deg apart, so at most one is that near)
BRANCH_MIN_FRACTION = 0.25  # tumblenav default: a run is on a branch when its estimate lies
# near that frame at >= 25% of its epochs (a random attitude is within 45 deg of a given frame
# at 2.5% of epochs: (theta - sin theta) / pi)


def register_alignment(
    convention: str,
) -> Callable[[Callable[[Any, EstimateHistory], Array]], Callable[[Any, EstimateHistory], Array]]:
    """Decorator: ``fn(truth, history) -> (n, nominal_dim)`` for histories whose
    ``info["convention"]`` is ``convention`` (its frame only: no symmetries)."""

    def deco(
        fn: Callable[[Any, EstimateHistory], Array],
    ) -> Callable[[Any, EstimateHistory], Array]:
        _ALIGNMENTS[convention] = lambda truth, history, G: fn(truth, history)
        _SYMMETRIC.discard(convention)
        return fn

    return deco


def register_frame_alignment(convention: str) -> Callable[[FrameFn], FrameFn]:
    """Decorator: ``fn(truth, history, G) -> (n, nominal_dim)``: the truth in the symmetric
    frame ``T_G = G T`` of the convention's frame T (``G`` None: T itself), for histories
    whose ``info["convention"]`` is ``convention``; such conventions take part in the
    symmetries the history declares (:func:`align`)."""

    def deco(fn: FrameFn) -> FrameFn:
        _ALIGNMENTS[convention] = fn
        _SYMMETRIC.add(convention)
        return fn

    return deco


@dataclass(frozen=True)
class Alignment:
    """The truth in an estimator's convention and frame (``x``, (n, nominal_dim)), the
    symmetric frame ``G`` it is expressed in (identity: the convention's own) and the
    run's branch (``"nominal"`` or :func:`branch_name`)."""

    x: Array
    G: Array
    branch: str


def truth_state(truth: Any, history: EstimateHistory) -> Array:
    """The true nominal state (n, nominal_dim) in the history's convention and frame, so that
    ``history.layout.boxminus(truth_state, history.x)`` is the estimation error."""
    return align(truth, history).x


def align(truth: Any, history: EstimateHistory) -> Alignment:
    """The truth in the history's convention and in the symmetric frame its estimate is on
    (module docstring), with the run's branch."""
    conv = history.info.get("convention", "")
    fn = _ALIGNMENTS.get(conv)
    symmetric = fn is None or conv in _SYMMETRIC
    if fn is None:  # no convention, or one nobody registered: the generic blocks
        fn = generic_truth_state
    x0 = fn(truth, history, None)
    eye = np.eye(3)
    group = symmetry_group(history.info)
    if not symmetric or "attitude" not in history.layout.names():
        return Alignment(x0, eye, NOMINAL)
    if len(group) == 1 and np.array_equal(group[0], eye):
        return Alignment(x0, eye, NOMINAL)
    rule = history.info.get("symmetry_reference") or (
        "first" if history.info.get("symmetries") is not None else "run"
    )
    sq = history.layout.nom("attitude")
    i = choose_frame(x0[:, sq], history.x, sq, group, rule)
    if i is None or np.allclose(group[i], eye, atol=1e-9):
        return Alignment(x0, eye, NOMINAL)
    G = group[i]
    return Alignment(fn(truth, history, G), G, branch_name(G))


def symmetry_group(info: dict[str, Any]) -> list[Array]:
    """The symmetric frames a history declares (module docstring): 3x3 rotations, the
    identity alone when it declares none."""
    explicit = info.get("symmetries")
    if explicit is not None:
        out = [np.asarray(S, dtype=float).reshape(3, 3) for S in explicit]
        return out or [np.eye(3)]
    name = info.get("symmetry")
    if name is None:
        return [np.eye(3)]
    if name not in SYMMETRY_GROUPS:
        raise ValueError(
            f"history.info['symmetry'] = {name!r}: the known groups are "
            f"{', '.join(sorted(SYMMETRY_GROUPS))} (or give info['symmetries'], a list of 3x3)"
        )
    return SYMMETRY_GROUPS[name]()


def signed_permutations() -> list[Array]:
    """The 24 proper signed permutation matrices (det +1), the identity first."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            G = np.zeros((3, 3))
            G[np.arange(3), perm] = signs
            if np.linalg.det(G) > 0:
                out.append(G)
    return out


def half_turns() -> list[Array]:
    """The identity and the half turns about x, y and z."""
    return [np.diag(d) for d in ([1.0, 1, 1], [1.0, -1, -1], [-1.0, 1, -1], [-1.0, -1, 1])]


SYMMETRY_GROUPS: dict[str, Callable[[], list[Array]]] = {
    "principal_axes": signed_permutations,
    "half_turns": half_turns,
}


def choose_frame(
    q_true: Array, x_est: Array, sq: slice, group: Sequence[Array], rule: str
) -> int | None:
    """Index into ``group`` of the symmetric frame the estimate is on (module docstring);
    ``q_true`` (n, 4): the true attitude in the convention's own frame; None: no estimate."""
    if rule == "first":
        first = np.flatnonzero(np.all(np.isfinite(x_est), axis=1))
        if not len(first):
            return None
        k = first[0]
        R_est = rot.quat_to_matrix(x_est[k, sq])
        R_true = rot.quat_to_matrix(q_true[k])
        scores = [np.sum(R_est * (S @ R_true)) for S in group]
        return int(np.argmax(scores))  # the first of equal scores, as max() does
    if rule != "run":
        raise ValueError(f"history.info['symmetry_reference'] = {rule!r}: use 'first' or 'run'")
    q_est = x_est[:, sq]
    ok = np.all(np.isfinite(q_est), axis=1) & np.all(np.isfinite(q_true), axis=1)
    if not ok.any():
        return None
    R_est = rot.quat_to_matrix(q_est[ok])  # (m, 3, 3)
    R_true = rot.quat_to_matrix(q_true[ok])
    Gs = np.stack(group)  # (g, 3, 3)
    # trace(R_est^T G R_true) = 1 + 2 cos(angle between the estimate and the frame G)
    tr = np.einsum("mij,gik,mkj->mg", R_est, Gs, R_true)
    best = np.argmax(tr, axis=1)
    near = tr[np.arange(len(tr)), best] >= 1.0 + 2.0 * np.cos(np.radians(BRANCH_MAX_DEG))
    votes = np.bincount(best[near], minlength=len(group))
    eye = [i for i, S in enumerate(group) if np.allclose(S, np.eye(3), atol=1e-9)]
    own = votes[eye[0]] if eye else 0
    i = int(np.argmax(votes))
    if votes[i] <= own or votes[i] < BRANCH_MIN_FRACTION * ok.sum():
        return eye[0] if eye else None
    return i


def branch_name(G: Array) -> str:
    """A short name of the symmetric frame ``G``: ``"nominal"`` (identity), ``"half turn
    z"``, ``"x<->y (y,x,-z)"`` (the estimate's axes in the truth's: its x is the truth's y,
    its z the truth's -z), ``"x->y->z (y,z,x)"``; another rotation by its angle and axis."""
    G = np.asarray(G, dtype=float)
    if np.allclose(G, np.eye(3), atol=1e-9):
        return NOMINAL
    a = np.abs(G)
    if np.allclose(np.sort(a, axis=1), [[0, 0, 1]] * 3, atol=1e-9) and np.allclose(
        a.sum(0), 1, atol=1e-9
    ):
        perm = np.argmax(a, axis=1)
        signs = np.sign(G[np.arange(3), perm])
        axes = ",".join(("-" if s < 0 else "") + "xyz"[p] for s, p in zip(signs, perm, strict=True))
        moved = [i for i in range(3) if perm[i] != i]
        if not moved:
            return f"half turn {'xyz'[int(np.flatnonzero(signs > 0)[0])]}"
        if len(moved) == 2:
            return f"{'xyz'[moved[0]]}<->{'xyz'[moved[1]]} ({axes})"
        return f"x->{'xyz'[perm[0]]}->{'xyz'[perm[perm[0]]]} ({axes})"
    rv = rot.log_map(G)
    norm = float(np.linalg.norm(rv))
    ang = float(np.degrees(norm))
    ax = np.round(rv / max(norm, 1e-12), 2).tolist()
    return f"rotation {ang:.0f} deg about {ax}"


def _turned(x: Array, lay: StateLayout, G: Array) -> None:
    """Turn the generic T-fixed blocks of ``x`` (n, nominal_dim) in place into ``T_G = G T``:
    attitude ``q(G) (x) q_TI``, rate, features and offset ``G v``; other blocks as they are."""
    names = lay.names()
    if "attitude" in names:
        sq = lay.nom("attitude")
        x[:, sq] = rot.quat_multiply(rot.matrix_to_quat(G), x[:, sq])
    for name in ("rate", "offset"):
        if name in names:
            s = lay.nom(name)
            x[:, s] = x[:, s] @ G.T
    if "features" in names:
        s = lay.nom("features")
        f = x[:, s].reshape(len(x), -1, 3)
        x[:, s] = (f @ G.T).reshape(len(x), -1)


def generic_truth_state(truth: Any, history: EstimateHistory, G: Array | None = None) -> Array:
    """The standard blocks in the scenario's T (see the module docstring), or in ``G T``;
    NaN elsewhere."""
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
    if G is not None:
        _turned(x, lay, np.asarray(G, dtype=float))
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


@register_frame_alignment("hu2024")
def hu_truth_state(truth: Any, history: EstimateHistory, G: Array | None = None) -> Array:
    """The truth in the run's DPACF frame T' (:func:`canonical_frame`), or in ``G T'`` (the
    inertia ratios of the turned moments: Hu 2024's p, relabelled with the axes)."""
    R = canonical_frame(history.info["template_G"], history.info["known"], truth)
    if G is not None:
        R = np.asarray(G, dtype=float) @ R
    return truth_in_frame(truth, R, history.layout)


# --- Kabir 2025 ----------------------------------------------------------------------------


def kabir_truth_state_of(truth: Any, G: Array | None = None) -> Array:
    """The truth (n, 9 + 3N) in Kabir 2025's state: ``[omega_TI_T, q_TI, k1, k2, p]`` with
    ``k1 = log(I1/I2)``, ``k2 = log(I3/I2)`` (eq. 7); with ``G``, in the frame ``G T`` (the
    moments relabelled with the axes: ``I_G = diag(G I G^T)``)."""
    I_T = np.asarray(truth.inertia_T, dtype=float)
    if G is not None:
        G = np.asarray(G, dtype=float)
        I_T = G @ I_T @ G.T
    I = np.diag(I_T)
    n = len(truth.t)
    k = np.array([np.log(I[0] / I[1]), np.log(I[2] / I[1])])
    f = np.asarray(truth.features_T, dtype=float)
    w, q = truth.omega_TI_T, truth.q_TI
    if G is not None:
        w = w @ G.T
        q = rot.quat_multiply(rot.matrix_to_quat(G), q)
        f = f @ G.T
    f = f.ravel()
    return np.concatenate([w, q, np.tile(k, (n, 1)), np.tile(f, (n, 1))], axis=1)


@register_frame_alignment("kabir2025")
def kabir_truth_state(truth: Any, history: EstimateHistory, G: Array | None = None) -> Array:
    return kabir_truth_state_of(truth, G)


# --- Yu 2019 -------------------------------------------------------------------------------


@register_frame_alignment("yu2019")
def yu_truth_state(truth: Any, history: EstimateHistory, G: Array | None = None) -> Array:
    """The truth in the estimator's frame, ``G T``: rectangles alone fix the attitude only
    up to the model's own symmetries (for the procedural satellite: half turns about its
    axes), which the estimator declares in ``info["symmetries"]``; :func:`align` picks the
    symmetric frame the filter started in (at the first estimate; later jumps between
    symmetric frames count as errors). Yu's inertia is the full matrix over ``I_xx``:
    ``[I_yy, I_zz, I_xy, I_xz, I_yz] / I_xx`` of ``G I G^T``."""
    lay = history.layout
    G = np.eye(3) if G is None else np.asarray(G, dtype=float)
    sq = lay.nom("attitude")
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
