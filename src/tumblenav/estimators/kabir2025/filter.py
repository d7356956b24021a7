"""Kabir 2025's UKF run: predict and update (eq. 13-15, 22-25) as stateless steps folded per
run (:class:`UKFSteps`, the reference), the batched engine :func:`_filter` (campaigns), and
the histories."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from tumblenav import rotations as rot
from tumblenav.estimators.base import (
    Belief,
    EstimateHistory,
    StateLayout,
    StepInfo,
    fold,
)
from tumblenav.estimators.context import context_from_scenario
from tumblenav.estimators.kabir2025.init import initial_state
from tumblenav.estimators.kabir2025.model import (
    KabirGeometry,
    _boxplus,
    _filter_layout,
    _process_noise,
    additive_to_error_cov,
    geometry,
    layout,
    propagate_rotation,
)
from tumblenav.estimators.kabir2025.observations import measurement_model
from tumblenav.estimators.kabir2025.tuning import KabirTuning, parse_tuning
from tumblenav.estimators.kabir2025.unscented import _Unscented

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


@dataclass(frozen=True)
class _UKFModel:
    """What the UKF's predict and update share, for one run or a batch: the unscented
    transform, Q, the gate, the known geometry, the tuning and the variant."""

    ut: _Unscented
    Q: Array
    gate: Array | None
    geom: KabirGeometry
    tun: KabirTuning
    variant: Variant
    N: int

    @classmethod
    def make(cls, d: int, N: int, geom: KabirGeometry, tun: KabirTuning, variant: Variant):
        gate = None
        if tun.gate_probability is not None:
            gate = stats.chi2.ppf(tun.gate_probability, np.arange(10))  # by dof 0..9
        ut = _Unscented.make(d, tun.alpha, tun.beta, tun.kappa)
        return cls(ut, _process_noise(tun, N, variant), gate, geom, tun, variant, N)

    @property
    def additive(self) -> bool:
        return self.variant == "additive"

    def sigma(self, x: Array, P: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Sigma points (B, 2d+1, nom), their offsets, and the runs whose P needed a repair."""
        off, rep = self.ut.offsets(P)
        X = x[:, None, :] + off if self.additive else _boxplus(x[:, None, :], off)
        return X, off, rep

    def predict(self, x: Array, P: Array, dt: float) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Kabir 2025 eq. 13-15 for B runs over ``dt``; also the runs repaired."""
        Wm = self.ut.Wm
        X, _, rep = self.sigma(x, P)
        w, q = propagate_rotation(X[..., 0:3], X[..., 3:7], X[..., 7:9], dt)
        if self.additive:
            X = np.concatenate([w, q, X[..., 7:]], axis=-1)
            x = Wm @ X
            D = X - x[:, None, :]
            x[:, 3:7] /= np.linalg.norm(x[:, 3:7], axis=-1, keepdims=True)
        else:
            q = q / np.linalg.norm(q, axis=-1, keepdims=True)
            X = np.concatenate([w, q, X[..., 7:]], axis=-1)
            x = Wm @ X
            # mean attitude: the weighted mean e_bar of the sigma points' errors e_i about the
            # propagated centre point, and their deviations e_i - e_bar (BCH: exact to
            # O(|e_i| |e_bar|), e_bar being second order in the spread)
            qc = q[:, 0]
            e = rot.boxminus_fast(q, qc[:, None, :])
            e_bar = Wm @ e
            x[:, 3:7] = rot.boxplus_fast(qc, e_bar)
            D = np.concatenate(
                [w - x[:, None, 0:3], e - e_bar[:, None, :], X[..., 7:] - x[:, None, 7:]],
                axis=-1,
            )
        return x, self.ut.cov(D, D) + self.Q, rep

    def update(
        self, x: Array, P: Array, k: int, zk: Array, Rk: Array, rows: NDArray[np.bool_]
    ) -> tuple[Array, Array, Array, NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
        """Kabir 2025 eq. 22-25 for B runs with epoch ``k``'s measurements ``zk``, variances
        ``Rk`` (B, 9N) where ``rows``; returns x, P, NIS and its dof (B,), the rejected
        features (B,) and the runs repaired."""
        ut, geom, N = self.ut, self.geom, self.N
        B, M, d = x.shape[0], 9 * N, P.shape[-1]
        diag = np.arange(M)
        X, off, rep = self.sigma(x, P)
        Z = measurement_model(
            X, geom.R_CI, geom.rho0_C[k], geom.rho0_dot_C[k], geom.centres_x
        ).reshape(B, -1, M)
        zh = ut.Wm @ Z
        dZ = Z - zh[:, None, :]
        S0 = ut.cov(dZ, dZ)
        S0[:, diag, diag] += np.where(rows, Rk, 0.0)
        Pxz = ut.cov(off, dZ)
        nu = np.where(rows, zk - zh, 0.0)
        rejected = np.zeros(B, dtype=np.int64)
        if self.gate is not None:
            rows, rejected = _gate(S0, nu, rows, self.gate, N)
            nu = np.where(rows, nu, 0.0)
        both = rows[:, :, None] & rows[:, None, :]
        S = np.where(both, S0, 0.0)
        S[:, diag, diag] += ~rows
        Pxz = Pxz * rows[:, None, :]
        sol = np.linalg.solve(S, np.concatenate([np.swapaxes(Pxz, 1, 2), nu[..., None]], 2))
        Kt, Sinv_nu = sol[..., :d], sol[..., d]
        dx = (Pxz @ Sinv_nu[..., None])[..., 0]
        P = P - Pxz @ Kt
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        if self.additive:
            x = x + dx
            x[:, 3:7] /= np.linalg.norm(x[:, 3:7], axis=-1, keepdims=True)
        else:
            x = _boxplus(x, dx)
            # reset of the error to the new nominal: theta' = theta - dtheta +
            # 1/2 [dtheta x] theta (BCH), so P <- G P G^T, G = I + 1/2 [dtheta x]
            G = np.broadcast_to(np.eye(d), P.shape).copy()
            G[:, 3:6, 3:6] += 0.5 * rot.skew(dx[:, 3:6])
            P = G @ P @ np.swapaxes(G, -1, -2)
        nis = np.where(rows.any(1), np.sum(nu * Sinv_nu, axis=1), np.nan)
        return x, P, nis, rows.sum(1), rejected, rep


def _filter(
    t: Array,
    z: Array,
    Rv: Array,
    x0: Array,
    P0: Array,
    geom: KabirGeometry,
    tun: KabirTuning,
    variant: Variant,
) -> dict[str, Any]:
    """The batched engine: B filters at once, z, Rv (B, n, N, 9); x0 (B, nom); P0 (B, d, d);
    the same predict and update as :class:`UKFSteps` (tested equal to its fold).

    Returns x (B, n, nom), P (B, n, d, d) of the filter's own state, nis, nis_dof,
    rejected (B,), diverged_at (B,) epoch or -1, repairs (B,).
    """
    B, n, N, _ = z.shape
    M = 9 * N
    nom = 9 + 3 * N
    d = P0.shape[-1]
    m = _UKFModel.make(d, N, geom, tun, variant)
    z = z.reshape(B, n, M)
    Rv = Rv.reshape(B, n, M)
    usable = np.isfinite(z) & np.isfinite(Rv)
    x = np.array(x0, dtype=float)
    P = np.array(P0, dtype=float)
    xs = np.full((B, n, nom), np.nan)
    Ps = np.full((B, n, d, d), np.nan)
    nis = np.full((B, n), np.nan)
    nis_dof = np.zeros((B, n), dtype=np.int64)
    rejected = np.zeros(B, dtype=np.int64)
    repairs = np.zeros(B, dtype=np.int64)
    diverged_at = np.full(B, -1, dtype=np.int64)
    alive = np.ones(B, dtype=bool)

    # a diverging run overflows before it is caught (and stopped) by the finite check
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for k in range(n):
            x_prev, P_prev = x, P
            try:
                if k > 0:
                    x, P, rep = m.predict(x, P, t[k] - t[k - 1])
                    repairs[rep & alive] += 1
                rows = usable[:, k] & alive[:, None]
                if rows.any():
                    x, P, nis_k, dof_k, rej, rep = m.update(x, P, k, z[:, k], Rv[:, k], rows)
                    repairs[rep & alive] += 1
                    rejected += rej
                    nis[:, k] = nis_k
                    nis_dof[:, k] = dof_k
                ok = _sane(x, P)
            except np.linalg.LinAlgError:
                ok = np.zeros(B, dtype=bool)
                x, P = x_prev, P_prev
            if not ok.all():
                bad = alive & ~ok
                diverged_at[bad] = k
                alive &= ok
                x = np.where(ok[:, None], x, x_prev)
                P = np.where(ok[:, None, None], P, P_prev)
                if not alive.any():
                    break
            xs[:, k] = np.where(alive[:, None], x, np.nan)
            Ps[:, k] = np.where(alive[:, None, None], P, np.nan)
    nis[~np.isfinite(xs[..., 0])] = np.nan
    return {
        "x": xs,
        "P": Ps,
        "nis": nis,
        "nis_dof": nis_dof,
        "rejected": rejected,
        "diverged_at": diverged_at,
        "repairs": repairs,
        "usable": usable.reshape(B, n, N, 9),
    }


@dataclass(frozen=True)
class UKFSteps:
    """Kabir 2025's UKF as stateless steps on one run's prepared measurements, folded by
    :func:`tumblenav.estimators.base.fold` (the reference engine of :func:`run_ukf`; the
    batched :func:`_filter` is the fast one for campaigns, tested equal). The filter starts
    at the first epoch from ``x0``, ``P0``; a state or covariance that is no longer finite or
    absurd stops the run (counted as diverged, Kabir 2025 Sec. 3.2)."""

    model: _UKFModel
    t: Array
    z: Array  # (n, 9N)
    Rv: Array  # (n, 9N)
    x0: Array
    P0: Array
    layout: StateLayout

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        if k != 0:
            return None, StepInfo()
        return Belief(float(self.t[0]), self.x0.copy(), self.P0.copy(), self.layout), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            try:
                x, P, rep = self.model.predict(belief.x[None], belief.P[None], t - belief.t)
            except np.linalg.LinAlgError:  # update() sees a non-finite state: diverged
                x, P, rep = (
                    np.full((1,) + belief.x.shape, np.nan),
                    belief.P[None],
                    np.array([False]),
                )
        return Belief(t, x[0], P[0], self.layout, memo=int(rep[0]))

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        repairs = belief.memo or 0
        rows = (np.isfinite(self.z[k]) & np.isfinite(self.Rv[k]))[None]
        x, P = belief.x[None], belief.P[None]
        nis, dof, rej = float("nan"), 0, 0
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            try:
                if rows.any():
                    x, P, nis_k, dof_k, rej_k, rep = self.model.update(
                        x, P, k, self.z[k][None], self.Rv[k][None], rows
                    )
                    nis, dof, rej = float(nis_k[0]), int(dof_k[0]), int(rej_k[0])
                    repairs += int(rep[0])
                ok = bool(_sane(x, P)[0])
            except np.linalg.LinAlgError:
                ok = False
        skipped = {"covariance_repairs": repairs}
        out = Belief(belief.t, x[0], P[0], self.layout)
        if not ok:
            return belief, StepInfo(diverged=True, skipped=skipped)
        return out, StepInfo(nis=nis, dof=dof, rejected=rej, skipped=skipped)

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P


# A run is stopped (counted as diverged) once its state or covariance is no longer finite or
# is absurd: any state component beyond 1e6 (rad/s, log inertia ratio, m) or variance beyond
# 1e12.  Kabir 2025 Sec. 3.2 stops its UKF the same way when the covariance of omega "reaches
# virtually infinity" during occlusion.
_MAX_STATE, _MAX_VARIANCE = 1e6, 1e12


def _sane(x: Array, P: Array) -> NDArray[np.bool_]:
    var = np.diagonal(P, axis1=1, axis2=2)
    return (
        np.all(np.abs(x) < _MAX_STATE, axis=1)
        & np.all(var < _MAX_VARIANCE, axis=1)
        & np.all(np.isfinite(P), axis=(1, 2))
    )


def _gate(
    S: Array, nu: Array, rows: NDArray[np.bool_], gate: Array, N: int
) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """Per-feature chi-square gate on the 9 (or fewer available) components of each feature."""
    B = S.shape[0]
    r = rows.reshape(B, N, 9)
    Sb = np.stack([S[:, 9 * i : 9 * i + 9, 9 * i : 9 * i + 9] for i in range(N)], axis=1)
    both = r[..., :, None] & r[..., None, :]
    Sb = np.where(both, Sb, 0.0) + (~r)[..., None] * np.eye(9)
    nb = np.where(r, nu.reshape(B, N, 9), 0.0)
    d2 = np.sum(nb * np.linalg.solve(Sb, nb[..., None])[..., 0], axis=-1)
    dof = r.sum(-1)
    reject = (dof > 0) & (d2 > gate[dof])
    return (r & ~reject[..., None]).reshape(B, -1), reject.sum(axis=1)


def run_ukf(
    scenario: Any,
    t: Array,
    z: Array,
    R_diag: Array,
    variant: Variant = "additive",
    tuning: KabirTuning | None = None,
    geom: KabirGeometry | None = None,
    x0: Array | None = None,
    P0: Array | None = None,
) -> EstimateHistory:
    """Kabir 2025's UKF (``variant='additive'``) or its multiplicative variant (``'mult'``)
    on prepared measurements.

    Parameters
    ----------
    scenario : Scenario
        For the known geometry (the mass centre from the settings, the rig).
    t : (n,) s
        Epochs; the filter starts at ``t[0]`` (update with ``z[0]``), then predicts and
        updates at every epoch.
    z : (n, N, 9) array
        Per feature ``[u_R, v_R, u_L, v_L, u_L - u_R, du_R, dv_R, du_L, dv_L]`` (rad, rad/s),
        NaN where not available (that component is not used; an epoch with none is a
        prediction only).
    R_diag : (n, N, 9) array
        Variance of each component of ``z`` (rad^2, rad^2/s^2); NaN = not available.
    variant : 'additive' or 'mult'
    tuning : KabirTuning, optional
        Default: ``parse_tuning(scenario.estimator.tuning)``.
    geom : KabirGeometry, optional
        Default: :func:`geometry` ``(scenario, t)``.
    x0, P0 : arrays, optional
        Initial state and covariance (24x24 additive, 23x23 mult); default
        :func:`initial_state`.

    Returns
    -------
    EstimateHistory
        Layout :func:`layout`; ``P`` is the 23-dim error-state covariance for both variants.
    """
    scenario = context_from_scenario(scenario)  # never the target's truth
    if variant not in ("additive", "mult"):
        raise ValueError(f"variant must be 'additive' or 'mult', got {variant!r}")
    tun = tuning if tuning is not None else parse_tuning(scenario.estimator.tuning)
    t = np.asarray(t, dtype=float)
    z = np.asarray(z, dtype=float)
    R_diag = np.asarray(R_diag, dtype=float)
    N = z.shape[1] if z.ndim == 3 else 0
    if z.shape != (len(t), N, 9) or R_diag.shape != z.shape:
        raise ValueError(f"z and R_diag must have shape (n, N, 9) = ({len(t)}, N, 9)")
    geom = geom if geom is not None else geometry(scenario, t)
    if x0 is None or P0 is None:
        x0_, P0_ = initial_state(scenario, t, z, geom, tun, variant)
        x0 = x0_ if x0 is None else x0
        P0 = P0_ if P0 is None else P0
    n = len(t)
    steps = UKFSteps(
        model=_UKFModel.make(np.asarray(P0).shape[-1], N, geom, tun, variant),
        t=t,
        z=z.reshape(n, 9 * N),
        Rv=R_diag.reshape(n, 9 * N),
        x0=np.asarray(x0, dtype=float),
        P0=np.asarray(P0, dtype=float),
        layout=_filter_layout(N, variant),
    )
    r = fold(steps, t)
    stopped = np.flatnonzero(np.isfinite(r.x[:-1, 0]) & ~np.isfinite(r.x[1:, 0])) + 1
    usable = np.isfinite(z) & np.isfinite(R_diag)
    res = {
        "x": r.x[None],
        "P": r.P[None],
        "nis": r.nis[None],
        "nis_dof": r.nis_dof[None].astype(np.int64),
        "rejected": np.array([r.rejected]),
        "diverged_at": np.array([(int(stopped[0]) if len(stopped) else 0) if r.diverged else -1]),
        "repairs": np.array([r.skipped.get("covariance_repairs", 0)]),
        "usable": usable[None],
    }
    return _history(t, res, 0, variant, tun, np.asarray(x0))


def _history(
    t: Array, res: dict[str, Any], b: int, variant: Variant, tun: KabirTuning, x0: Array
) -> EstimateHistory:
    """Run ``b`` of a :func:`_filter` result as an :class:`EstimateHistory` (the covariance
    as the 23-dim error-state covariance for both variants)."""
    x, P = res["x"][b], res["P"][b]
    if variant == "additive":
        P = additive_to_error_cov(x, P)
    div = int(res["diverged_at"][b])
    return EstimateHistory(
        t=t,
        x=x,
        P=P,
        layout=layout((x.shape[-1] - 9) // 3),
        nis=res["nis"][b],
        nis_dof=res["nis_dof"][b],
        skipped=_skipped(res["usable"][b], res, b),
        info={
            "convention": "kabir2025",  # [omega_TI_T, q_TI, k1, k2, p_T]: evaluation.alignment
            "variant": variant,
            "diverged_at_s": float(t[div]) if div >= 0 else None,
            "tuning": tun.model_dump(),
            "x0": x0,
        },
    )


def _skipped(usable: NDArray[np.bool_], res: dict, b: int) -> dict[str, int]:
    any_f = usable.any(axis=-1)  # (n, N)
    return {
        "no_measurement_epochs": int((~any_f.any(axis=-1)).sum()),
        "unobserved_feature_epochs": int((~any_f).sum()),
        "gated_out": int(res["rejected"][b]),
        "diverged": int(res["diverged_at"][b] >= 0),
        "covariance_repairs": int(res["repairs"][b]),
    }
