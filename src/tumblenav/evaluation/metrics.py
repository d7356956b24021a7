"""Errors against the truth, RMSE over time and over runs, NEES and NIS with chi-square bounds.

Part of :mod:`tumblenav.evaluation`, the stage after the estimator: no estimator imports it.

Quantities reported (summary.json keys): ``attitude_deg`` (rotation angle of
``q_true (x) conj(q_hat)``), ``rate_deg_s``, ``position_m``, ``velocity_m_s`` (Euclidean norms
of the error vectors), ``inertia`` (norm of the inertia-parameter error), ``features_m`` (RMS
over features of the feature position error norm), ``offset_m``.

RMSE over runs follows Hu 2024 eq. 45: ``RMSE(t) = sqrt(1/N sum_i e_i(t)^T e_i(t))``; the
summary number is the RMS of that curve over the steady-state window.
"""

from __future__ import annotations

import warnings
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from tumblenav import rotations as rot
from tumblenav.estimators.base import EstimateHistory

Array = NDArray[np.float64]

NOMINAL = "nominal"  # the branch of a run compared in its estimator's own frame

QUANTITIES = {
    "attitude": ("attitude_deg", np.degrees(1.0)),
    "rate": ("rate_deg_s", np.degrees(1.0)),
    "position": ("position_m", 1.0),
    "velocity": ("velocity_m_s", 1.0),
    "inertia": ("inertia", 1.0),
    "features": ("features_m", 1.0),
    "offset": ("offset_m", 1.0),
}


def attitude_error_rad(q_true: Array, q_hat: Array) -> Array:
    """Rotation angle (rad) between two attitude histories (..., 4)."""
    return rot.quat_angle(rot.quat_multiply(q_true, rot.quat_conjugate(q_hat)))


@dataclass(frozen=True)
class RunErrors:
    """Per-time error magnitudes of one run, in summary units (deg, deg/s, m, m/s)."""

    t: Array
    errors: dict[str, Array]  # key: summary name ('attitude_deg', ...) -> (n,)
    nees: Array  # (n,) full-state NEES
    nees_dof: int
    nis: Array  # (n,)
    nis_dof: Array  # (n,)
    # per-axis error components (n, 3) of the 3-vector quantities, in summary units (the
    # attitude's are the rotation-vector error's), for per-axis means and spreads
    components: dict[str, Array] = field(default_factory=dict)
    # the symmetric frame the truth was expressed in (evaluation.alignment.align): "nominal"
    # (the estimator's own frame) or a short name such as "x<->y (y,x,-z)"
    branch: str = NOMINAL


AXIS_QUANTITIES = ("attitude", "rate", "position", "velocity")


def error_components(dx: Array, lay) -> dict[str, Array]:
    """Per-axis error components (..., 3) of the 3-vector quantities in summary units."""
    out: dict[str, Array] = {}
    for b in lay.blocks:
        if b.name in AXIS_QUANTITIES and b.size == 3:
            key, scale = QUANTITIES[b.name]
            out[key] = scale * dx[..., lay.err(b.name)]
    return out


def axis_moments(r: RunErrors, window: tuple[float, float]) -> dict[str, float]:
    """Per-axis sums over the window of one run's error components, as scalars a campaign
    stores per run (``axis_<quantity>_<x|y|z>_{sum,sq,n}``): over runs they give each axis'
    mean and standard deviation (:func:`axis_statistics`)."""
    w = window_mask(r.t, window)
    out: dict[str, float] = {}
    for key, c in r.components.items():
        for i, ax in enumerate("xyz"):
            v = c[w, i]
            v = v[np.isfinite(v)]
            out[f"axis_{key}_{ax}_sum"] = float(v.sum())
            out[f"axis_{key}_{ax}_sq"] = float(np.sum(v**2))
            out[f"axis_{key}_{ax}_n"] = float(len(v))
    return out


def axis_statistics(extras: list[dict[str, float]]) -> dict[str, dict[str, list[float]]]:
    """Mean and standard deviation per axis over all runs and window epochs, from the runs'
    :func:`axis_moments`: ``{quantity: {"mean": [x, y, z], "std": [x, y, z]}}``."""
    keys = sorted(
        {k[5:-6] for e in extras for k in e if k.startswith("axis_") and k.endswith("_x_sum")}
    )
    out: dict[str, dict[str, list[float]]] = {}
    for key in keys:
        mean, std = [], []
        for ax in "xyz":
            n = sum(e.get(f"axis_{key}_{ax}_n", 0.0) for e in extras)
            s1 = sum(e.get(f"axis_{key}_{ax}_sum", 0.0) for e in extras)
            s2 = sum(e.get(f"axis_{key}_{ax}_sq", 0.0) for e in extras)
            m = s1 / n if n else float("nan")
            mean.append(m)
            std.append(float(np.sqrt(max(s2 / n - m * m, 0.0) * n / max(n - 1, 1))) if n else m)
        out[key] = {"mean": mean, "std": std}
    return out


def error_magnitudes(dx: Array, lay) -> dict[str, Array]:
    """Per-time error magnitudes in summary units from error states ``dx`` (..., dim)."""
    out: dict[str, Array] = {}
    for b in lay.blocks:
        if b.name not in QUANTITIES:
            continue
        key, scale = QUANTITIES[b.name]
        e = dx[..., lay.err(b.name)]
        if b.name == "features":
            e3 = e.reshape(e.shape[:-1] + (-1, 3))
            out[key] = scale * np.sqrt(np.mean(np.sum(e3**2, axis=-1), axis=-1))
        else:
            out[key] = scale * np.linalg.norm(e, axis=-1)
    return out


def run_errors(
    history: EstimateHistory, x_true: Array, nees_every: int = 1, branch: str = NOMINAL
) -> RunErrors:
    """Errors and NEES of one run; ``x_true`` is the truth in the estimator's state layout
    (in the symmetric frame ``branch``). The NEES is evaluated every ``nees_every`` epochs
    (NaN in between)."""
    lay = history.layout
    dx = lay.boxminus(x_true, history.x)  # (n, dim)
    e = np.full(len(dx), np.nan)
    if history.P_every > 1:  # the covariance is there every P_every epochs only
        e[:: history.P_every] = nees(dx[:: history.P_every], history.P)
    else:
        e[::nees_every] = nees(dx[::nees_every], history.P[::nees_every])
    return RunErrors(
        t=history.t,
        errors=error_magnitudes(dx, lay),
        nees=e,
        nees_dof=lay.dim,
        nis=history.nis,
        nis_dof=history.nis_dof,
        components=error_components(dx, lay),
        branch=branch,
    )


def nees(dx: Array, P: Array) -> Array:
    """Normalised estimation error squared ``dx^T P^-1 dx`` per row; NaN where undefined
    (a non-finite error or covariance, or a singular covariance)."""
    out = np.full(dx.shape[0], np.nan)
    ok = np.all(np.isfinite(dx), axis=-1) & np.all(np.isfinite(P), axis=(-1, -2))
    idx = np.flatnonzero(ok)
    if not len(idx):
        return out
    try:
        sol = np.linalg.solve(P[idx], dx[idx][..., None])[..., 0]
        out[idx] = np.sum(dx[idx] * sol, axis=-1)
    except np.linalg.LinAlgError:  # one singular covariance: row by row
        for k in idx:
            try:
                out[k] = dx[k] @ np.linalg.solve(P[k], dx[k])
            except np.linalg.LinAlgError:
                out[k] = np.nan
    return out


def window_mask(t: Array, window: tuple[float, float]) -> NDArray[np.bool_]:
    return (t >= window[0] - 1e-9) & (t <= window[1] + 1e-9)


def nanmean_quiet(a: Array, axis=None) -> Array:
    """``np.nanmean`` that quietly gives NaN for all-NaN slices (runs not started yet)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(a, axis=axis)


def nanmedian_quiet(a: Array, axis=None) -> Array:
    """``np.nanmedian`` that quietly gives NaN for all-NaN slices."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=axis)


def rmse_over_runs(errors: Array) -> Array:
    """Hu 2024 eq. 45: (runs, n) error magnitudes -> (n,) RMSE across runs (NaN-aware)."""
    return np.sqrt(nanmean_quiet(np.asarray(errors) ** 2, axis=0))


def rmse_over_time(err: Array, t: Array, window: tuple[float, float]) -> float:
    m = window_mask(t, window)
    return float(np.sqrt(nanmean_quiet(np.asarray(err)[..., m] ** 2)))


def chi2_bounds(dof: int, n_avg: int, p: float = 0.95) -> tuple[float, float]:
    """Two-sided ``p`` bounds of the *normalised* average of ``n_avg`` chi-square(dof) samples:
    ``chi2.ppf(a, n_avg dof) / (n_avg dof)`` (Bar-Shalom, Li, Kirubarajan 2001, Sec. 5.4)."""
    a = (1 - p) / 2
    k = n_avg * dof
    return float(stats.chi2.ppf(a, k) / k), float(stats.chi2.ppf(1 - a, k) / k)


def consistency(values: Array, dof: Array | int, t: Array, window: tuple[float, float]) -> dict:
    """NEES/NIS statistics over runs in a window, normalised by their degrees of freedom.

    ``values``: (runs, n); ``dof``: int or (runs, n) (NIS dof vary with visible features).
    Returns ``mean`` (time average in the window of the run-averaged normalised value),
    ``dof``, ``bounds95`` (for an average over the number of runs: Bar-Shalom's average NEES,
    ``R`` runs' sum is chi2(``R dof``) at each time; ``R`` the median over the window of the
    runs with a value), ``inside_fraction`` (fraction of window times whose run-average
    lies inside the bounds) and, only when there are any, ``negative_epochs``: the (run,
    time) values in the window below zero, which no positive semi-definite covariance gives
    (a defect of the estimator's reported covariance, not noise: the mean cannot be read).

    The bounds are exact for the run average at one time, hence for ``inside_fraction``. For
    ``mean``, a time average over correlated epochs, they are conservative: its own 95%
    range is narrower (by up to the square root of the number of independent epochs in the
    window), and equals them only when the errors are fully correlated over the window; so
    a ``mean`` outside them is inconsistent, one inside them may still be off by up to about
    the bounds' width.
    """
    v = np.atleast_2d(np.asarray(values, dtype=float))
    d = np.broadcast_to(np.asarray(dof, dtype=float), v.shape)
    m = window_mask(t, window)
    valid = np.isfinite(v) & (d > 0)
    norm = np.where(valid, v / np.where(d > 0, d, 1.0), np.nan)
    per_t = nanmean_quiet(norm[:, m], axis=0)
    dof_typ = int(np.round(np.nanmedian(np.where(valid, d, np.nan)))) if valid.any() else 0
    if dof_typ == 0 or not np.isfinite(per_t).any():
        return {"mean": None, "dof": dof_typ, "bounds95": None, "inside_fraction": None}
    # the run average at a time is over the runs that have a value then (runs not started,
    # stopped as diverged, or without an update are not in it): the bounds are for the
    # typical number of them in the window (all runs when every run has a value)
    counts = valid[:, m].sum(axis=0)
    runs = max(1, int(np.round(np.median(counts[np.isfinite(per_t)]))))
    lo, hi = chi2_bounds(dof_typ, runs)
    finite = per_t[np.isfinite(per_t)]
    out = {
        "mean": float(np.mean(finite)),
        "dof": dof_typ,
        "bounds95": [lo, hi],
        "inside_fraction": float(np.mean((finite >= lo) & (finite <= hi))),
    }
    negative = int(np.sum(norm[:, m] < 0.0))
    if negative:
        out["negative_epochs"] = negative
    return out


def branch_counts(branches: Iterable[str]) -> dict[str, int]:
    """Runs per branch (summary.json ``branches``): ``"nominal"`` first (0 if none), then
    the symmetric frames by decreasing count."""
    c = Counter(str(b) for b in branches)
    out = {NOMINAL: c.pop(NOMINAL, 0)}
    out.update(sorted(c.items(), key=lambda kv: (-kv[1], kv[0])))
    return out


def branch_warning(branches: dict[str, int] | None) -> str | None:
    """One warning line when any run is on a symmetric branch (``branches`` as
    :func:`branch_counts` gives it), else None."""
    if not branches:
        return None
    other = {k: int(v) for k, v in branches.items() if k != NOMINAL and v}
    if not other:
        return None
    k, n = sum(other.values()), sum(int(v) for v in branches.values())
    which = ", ".join(f"{name}: {v}" for name, v in other.items())
    run_s = "run" if n == 1 else "runs"
    return (
        f"{k} of {n} {run_s} converged to a symmetric equivalent of the truth ({which}): "
        "errors measured in that frame (the estimate describes the same motion with the "
        "axes relabelled or turned; see 'branches')"
    )
