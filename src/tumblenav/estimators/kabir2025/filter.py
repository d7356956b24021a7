"""Kabir 2025's UKF run: predict and update (eq. 13-15, 22-25) as stateless steps folded per
run (:class:`UKFSteps`, the reference), the batched engine :func:`_filter` (campaigns), and
the histories."""

from __future__ import annotations

import dataclasses
import functools
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
from tumblenav.estimators.kabir2025.init import KabirStart, error_to_filter_cov, start
from tumblenav.estimators.kabir2025.model import (
    KabirGeometry,
    _boxplus,
    _filter_layout,
    _process_noise,
    additive_to_error_cov,
    geometry,
    layout,
    propagate_rotation_compiled,
    world_chart_points,
)
from tumblenav.estimators.kabir2025.observations import (
    measurement_model,
    stencil_measurement_model_compiled,
)
from tumblenav.estimators.kabir2025.tuning import (
    KabirTuning,
    derive_tuning,
    parse_tuning,
    resolve_tuning,
)
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
    dt: float  # the (uniform) sample interval: eq. 27's stencil in the flow model

    @classmethod
    def make(
        cls,
        d: int,
        N: int,
        geom: KabirGeometry,
        tun: KabirTuning,
        variant: Variant,
        dt: float = 1.0,
    ):
        gate = None
        if tun.gate_probability is not None:
            gate = stats.chi2.ppf(tun.gate_probability, np.arange(10))  # by dof 0..9
        ut = _Unscented.make(d, tun.alpha, tun.beta, tun.kappa)
        return cls(ut, _process_noise(tun, N, variant), gate, geom, tun, variant, N, dt)

    @property
    def additive(self) -> bool:
        return self.variant == "additive"

    def sigma(self, x: Array, P: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Sigma points (B, 2d+1, nom), their offsets, and the runs whose P needed a repair."""
        off, rep = self.ut.offsets(P)
        X = x[:, None, :] + off if self.additive else _boxplus(x[:, None, :], off)
        return X, off, rep

    def predict(
        self,
        x: Array,
        P: Array,
        dt: float,
        coast: NDArray[np.bool_] | None = None,
        rigid_fixed: NDArray[np.bool_] | None = None,
    ) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Kabir 2025 eq. 13-15 for B runs over ``dt``; also the runs repaired.

        ``coast`` (B,): runs that had no measurement at the previous epoch (a loss of every
        feature: the filter only propagates). For them the mean is the propagated centre
        point: the scaled transform's large negative centre weight (alpha = 0.1: W_0 ~ -99)
        extrapolates the curvature of hundreds of steps of uncorrected propagation, and drove
        the rate of ukf-mult to 1e4 deg/s through Kabir's 1500-s occlusion. The covariance is
        ``sum_i>0 W_i (X_i - X_0)(X_i - X_0)^T`` over the points of ``tun.coast_covariance``:
        the cubature rule's (default: points at +- sqrt(d) sigma, which see how a rate error
        shifts the polhode's phase over the coast) or alpha's (at 0.1 sqrt(d) sigma: the
        linearised propagation, which let the rate and attitude errors of kabir_paper's loss
        grow 2-6x beyond their sigma). tumblenav defaults.

        ``rigid_fixed`` (B,): runs predicting into an epoch whose update leaves the rigid
        parameters alone (``consider`` in :meth:`update`): no process noise on them, nor on
        runs in ``coast``. Their Q is a floor for what thousands of updates' linearisation
        errors do to them (:func:`~.tuning.derive_tuning`); without an update the rigid
        body's inertia and features do not move.
        """
        B = x.shape[0]
        coast = np.zeros(B, dtype=bool) if coast is None else np.asarray(coast, dtype=bool)
        x_in, P_in = x, P
        x, D, rep = self._propagate_points(self.ut, x_in, P_in, dt, coast)
        P = self.ut.cov(D, D)
        if coast.any():
            # a coast: the mean is the propagated centre point (above), the covariance the
            # spread of the points about it; the cubature rule's points by default
            # (coast_covariance; tumblenav, issue 18)
            ut = self.ut
            if self.tun.coast_covariance == "cubature":
                ut = self._coast_ut
                _, Dc_all, rep_c = self._propagate_points(ut, x_in[coast], P_in[coast], dt, None)
                rep[coast] |= rep_c
            else:
                Dc_all = D[coast]
            Dc = Dc_all[:, 1:]
            P[coast] = np.swapaxes(Dc * ut.Wm[1:, None], -1, -2) @ Dc
        fixed = coast.copy()  # nothing updates the rigid parameters in a coast
        if rigid_fixed is not None:
            fixed |= np.asarray(rigid_fixed, dtype=bool)
        if fixed.any():
            o = 7 if self.additive else 6
            Qr = np.broadcast_to(self.Q, P.shape).copy()
            Qr[fixed, o:, o:] = 0.0
            P = P + Qr
        else:
            P = P + self.Q
        if not self.additive:  # a long occlusion is all predictions: hold the lost attitude
            P = _cap_attitude(P)
        return x, P, rep

    @functools.cached_property
    def _coast_ut(self) -> _Unscented:
        """The third-degree spherical-radial cubature rule (Arasaratnam & Haykin 2009) as
        an unscented transform: alpha 1, kappa 0 (lambda 0: no centre weight, the 2d points
        at +- sqrt(d) columns of sqrt(P), weights 1/(2d))."""
        return _Unscented.make(self.Q.shape[-1], 1.0, 0.0, 0.0)

    def _propagate_points(
        self, ut: _Unscented, x: Array, P: Array, dt: float, coast: NDArray[np.bool_] | None
    ) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Kabir 2025 eq. 13-14 with ``ut``'s points: the predicted mean (B, nom) -- the
        propagated centre point for runs in ``coast`` (None: every run), else the weighted
        mean -- the points' deviations from it (B, S, d) and the runs repaired."""
        Wm = ut.Wm
        B = x.shape[0]
        coast = np.ones(B, dtype=bool) if coast is None else coast
        off, rep = ut.offsets(P)
        X = x[:, None, :] + off if self.additive else _boxplus(x[:, None, :], off)
        w, q = propagate_rotation_compiled(X[..., 0:3], X[..., 3:7], X[..., 7:9], dt)
        if self.additive:
            X = np.concatenate([w, q, X[..., 7:]], axis=-1)
            x = np.where(coast[:, None], X[:, 0], Wm @ X)
            D = X - x[:, None, :]
            x[:, 3:7] /= np.linalg.norm(x[:, 3:7], axis=-1, keepdims=True)
        else:
            q = q / np.linalg.norm(q, axis=-1, keepdims=True)
            X = np.concatenate([w, q, X[..., 7:]], axis=-1)
            x = np.where(coast[:, None], X[:, 0], Wm @ X)
            # mean attitude: the weighted mean e_bar of the sigma points' errors e_i about the
            # propagated centre point, and their deviations e_i - e_bar (BCH: exact to
            # O(|e_i| |e_bar|), e_bar being second order in the spread)
            qc = q[:, 0]
            e = rot.boxminus_fast(q, qc[:, None, :])
            e_bar = np.where(coast[:, None], 0.0, Wm @ e)
            x[:, 3:7] = rot.boxplus_fast(qc, e_bar)
            D = np.concatenate(
                [w - x[:, None, 0:3], e - e_bar[:, None, :], X[..., 7:] - x[:, None, 7:]],
                axis=-1,
            )
        return x, D, rep

    def update(
        self,
        x: Array,
        P: Array,
        k: int,
        zk: Array,
        Rk: Array,
        rows: NDArray[np.bool_],
        consider: NDArray[np.bool_] | None = None,
    ) -> tuple[Array, Array, Array, NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_], Array]:
        """Kabir 2025 eq. 22-25 for B runs with epoch ``k``'s measurements ``zk``, variances
        ``Rk`` (B, 9N) where ``rows``; returns x, P, NIS and its dof (B,), the rejected
        features (B,), the runs repaired and the innovations (B, 9N; NaN where not used).

        ``consider`` (B,): runs whose rigid parameters (inertia ratios and features) are
        consider parameters in this update (Schmidt): their gain is zero, so they keep their
        mean and covariance, while their cross-covariance with the rate and attitude is
        updated as for any gain (``P - K Pxz^T - Pxz K^T + K S K^T``, i.e. only the rigid
        block keeps its prior). ukf-gp uses it for its GP pseudo-measurements, which are
        made from the same training data the filter already used for these parameters
        (tumblenav addition)."""
        ut, geom, N = self.ut, self.geom, self.N
        B, M, d = x.shape[0], 9 * N, P.shape[-1]
        diag = np.arange(M)
        # the update's chart (update_chart): 'world' for every run whose rigid parameters
        # are updated (a consider update keeps them, so it stays in the body chart)
        world = np.zeros(B, dtype=bool)
        if self.tun.update_chart == "world":
            world = np.ones(B, dtype=bool) if consider is None else ~np.asarray(consider)
        rep = np.zeros(B, dtype=bool)
        if world.any():
            x, P, rep = self._change_chart(x, P, world, to_world=True)
        X, off, rep_s = self.sigma(x, P)
        rep |= rep_s
        Xb = world_chart_points(X, world, to_world=False) if world.any() else X
        if self.tun.flow_model == "stencil" and np.any(rows.reshape(B, N, 9)[..., 5:]):
            Z = stencil_measurement_model_compiled(
                Xb, geom.R_CI, geom.rho0_C[k], geom.rho0_dot_C[k], geom.centres_x, self.dt
            )
        else:
            Z = measurement_model(Xb, geom.R_CI, geom.rho0_C[k], geom.rho0_dot_C[k], geom.centres_x)
        Z = Z.reshape(B, -1, M)
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
        if consider is not None and np.any(consider):
            # Schmidt update: K's rigid rows zero; P - K_c Pxz^T - Pxz K_c^T + K_c S K_c^T
            # is P - (K S K^T) o (1 - c c^T) with K S K^T = Pxz Kt (c: the rigid components)
            c = np.zeros((B, d), dtype=bool)
            c[:, (7 if self.additive else 6) :] = np.asarray(consider, dtype=bool)[:, None]
            dx = np.where(c, 0.0, dx)
            P = P - (Pxz @ Kt) * (1.0 - (c[:, :, None] & c[:, None, :]))
        else:
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
        if world.any():
            x, P, rep_b = self._change_chart(x, P, world, to_world=False)
            rep |= rep_b
        if self.tun.relabel_axes:
            x, P = canonical_axes(x, P, self.additive)
        if not self.additive:
            P = _cap_attitude(P)
        nis = np.where(rows.any(1), np.sum(nu * Sinv_nu, axis=1), np.nan)
        return x, P, nis, rows.sum(1), rejected, rep, np.where(rows, nu, np.nan)

    def _change_chart(
        self, x: Array, P: Array, runs: NDArray[np.bool_], to_world: bool
    ) -> tuple[Array, Array, NDArray[np.bool_]]:
        """The mean and covariance of ``runs`` in the other chart
        (:func:`~.model.world_chart_points`): the mean is the centre point's image (the
        charts are one bijection, so a round trip returns the same mean), the covariance the
        spread of the transformed sigma points about it (the first-order map J P J^T, to
        fourth order in the spread)."""
        ut = self.ut
        off, rep = ut.offsets(P)
        X = x[:, None, :] + off if self.additive else _boxplus(x[:, None, :], off)
        Y = world_chart_points(X, runs, to_world)
        y = Y[:, 0]
        if self.additive:
            D = Y - y[:, None, :]
        else:
            D = np.concatenate(
                [
                    Y[..., 0:3] - y[:, None, 0:3],
                    rot.boxminus_fast(Y[..., 3:7], y[:, None, 3:7]),
                    Y[..., 7:] - y[:, None, 7:],
                ],
                axis=-1,
            )
        Pn = ut.cov(D, D)
        Pn = 0.5 * (Pn + np.swapaxes(Pn, -1, -2))
        return (
            np.where(runs[:, None], y, x),
            np.where(runs[:, None, None], Pn, P),
            rep & runs,
        )


def _filter(
    t: Array,
    z: Array,
    Rv: Array,
    x0: Array,
    P0: Array,
    geom: KabirGeometry,
    tun: KabirTuning,
    variant: Variant,
    k0: Array | None = None,
    skip_first: Array | None = None,
    Q: Array | None = None,
    consider: NDArray[np.bool_] | None = None,
) -> dict[str, Any]:
    """The batched engine: B filters at once, z, Rv (B, n, N, 9); x0 (B, nom); P0 (B, d, d)
    at each run's start epoch ``k0`` (B,) (default 0; ``skip_first``: no update at it, the
    start already holds that epoch's data); the same predict and update as
    :class:`UKFSteps` (tested equal to its fold). ``consider`` (B, n): epochs whose updates
    leave the rigid parameters as they are (:meth:`_UKFModel.update`).

    Returns x (B, n, nom), P (B, n, d, d) of the filter's own state, nis, nis_dof,
    rejected (B,), diverged_at (B,) epoch or -1, repairs (B,).
    """
    B, n, N, _ = z.shape
    M = 9 * N
    nom = 9 + 3 * N
    d = P0.shape[-1]
    m = _UKFModel.make(d, N, geom, tun, variant, _sample_interval(t))
    if Q is not None:  # per run (B, d, d): each run's derived tuning
        m = dataclasses.replace(m, Q=np.asarray(Q, dtype=float))
    z = z.reshape(B, n, M)
    Rv = Rv.reshape(B, n, M)
    usable = np.isfinite(z) & np.isfinite(Rv)
    x = np.array(x0, dtype=float)
    P = np.array(P0, dtype=float)
    xs = np.full((B, n, nom), np.nan)
    Ps = np.full((B, n, d, d), np.nan)
    nis = np.full((B, n), np.nan)
    nis_dof = np.zeros((B, n), dtype=np.int64)
    innov = np.full((B, n, M), np.nan)
    rejected = np.zeros(B, dtype=np.int64)
    repairs = np.zeros(B, dtype=np.int64)
    diverged_at = np.full(B, -1, dtype=np.int64)
    alive = np.ones(B, dtype=bool)
    coast = np.zeros(B, dtype=bool)  # no measurement at the previous epoch
    k0 = np.zeros(B, dtype=np.int64) if k0 is None else np.asarray(k0, dtype=np.int64)
    skip_first = np.zeros(B, dtype=bool) if skip_first is None else np.asarray(skip_first)
    x0 = np.asarray(x0, dtype=float)
    P0 = np.asarray(P0, dtype=float)

    # a diverging run overflows before it is caught (and stopped) by the finite check
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for k in range(n):
            x_prev, P_prev = x, P
            try:
                if k > 0:
                    fixed = None if consider is None else np.asarray(consider)[:, k]
                    x, P, rep = m.predict(x, P, t[k] - t[k - 1], coast, fixed)
                    repairs[rep & alive & (k > k0)] += 1
                fresh = k0 == k
                if fresh.any():  # runs starting now (before: placeholders, not reported)
                    x = np.where(fresh[:, None], x0, x)
                    P = np.where(fresh[:, None, None], P0, P)
                started = k >= k0
                rows = usable[:, k] & (alive & started & ~(fresh & skip_first))[:, None]
                coast = ~rows.any(axis=1)
                if rows.any():
                    ck = None if consider is None else np.asarray(consider)[:, k]
                    x, P, nis_k, dof_k, rej, rep, nu_k = m.update(
                        x, P, k, z[:, k], Rv[:, k], rows, ck
                    )
                    repairs[rep & alive] += 1
                    rejected += rej
                    nis[:, k] = nis_k
                    nis_dof[:, k] = dof_k
                    innov[:, k] = nu_k
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
            shown = alive & (k >= k0)
            xs[:, k] = np.where(shown[:, None], x, np.nan)
            Ps[:, k] = np.where(shown[:, None, None], P, np.nan)
    nis[~np.isfinite(xs[..., 0])] = np.nan
    return {
        "x": xs,
        "P": Ps,
        "nis": nis,
        "nis_dof": nis_dof,
        "innov": innov,
        "rejected": rejected,
        "diverged_at": diverged_at,
        "repairs": repairs,
        "usable": usable.reshape(B, n, N, 9),
        "k0": k0,
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
    k0: int = 0
    skip_first: bool = False
    consider: NDArray[np.bool_] | None = None  # (n,) epochs: _UKFModel.update's consider
    innovations: Array | None = None  # (n, 9N), filled in: each update's innovation (NaN: unused)

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]:
        if k != self.k0:
            return None, StepInfo()
        return Belief(float(self.t[k]), self.x0.copy(), self.P0.copy(), self.layout), StepInfo()

    def predict(self, belief: Belief, t: float) -> Belief:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            try:
                coast = np.array([bool((belief.memo or {}).get("coast", False))])
                fixed = None
                if self.consider is not None:
                    k = min(int(np.searchsorted(self.t, t)), len(self.t) - 1)
                    fixed = self.consider[k : k + 1]
                x, P, rep = self.model.predict(
                    belief.x[None], belief.P[None], t - belief.t, coast, fixed
                )
            except np.linalg.LinAlgError:  # update() sees a non-finite state: diverged
                x, P, rep = (
                    np.full((1,) + belief.x.shape, np.nan),
                    belief.P[None],
                    np.array([False]),
                )
        return Belief(t, x[0], P[0], self.layout, memo={"repairs": int(rep[0])})

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]:
        repairs = int((belief.memo or {}).get("repairs", 0))
        rows = (np.isfinite(self.z[k]) & np.isfinite(self.Rv[k]))[None]
        if started and self.skip_first:
            rows = np.zeros_like(rows)
        coast = {"coast": not bool(rows.any())}
        x, P = belief.x[None], belief.P[None]
        nis, dof, rej = float("nan"), 0, 0
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            try:
                if rows.any():
                    ck = None if self.consider is None else self.consider[k : k + 1]
                    x, P, nis_k, dof_k, rej_k, rep, nu_k = self.model.update(
                        x, P, k, self.z[k][None], self.Rv[k][None], rows, ck
                    )
                    nis, dof, rej = float(nis_k[0]), int(dof_k[0]), int(rej_k[0])
                    if self.innovations is not None:
                        self.innovations[k] = nu_k[0]
                    repairs += int(rep[0])
                ok = bool(_sane(x, P)[0])
            except np.linalg.LinAlgError:
                ok = False
        skipped = {"covariance_repairs": repairs}
        out = Belief(belief.t, x[0], P[0], self.layout, memo=coast)
        if not ok:
            return belief, StepInfo(diverged=True, skipped=skipped)
        return out, StepInfo(nis=nis, dof=dof, rejected=rej, skipped=skipped)

    def report(self, belief: Belief, k: int) -> Array:
        return belief.P


def _sample_interval(t: Array) -> float:
    """The median step of ``t`` (s; 1 for a single epoch): eq. 27's ``dt``."""
    return float(np.median(np.diff(t))) if len(t) > 1 else 1.0


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


@dataclass
class Prepared:
    """A run's start, its tuning with the derived values filled in, the flow variances set
    from it, and the warnings (issue 18: the tuning follows the scenario)."""

    start: KabirStart
    tuning: KabirTuning
    R_diag: Array
    derived: dict[str, Any]
    warnings: list[str]


def prepare(
    scenario: Any, t: Array, z: Array, R_diag: Array, geom: KabirGeometry, tun: KabirTuning
) -> Prepared:
    """The start (:func:`~tumblenav.estimators.kabir2025.init.start`) and the tuning derived
    from it (:func:`~tumblenav.estimators.kabir2025.tuning.derive_tuning`): unset Q and
    ``sigma_o`` take the derived values, explicit ones far from them draw a warning."""
    scenario = context_from_scenario(scenario)  # never the target's truth
    sigma_p = (
        float(np.sqrt(np.nanmax(R_diag[..., 0]))) if np.isfinite(R_diag[..., 0]).any() else 1e-5
    )
    st = start(scenario, t, z, geom, tun, sigma_p)
    x = st.x0
    k0 = st.k0
    R_CT = geom.R_CI @ rot.quat_to_matrix(x[3:7]).T
    rho = geom.rho0_C[k0] + x[9:].reshape(-1, 3) @ R_CT.T
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    pn = getattr(scenario, "process_noise", None)
    q_r = float(getattr(pn, "rotational_rad2_s4", 0.0) or 0.0)
    derived = derive_tuning(
        x[0:3],
        x[7:9],
        R_CT @ x[0:3],
        rho,
        geom.rho0_C[k0],
        geom.centres_x,
        dt,
        sigma_p,
        q_r,
        tun.flow_model,
    )
    tun_r, warns = resolve_tuning(tun, derived)
    R_diag = np.array(R_diag, dtype=float)
    if tun.sigma_flow_rad_s is None:
        flow = R_diag[..., 5:9]
        R_diag[..., 5:9] = np.where(np.isfinite(flow), derived["sigma_flow_rad_s"] ** 2, flow)
    if "warning" in st.info:
        warns.append(st.info["warning"])
    return Prepared(st, tun_r, R_diag, derived, warns)


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
    prepared: Prepared | None = None,
    consider: NDArray[np.bool_] | None = None,
) -> EstimateHistory:
    """Kabir 2025's UKF (``variant='additive'``) or its multiplicative variant (``'mult'``)
    on prepared measurements.

    Parameters
    ----------
    scenario : Scenario
        For the known geometry (the mass centre from the settings, the rig) and the process
        noise the derived Q follows.
    t : (n,) s
        Epochs; the filter starts at its start epoch (:func:`prepare`; ``t[0]`` for the
        ``given`` and ``triangulated`` starts), then predicts and updates at every epoch.
    z : (n, N, 9) array
        Per feature ``[u_R, v_R, u_L, v_L, u_L - u_R, du_R, dv_R, du_L, dv_L]`` (rad, rad/s),
        NaN where not available (that component is not used; an epoch with none is a
        prediction only).
    R_diag : (n, N, 9) array
        Variance of each component of ``z`` (rad^2, rad^2/s^2); NaN = not available. The flow
        variances are replaced by the derived ``sigma_o^2`` unless it is set explicitly.
    variant : 'additive' or 'mult'
    tuning : KabirTuning, optional
        Default: ``parse_tuning(scenario.estimator.tuning)``.
    geom : KabirGeometry, optional
        Default: :func:`geometry` ``(scenario, t)``.
    x0, P0 : arrays, optional
        Initial state and covariance (24x24 additive, 23x23 mult) at ``t[0]``, replacing the
        start's.
    prepared : Prepared, optional
        :func:`prepare`'s result, if already made (ukf-gp).
    consider : (n,) bool array, optional
        Epochs whose updates leave the inertia ratios and features as they are (consider
        parameters, :meth:`_UKFModel.update`; ukf-gp's pseudo-measurements).

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
    prep = prepared if prepared is not None else prepare(scenario, t, z, R_diag, geom, tun)
    st = prep.start
    k0, skip = st.k0, st.info.get("init") == "identified"
    if x0 is None:
        x0 = st.x0
    if P0 is None:
        P0 = error_to_filter_cov(np.asarray(x0), st.P0_err, variant)
    n = len(t)
    steps = UKFSteps(
        model=_UKFModel.make(
            np.asarray(P0).shape[-1], N, geom, prep.tuning, variant, _sample_interval(t)
        ),
        t=t,
        z=z.reshape(n, 9 * N),
        Rv=prep.R_diag.reshape(n, 9 * N),
        x0=np.asarray(x0, dtype=float),
        P0=np.asarray(P0, dtype=float),
        layout=_filter_layout(N, variant),
        k0=k0,
        skip_first=skip,
        consider=None if consider is None else np.asarray(consider, dtype=bool),
        innovations=np.full((n, 9 * N), np.nan),
    )
    r = fold(steps, t)
    stopped = np.flatnonzero(np.isfinite(r.x[:-1, 0]) & ~np.isfinite(r.x[1:, 0])) + 1
    usable = np.isfinite(z) & np.isfinite(prep.R_diag)
    res = {
        "x": r.x[None],
        "P": r.P[None],
        "nis": r.nis[None],
        "nis_dof": r.nis_dof[None].astype(np.int64),
        "rejected": np.array([r.rejected]),
        "diverged_at": np.array([(int(stopped[0]) if len(stopped) else 0) if r.diverged else -1]),
        "repairs": np.array([r.skipped.get("covariance_repairs", 0)]),
        "usable": usable[None],
        "innov": np.asarray(steps.innovations)[None],
    }
    return _history(t, res, 0, variant, prep.tuning, np.asarray(x0), prep)


def _history(
    t: Array,
    res: dict[str, Any],
    b: int,
    variant: Variant,
    tun: KabirTuning,
    x0: Array,
    prep: Prepared | None = None,
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
        innovations=res["innov"][b] if "innov" in res else None,
        skipped=_skipped(res["usable"][b], res, b),
        info={
            "convention": "kabir2025",  # [omega_TI_T, q_TI, k1, k2, p_T]: evaluation.alignment
            "variant": variant,
            "diverged_at_s": float(t[div]) if div >= 0 else None,
            "tuning": tun.model_dump(),
            "x0": x0,
            # the principal frame is the state's body frame: its axes are labelled by
            # ascending moments (k1 < 0 < k2, canonical_axes) and its signs are the start's;
            # an estimate is defined up to the principal axes' sign flips (and relabelling
            # where two moments are close)
            "symmetry": "principal_axes",
            "start": dict(prep.start.info) if prep is not None else {},
            "derived_tuning": dict(prep.derived) if prep is not None else {},
            "warnings": list(prep.warnings) if prep is not None else [],
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


# --- the principal axes' labelling (tumblenav default; issue 18) ----------------------------


def _axes_map(k: Array) -> tuple[Array, Array] | None:
    """For log-ratios ``k`` whose moments ``[e^k1, 1, e^k2]`` are not ascending: the proper
    signed permutation ``S`` (T' = S T) that sorts them, and the (2, 2) map of ``k``; None
    when already ascending."""
    logm = np.array([k[0], 0.0, k[1]])
    order = np.argsort(logm, kind="stable")
    if np.array_equal(order, [0, 1, 2]):
        return None
    S = np.zeros((3, 3))
    S[np.arange(3), order] = 1.0
    if np.linalg.det(S) < 0:
        S[1] *= -1.0  # the middle axis flips: a proper rotation
    # log m' = Pi log m; k' = [log m'_0 - log m'_1, log m'_2 - log m'_1] (log m_1 = 0)
    Pi = np.abs(S)
    D = np.array([[1.0, -1.0, 0.0], [0.0, -1.0, 1.0]]) @ Pi  # (2, 3) on [k1, 0, k2]
    return S, D[:, [0, 2]]


def canonical_axes(x: Array, P: Array, additive: bool) -> tuple[Array, Array]:
    """Relabel the principal axes of the runs (B) whose moments are confidently not ascending
    (``k1 < 0 < k2`` violated by more than 3 sigma of the difference: near a tie, e.g. from
    the paper's ``k = 0`` start, the labelling is left alone): the same physical estimate in
    the canonical labelling, with its covariance mapped exactly (every block is linear in the
    relabelling)."""
    o = 7 if additive else 6
    for b in np.flatnonzero((x[:, 7] > 0) | (x[:, 8] < 0) | (x[:, 7] > x[:, 8])):
        if not np.all(np.isfinite(x[b, 7:9])):
            continue
        Ck = P[b, o : o + 2, o : o + 2]
        # the three differences log m_i - log m_j (log m = [k1, 0, k2]) and their sigmas
        d = np.array([x[b, 7], -x[b, 8], x[b, 7] - x[b, 8]])
        var = np.array([Ck[0, 0], Ck[1, 1], Ck[0, 0] + Ck[1, 1] - 2 * Ck[0, 1]])
        if not np.any(d > 3.0 * np.sqrt(np.maximum(var, 0.0))):
            continue
        m = _axes_map(x[b, 7:9])
        if m is None:
            continue
        S, Dk = m
        qS = rot.matrix_to_quat(S)
        xb = x[b].copy()
        xb[0:3] = S @ x[b, 0:3]
        xb[3:7] = rot.quat_multiply(qS, x[b, 3:7])
        xb[7:9] = Dk @ x[b, 7:9]
        xb[9:] = (x[b, 9:].reshape(-1, 3) @ S.T).ravel()
        d = P.shape[-1]
        G = np.zeros((d, d))
        G[0:3, 0:3] = S
        if additive:
            Lq = rot.quat_multiply(qS, np.eye(4))  # q' = qS (x) q, linear in q: (4 j, 4)
            G[3:7, 3:7] = Lq.T
            o = 7
        else:
            G[3:6, 3:6] = S
            o = 6
        G[o : o + 2, o : o + 2] = Dk
        nf = (d - o - 2) // 3
        for i in range(nf):
            a = o + 2 + 3 * i
            G[a : a + 3, a : a + 3] = S
        x = x.copy()
        P = P.copy()
        x[b] = xb
        P[b] = G @ P[b] @ G.T
    return x, P


# Once ukf-mult's attitude is lost (1-sigma beyond ~100 deg) its rotation-vector sigma points
# wrap around and the weighted means stop meaning anything (the rate diverged to 1e5 deg/s
# through Kabir's long occlusions): the attitude block is held at that size, its
# correlations scaled alike (tumblenav default).
_MAX_ATTITUDE_SIGMA = np.radians(100.0)


def _cap_attitude(P: Array) -> Array:
    lam = np.linalg.eigvalsh(P[:, 3:6, 3:6])[:, -1]
    over = lam > _MAX_ATTITUDE_SIGMA**2
    if not over.any():
        return P
    P = P.copy()
    for b in np.flatnonzero(over):
        s = np.ones(P.shape[-1])
        s[3:6] = _MAX_ATTITUDE_SIGMA / np.sqrt(lam[b])
        P[b] = P[b] * np.outer(s, s)
    return P
