"""The one estimator interface, the state layout and the registry.

An estimator turns a run's measurements into an :class:`EstimateHistory`: the nominal state
and the error-state covariance at every measurement time, with a :class:`StateLayout` that
names the blocks, so that metrics, plots and files never index by magic numbers.

Inside, estimators are written as pure steps on frozen beliefs
(``predict(belief, dt) -> belief``, ``update(belief, z) -> belief``); the public entry point
is ``run(scenario, measurements, rng)``. An estimator may also offer
``run_batch(scenario, [measurements...], [rng...])`` that runs many Monte Carlo runs at once
(vectorised); the campaign runner uses it when present.

Standard block names (the metrics know them):

========== ====== ====== ===============================================================
name       nom.   err.   meaning
========== ====== ====== ===============================================================
attitude   4      3      q_TI [x,y,z,w]; error dtheta with q = exp(dtheta) (x) q_hat
rate       3      3      omega_TI_T (rad/s)
inertia    k      k      inertia parameters (estimator-specific parametrisation, e.g. Hu's p)
position   3      3      r_L (m): target mass centre relative to the chaser, in L
velocity   3      3      v_L (m/s)
features   3N     3N     feature points in T (m)
offset     3      3      mass-centre offset b (m), Yu 2019
========== ====== ====== ===============================================================
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel

from tumblenav import rotations as rot
from tumblenav.errors import InputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Block:
    name: str
    kind: Literal["quat", "vector"]
    size: int  # error-state size (3 for a quaternion)

    @property
    def nominal_size(self) -> int:
        return 4 if self.kind == "quat" else self.size


@dataclass(frozen=True)
class StateLayout:
    """Names, kinds and slices of the nominal state and of the error state."""

    blocks: tuple[Block, ...]

    @property
    def dim(self) -> int:
        return sum(b.size for b in self.blocks)

    @property
    def nominal_dim(self) -> int:
        return sum(b.nominal_size for b in self.blocks)

    def _offsets(self, nominal: bool) -> dict[str, slice]:
        out, i = {}, 0
        for b in self.blocks:
            n = b.nominal_size if nominal else b.size
            out[b.name] = slice(i, i + n)
            i += n
        return out

    def err(self, name: str) -> slice:
        """Slice of block ``name`` in the error state / covariance."""
        return self._offsets(False)[name]

    def nom(self, name: str) -> slice:
        """Slice of block ``name`` in the nominal state."""
        return self._offsets(True)[name]

    def names(self) -> list[str]:
        return [b.name for b in self.blocks]

    def block(self, name: str) -> Block:
        return next(b for b in self.blocks if b.name == name)

    def boxminus(self, x: Array, x_hat: Array) -> Array:
        """Error state ``x [-] x_hat`` (..., dim): quaternion blocks by the log of
        ``q (x) conj(q_hat)``, vector blocks by subtraction (Hu 2024 eq. 26-27)."""
        parts = []
        for b in self.blocks:
            s = self.nom(b.name)
            if b.kind == "quat":
                parts.append(rot.boxminus(x[..., s], x_hat[..., s]))
            else:
                parts.append(x[..., s] - x_hat[..., s])
        return np.concatenate(parts, axis=-1)

    def boxplus(self, x_hat: Array, dx: Array) -> Array:
        """Nominal state ``x_hat [+] dx`` (Hu 2024 eq. 43-44)."""
        parts = []
        for b in self.blocks:
            s, e = self.nom(b.name), self.err(b.name)
            if b.kind == "quat":
                parts.append(rot.boxplus(x_hat[..., s], dx[..., e]))
            else:
                parts.append(x_hat[..., s] + dx[..., e])
        return np.concatenate(parts, axis=-1)


@dataclass(frozen=True)
class Belief:
    """Mean (nominal state) and error-state covariance at time ``t``; immutable. ``memo``: what
    a filter carries from step to step besides the mean and covariance (a frozen record of the
    estimator's own, e.g. the half-turn votes of Hu 2024's DPACF branch), or None."""

    t: float
    x: Array
    P: Array
    layout: StateLayout
    memo: Any = None


@dataclass(frozen=True)
class StepInfo:
    """What a step reports besides the belief: the NIS and its degrees of freedom (NaN and 0
    without an update), measurements rejected by a gate, measurements skipped and why
    (``skipped``: reason -> count, summed by the fold), and whether the filter diverged (then
    the fold stops the run)."""

    nis: float = float("nan")
    dof: int = 0
    rejected: int = 0
    diverged: bool = False
    skipped: dict[str, int] = field(default_factory=dict)


class Steps(Protocol):
    """An estimator as stateless steps over one run's measurement stream (epochs ``t``):

    - ``initialise(k) -> (belief, StepInfo)``: the first belief, at epoch ``k``, or None
      while the start condition is not met (the fold asks again at the next epoch);
    - ``predict(belief, t) -> belief`` at time ``t``;
    - ``update(belief, k, started) -> (belief, StepInfo)`` with epoch ``k``'s measurement
      (``started``: the belief was initialised at this epoch);
    - ``report(belief, k) -> P``: the covariance to report (usually ``belief.P``).
    """

    @property
    def layout(self) -> StateLayout: ...  # read-only: the steps may be frozen dataclasses

    def initialise(self, k: int) -> tuple[Belief | None, StepInfo]: ...

    def predict(self, belief: Belief, t: float) -> Belief: ...

    def update(self, belief: Belief, k: int, started: bool) -> tuple[Belief, StepInfo]: ...

    def report(self, belief: Belief, k: int) -> Array: ...


@dataclass(frozen=True)
class FoldResult:
    """The history of one fold: ``x`` (n, nom), ``P`` (ceil(n / p_every), d, d), ``nis``,
    ``nis_dof`` (n,), the measurements rejected, whether the run was stopped as diverged, the
    last belief's ``memo`` and the skip counts of every step."""

    x: Array
    P: Array
    nis: Array
    nis_dof: Array
    rejected: int
    diverged: bool
    memo: Any
    skipped: dict[str, int] = field(default_factory=dict)


def fold(steps: Steps, t: Array, p_every: int = 1) -> FoldResult:
    """The one generic filter loop: start (once the estimator's start condition holds),
    then predict and update at every epoch; a run that diverges is stopped (NaN from then
    on, and counted). The covariance is reported every ``p_every`` epochs. Compiled engines
    are faster folds of the same steps, tested equal to this one."""
    lay = steps.layout
    n = len(t)
    x = np.full((n, lay.nominal_dim), np.nan)
    P = np.full((-(-n // p_every), lay.dim, lay.dim), np.nan)
    nis = np.full(n, np.nan)
    dof = np.zeros(n)
    rejected, diverged = 0, False
    belief: Belief | None = None
    memo = None
    skipped: dict[str, int] = {}

    def count(info: StepInfo) -> None:
        for reason, c in info.skipped.items():
            skipped[reason] = skipped.get(reason, 0) + c

    for k in range(n):
        started = False
        if belief is not None:
            belief = steps.predict(belief, float(t[k]))
        elif not diverged:
            belief, info = steps.initialise(k)
            count(info)
            started = belief is not None
        if belief is None:
            continue
        belief, info = steps.update(belief, k, started)
        count(info)
        memo = belief.memo
        if info.diverged:
            belief, diverged = None, True
            continue
        nis[k] = info.nis if info.dof > 0 else np.nan
        dof[k] = info.dof
        rejected += info.rejected
        x[k] = belief.x
        if k % p_every == 0:
            P[k // p_every] = steps.report(belief, k)
    return FoldResult(x, P, nis, dof, rejected, diverged, memo, skipped)


@dataclass
class EstimateHistory:
    """What one estimator run returns.

    t : (n,) s; x : (n, nominal_dim); P : (n, dim, dim) error-state covariance, or with
    ``P_every`` > 1 only that of every ``P_every``-th epoch, (ceil(n / P_every), dim, dim)
    (campaigns keep the covariance where the NEES is evaluated, not at every epoch).
    nis : (n,) normalised innovation squared of each update (NaN where no update);
    nis_dof : (n,) its degrees of freedom (0 where no update).
    skipped : counts of measurements skipped and why (NaN, one camera only, ...).
    info : estimator-specific extras; ``info["convention"]`` names the state convention the
    evaluation compares the truth in (:mod:`tumblenav.evaluation.alignment`: principal frame,
    symmetries, inertia parametrisation), e.g. the DPACF frame definition for ``hu2024``.
    """

    t: Array
    x: Array
    P: Array
    layout: StateLayout
    nis: Array
    nis_dof: Array
    skipped: dict[str, int] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)
    P_every: int = 1
    # (n, m) each update's innovation (NaN: not used), where an estimator reports its NIS
    # against another covariance than its own after the run (Kabir's covariance analysis);
    # None elsewhere, and dropped once used
    innovations: Array | None = None

    def block(self, name: str) -> Array:
        return self.x[:, self.layout.nom(name)]

    def sigma(self, name: str) -> Array:
        """1-sigma of block ``name`` (n, size): at every epoch (``P_every`` must be 1)."""
        if self.P_every != 1:
            raise ValueError("this history keeps the covariance every P_every epochs only")
        s = self.layout.err(name)
        return np.sqrt(np.maximum(np.diagonal(self.P[:, s, s], axis1=1, axis2=2), 0.0))


@runtime_checkable
class Estimator(Protocol):
    name: str
    consumes: tuple[str, ...]  # measurement types it runs on (tumblenav.measurements.KINDS)
    needs: str  # what it needs beyond that, in words, for `tumblenav estimators`
    description: str

    def check(self, scenario: Any) -> None:
        """Raise :class:`InputError` (one line: what the estimator needs and what the scenario
        has) if this estimator cannot run on ``scenario``; called before any work starts."""
        ...

    def run(
        self, scenario: Any, measurements: Any, rng: np.random.Generator
    ) -> EstimateHistory: ...


_REGISTRY: dict[str, Callable[[], Estimator]] = {}

# Estimators a built-in scenario names that do not exist yet: a plain word for the user instead
# of "unknown estimator".
PLANNED: dict[str, str] = {}


def register(name: str) -> Callable[[Callable[[], Estimator]], Callable[[], Estimator]]:
    def deco(factory: Callable[[], Estimator]) -> Callable[[], Estimator]:
        _REGISTRY[name] = factory
        return factory

    return deco


ENTRY_POINT_GROUP = "tumblenav.estimators"
_PLUGINS: dict[str, str] = {}  # estimator name -> the distribution that provides it
PLUGIN_ERRORS: dict[str, str] = {}  # entry point name -> why it could not be loaded


def _load_builtin() -> None:
    """Register the built-in estimators (importing their modules does it) and, once, the
    plugins: every entry point of group ``tumblenav.estimators`` (name: the estimator's name,
    value: ``module:factory``, a callable returning the estimator). A plugin that fails to
    import is left out and its error kept in :data:`PLUGIN_ERRORS` (``tumblenav estimators``
    shows it); a plugin never replaces a built-in estimator."""
    from tumblenav.estimators import chang2021, hu2024, kabir2025, yu2019  # noqa: F401

    if _PLUGINS or PLUGIN_ERRORS:
        return
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in _REGISTRY and ep.name not in _PLUGINS:
            PLUGIN_ERRORS[ep.name] = f"{ep.value}: the name of a built-in estimator"
            continue
        try:
            factory = ep.load()
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the tool
            PLUGIN_ERRORS[ep.name] = f"{ep.value}: {exc.__class__.__name__}: {exc}"
            continue
        _REGISTRY[ep.name] = factory
        _PLUGINS[ep.name] = ep.dist.name if ep.dist is not None else ep.value


def plugin_source(name: str) -> str | None:
    """The distribution that registered estimator ``name`` as a plugin, or None (built in)."""
    _load_builtin()
    return _PLUGINS.get(name)


def available() -> dict[str, Estimator]:
    _load_builtin()
    return {n: f() for n, f in sorted(_REGISTRY.items())}


def get(name: str) -> Estimator:
    _load_builtin()
    if name not in _REGISTRY and name in PLANNED:
        raise InputError(PLANNED[name])
    if name not in _REGISTRY:
        raise InputError(
            f"unknown estimator '{name}' (available: {', '.join(sorted(_REGISTRY))})", "--estimator"
        )
    return _REGISTRY[name]()


TuningT = TypeVar("TuningT", bound=BaseModel)


def parse_tuning(raw: dict[str, Any] | None, model: type[TuningT]) -> TuningT:
    """Validate ``scenario.estimator.tuning`` against an estimator's pydantic model; an
    InputError naming the key (``estimator.tuning.KEY: unknown key`` / the reason) otherwise."""
    from tumblenav.settings_rules import validate

    return validate(model, raw, "estimator.tuning")


def nest_front_end_keys(raw: Any, front_end: type[BaseModel], key: str = "frontend") -> Any:
    """A tuning model's ``mode="before"`` validator step: the front end's keys given at the
    top level of ``estimator.tuning`` (where they were before they moved into the front end's
    own settings) go under ``key``, so that existing scenario files keep working."""
    if not isinstance(raw, dict):
        return raw
    moved = {k: raw[k] for k in front_end.model_fields if k in raw}
    if not moved:
        return raw
    rest = {k: v for k, v in raw.items() if k not in moved}
    return {**rest, key: {**moved, **dict(raw.get(key) or {})}}


def check_names(names: Sequence[str]) -> None:
    for n in names:
        get(n)


def get_for(name: str, scenario: Any) -> Estimator:
    """The estimator ``name``, checked against ``scenario`` (:meth:`Estimator.check`): an
    :class:`InputError` before any work if it cannot run there."""
    from tumblenav.estimators.context import context_from_scenario
    from tumblenav.measurements import CONVERTS, kind_of, runs_on

    est = get(name)
    given = kind_of(scenario.sensor)
    consumes = tuple(getattr(est, "consumes", ()) or ())
    if consumes and not runs_on(consumes, given):
        raise InputError(
            f"{name} runs on {' or '.join(consumes)}; scenario {scenario.name}'s "
            f"{scenario.sensor.kind} sensor gives {given}"
        )
    if given in CONVERTS and given not in consumes:  # the front end's settings, before work
        from tumblenav.frontends.stages import image_frontend_tuning

        image_frontend_tuning(scenario.sensor.images.frontend)
    est.check(context_from_scenario(scenario))
    return est
