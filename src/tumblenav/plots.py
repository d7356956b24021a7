"""Figures (PNG) for truth, measurements and estimates; matplotlib with the Agg backend.

Every figure names a quantity through one mapping, :data:`LABELS` (read through
:func:`quantity_label`), so that ``attitude_deg`` reads "attitude error [deg]" on every axis.
Figures of estimates shade what a GNC engineer reads them by: the steady-state window,
occlusions the caller knows of (a scenario's schedule, :func:`occlusion_windows`) and spans
without any measurement update (found in the history's ``nis_dof``, :func:`no_update_spans`).
Each ``plot_*`` function that shows estimates has a ``*_figure`` twin that returns the open
figure instead of saving it, so that tests and notebooks can look at what is drawn.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from matplotlib.ticker import NullFormatter  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from tumblenav.evaluation import metrics  # noqa: E402
from tumblenav.io import atomic_write  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.typing import ColorType

Array = NDArray[np.float64]
Span = tuple[float, float]

LABELS: dict[str, str] = {
    "attitude_deg": "attitude error [deg]",
    "rate_deg_s": "rate error [deg/s]",
    "position_m": "position error [m]",
    "velocity_m_s": "velocity error [m/s]",
    "inertia": "inertia-ratio error [-]",
    "features_m": "features RMS error [m]",
    "offset_m": "mass-centre offset error [m]",
    "dpacf_attitude_deg": "DPACF attitude error [deg]",
}
"""Axis label of each error quantity (the keys of ``summary.json`` ``rmse``)."""

# unit suffixes of quantity keys (degrees named so, design.md), longest first
_UNITS = (
    ("_deg_s", "deg/s"),
    ("_rad_s", "rad/s"),
    ("_m_s", "m/s"),
    ("_deg", "deg"),
    ("_rad", "rad"),
    ("_m", "m"),
    ("_s", "s"),
)
_OCCLUSION: dict[str, Any] = {
    "facecolor": "none",
    "edgecolor": "tab:red",
    "hatch": "///",
    "alpha": 0.25,
    "lw": 0,
}
_NO_UPDATE: dict[str, Any] = {"facecolor": "0.5", "alpha": 0.18, "lw": 0}
_WINDOW: dict[str, Any] = {"facecolor": "tab:blue", "alpha": 0.08, "lw": 0}
_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def quantity_label(key: str) -> str:
    """Axis label with units for an error-quantity key (``attitude_deg`` -> "attitude error
    [deg]").

    Keys missing from :data:`LABELS` name their unit by suffix (``_m``, ``_deg_s``, ...) or
    are read as dimensionless; a string that already reads as a label (it has a space or a
    bracket) is returned unchanged.
    """
    if key in LABELS:
        return LABELS[key]
    if any(c in key for c in " [("):
        return key
    for suffix, unit in _UNITS:
        if key.endswith(suffix) and len(key) > len(suffix):
            return f"{key[: -len(suffix)].replace('_', ' ')} error [{unit}]"
    return f"{key.replace('_', ' ')} error [-]"


def quantity_unit(key: str) -> str:
    """The unit of a quantity key or label as its axis label names it (``"-"`` if none)."""
    label = quantity_label(key)
    if "[" in label and label.rstrip().endswith("]"):
        return label[label.rindex("[") + 1 : label.rindex("]")]
    return "-"


def save(fig: plt.Figure, path: str | Path) -> Path:
    """Save a figure atomically and close it."""
    path = Path(path)

    def _write(tmp: Path) -> None:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")

    out = atomic_write(path, _write)
    plt.close(fig)
    return out


# ---------------------------------------------------------------------------------------------
# series, spans and limits (pure functions)


def finite_series(t: Array, y: Array, gap_factor: float = 3.0) -> tuple[Array, Array]:
    """The finite samples of ``y(t)``, ready for ``plot``.

    NaN samples are dropped, so a curve stored at 1 Hz with NaN in between (a campaign's NEES)
    is drawn through its samples; where two finite samples lie more than ``gap_factor`` typical
    spacings apart a NaN is inserted, so that a long hole is left open, not bridged.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = np.isfinite(t) & np.isfinite(y)
    tt, yy = t[ok], y[ok]
    if len(tt) < 3:
        return tt, yy
    dt = np.diff(tt)
    cut = np.flatnonzero(dt > gap_factor * np.median(dt)) + 1
    if len(cut) == 0:
        return tt, yy
    return np.insert(tt, cut, 0.5 * (tt[cut - 1] + tt[cut])), np.insert(yy, cut, np.nan)


def no_update_spans(
    t: Array, nis_dof: Array, active: NDArray[np.bool_] | None = None, min_samples: int = 3
) -> list[Span]:
    """Spans without a measurement update (``nis_dof == 0``) while an estimate exists.

    A span counts when it lasts at least ``max(min_samples, 3 typical update intervals)``
    samples, so an estimator that updates every k-th epoch is not shaded everywhere; it runs
    from its first sample without update to the next update (or the last sample), s.
    """
    t = np.asarray(t, dtype=float)
    updated = np.nan_to_num(np.asarray(nis_dof, dtype=float)) > 0
    act = np.ones(len(t), dtype=bool) if active is None else np.asarray(active, dtype=bool)
    idx = np.flatnonzero(updated)
    typical = float(np.median(np.diff(idx))) if len(idx) > 1 else 1.0
    need = max(min_samples, int(np.ceil(3 * typical)))
    gap = (~updated & act).astype(np.int8)
    edges = np.flatnonzero(np.diff(np.r_[0, gap, 0]))
    spans = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):  # samples a .. b-1
        if b - a >= need:
            spans.append((float(t[a]), float(t[b] if b < len(t) else t[b - 1])))
    return spans


def occlusion_windows(scenario: Any) -> list[Span]:
    """A scenario's scheduled occlusions (``occlusion.windows`` and the loss of all features
    from ``occlusion.loss_from_s`` to the end), s."""
    occ = scenario.occlusion
    spans = [(float(w.start_s), float(w.end_s)) for w in occ.windows]
    if occ.loss_from_s is not None:
        spans.append((float(occ.loss_from_s), float(scenario.duration_s)))
    return spans


def in_spans(t: Array, spans: Sequence[Span]) -> NDArray[np.bool_]:
    """Which times lie in any of the spans (ends included)."""
    t = np.asarray(t, dtype=float)
    out = np.zeros(len(t), dtype=bool)
    for a, b in spans:
        out |= (t >= a) & (t <= b)
    return out


def settled_mask(
    t: Array,
    active: NDArray[np.bool_],
    window: Span | None = None,
    exclude: Sequence[Span] = (),
    transient: float = 0.2,
) -> NDArray[np.bool_]:
    """The samples that set a figure's y-limits: the window if given, otherwise the estimate
    after its first ``transient`` fraction; without the ``exclude`` spans (occlusions, spans
    without updates) unless that leaves less than a quarter of them, in which case the spans
    are the steady state (an estimator that mostly propagates) and are kept."""
    t = np.asarray(t, dtype=float)
    if not active.any():
        return active.copy()
    if window is not None:
        base = active & metrics.window_mask(t, window)
    else:
        ta = t[active]
        base = active & (t >= ta[0] + transient * (ta[-1] - ta[0]))
    if base.sum() < 5:
        base = active.copy()
    keep = base & ~in_spans(t, exclude)
    return keep if keep.sum() >= max(5, 0.25 * base.sum()) else base


def robust_limit(a: Array, mask: NDArray[np.bool_], q: float = 95.0, margin: float = 1.25) -> float:
    """``margin`` times the largest per-column ``q``-th percentile of ``a`` (n, k) >= 0 over the
    rows in ``mask``: a limit set by the steady state, not by its worst moments."""
    a = np.atleast_2d(np.asarray(a, dtype=float).T).T
    rows = a[mask] if mask.any() else a
    with np.errstate(all="ignore"):
        cols = [np.percentile(c[np.isfinite(c)], q) for c in rows.T if np.isfinite(c).any()]
    lim = margin * max(cols) if cols else 0.0
    if not (np.isfinite(lim) and lim > 0):
        finite = np.abs(a[np.isfinite(a)])
        lim = float(finite.max()) if len(finite) and finite.max() > 0 else 1.0
    return float(lim)


def _log_limits(values: Array, settled: Array, decades: float = 6.0) -> Span:
    """Log-axis limits: bottom from the low end (0.5th percentile) of the settled values, so a
    start transient that begins near zero does not stretch the axis; top from the largest
    value but at most ``decades`` above the bottom."""
    v = np.asarray(values, dtype=float)
    pos = v[np.isfinite(v) & (v > 0)]
    if len(pos) == 0:
        return (1e-3, 1.0)
    s = np.asarray(settled, dtype=float)
    s = s[np.isfinite(s) & (s > 0)]
    lo = 0.6 * float(np.percentile(s if len(s) else pos, 0.5))
    hi = 1.6 * float(pos.max())
    hi = min(hi, lo * 10**decades)
    if not hi > lo:
        hi = 10 * lo
    return (lo, hi)


def _off_scale_note(t: Array, e: Array, s3: Array, lim: float, unit: str) -> str:
    """Says what leaves the y-range: the largest |error| and 3 sigma and when."""
    parts = []
    for name, v in (("|error|", np.abs(e)), ("3σ", s3)):
        v = np.where(np.isfinite(v), v, -np.inf)
        if v.size and v.max() > lim:
            k = np.unravel_index(np.argmax(v), v.shape)[0]
            parts.append(f"{name} up to {v.max():.3g}{unit} at {t[k]:.4g} s")
    return "off scale: " + "; ".join(parts) if parts else ""


def _log_axis(ax: plt.Axes, ylim: Span | None) -> None:
    """Log y-axis with limits; minor ticks unlabelled when it spans more than two decades."""
    ax.set_yscale("log")
    if ylim is None:
        return
    ax.set_ylim(*ylim)
    if ylim[1] > 100 * ylim[0]:
        ax.yaxis.set_minor_formatter(NullFormatter())


def _note(ax: plt.Axes, note: str, fontsize: float) -> None:
    """Write what leaves the axis range in its upper-left corner."""
    if note:
        ax.text(
            0.01,
            0.97,
            "↕ " + note,
            transform=ax.transAxes,
            va="top",
            fontsize=fontsize,
            color="tab:red",
            bbox={"facecolor": "white", "alpha": 0.8, "lw": 0},
        )


def _shade(ax: plt.Axes, occlusions: Sequence[Span], no_update: Sequence[Span]) -> None:
    for a, b in no_update:
        ax.axvspan(a, b, zorder=0, **_NO_UPDATE)
    for a, b in occlusions:
        ax.axvspan(a, b, zorder=0, **_OCCLUSION)


def _shading_handles(occlusions: Sequence[Span], no_update: Sequence[Span]) -> list[Patch]:
    out = []
    if occlusions:
        out.append(Patch(label="occlusion (scheduled)", **_OCCLUSION))
    if no_update:
        out.append(Patch(label="no measurement update", **_NO_UPDATE))
    return out


# ---------------------------------------------------------------------------------------------
# truth and measurements


def plot_truth(truth, path: str | Path, title: str = "") -> Path:
    """Rate, relative position and velocity of the truth."""
    t = truth.t
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    labels = ("x", "y", "z")
    for k in range(3):
        axes[0].plot(t, np.degrees(truth.omega_TI_T[:, k]), label=rf"$\omega_{labels[k]}$")
        axes[1].plot(t, truth.r_L[:, k], label=f"{labels[k]}$_L$")
        axes[2].plot(t, truth.v_L[:, k], label=f"{labels[k]}$_L$")
    axes[0].set_ylabel("rate of T in T [deg/s]")
    axes[1].set_ylabel("position in L [m]")
    axes[2].set_ylabel("velocity in L [m/s]")
    axes[2].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8, ncol=3)
    fig.suptitle(title or "truth")
    return save(fig, path)


def plot_image_pair(meas, path: str | Path, title: str = "") -> Path:
    """The stereo image pairs at the start, the middle and the end of a run (8-bit, as the
    cameras gave them), left beside right."""
    n = len(meas.t)
    ks = sorted({0, n // 2, n - 1})
    fig, axes = plt.subplots(len(ks), 2, figsize=(10, 4.6 * len(ks)), squeeze=False)
    for row, k in enumerate(ks):
        pair = meas.source.pair(k)
        for cam, name in enumerate(("left", "right")):
            ax = axes[row, cam]
            img = pair[cam]
            h, w = img.shape
            # pixel (i, j) covers [i, i+1) x [j, j+1) in tumblenav's (u, v); v grows along the
            # camera's z axis, up the scene: drawn upwards, the view is the scene's
            ax.imshow(img, cmap="gray", vmin=0, vmax=255, origin="lower", extent=(0, w, 0, h))
            ax.set_title(f"{name} camera, t = {meas.t[k]:.1f} s", fontsize=9)
            ax.set_xlabel("u [px]")
            ax.set_ylabel("v [px]")
    fig.suptitle(title or "stereo images")
    return save(fig, path)


def plot_measurements(meas, path: str | Path, title: str = "") -> Path:
    """Feature tracks in the left and right images, and per-feature visibility over time."""
    fig = plt.figure(figsize=(11, 8))
    gs = fig.add_gridspec(2, 2, height_ratios=[3, 1.3])
    n_feat = meas.uv.shape[2]
    cmap = plt.get_cmap("tab10" if n_feat <= 10 else "viridis")
    for cam, name in enumerate(("left", "right")):
        ax = fig.add_subplot(gs[0, cam])
        w, h = getattr(meas.rig, name).resolution_px
        for j in range(n_feat):
            ax.plot(
                meas.uv[:, cam, j, 0], meas.uv[:, cam, j, 1], ".", ms=1.5, color=cmap(j % cmap.N)
            )
        ax.set_xlim(0, w)
        ax.set_ylim(0, h)
        ax.set_aspect("equal")
        ax.set_title(f"{name} image (u, v) [px]")
    ax = fig.add_subplot(gs[1, :])
    both = meas.observed.all(axis=1)
    ax.imshow(
        both.T,
        aspect="auto",
        interpolation="nearest",
        cmap="Greens",
        extent=(meas.t[0], meas.t[-1], n_feat - 0.5, -0.5),
    )
    ax.set_xlabel("time [s]")
    ax.set_ylabel("feature")
    ax.set_title("seen by both cameras (green)")
    fig.suptitle(title or "stereo measurements")
    return save(fig, path)


# ---------------------------------------------------------------------------------------------
# errors of one run


@dataclass(frozen=True)
class ErrorPanel:
    """What one block of the state layout shows in ``errors.png``, in display units.

    ``error`` / ``sigma3`` (n, k): signed error components and their 3 sigma, or for
    ``features`` the RMS over the features per axis (``signed`` False); ``magnitude`` /
    ``magnitude_sigma3`` (n,): the block's error norm (RMS over features) as in ``summary.json``
    and ``3 sqrt(tr P_block)`` (``3 sqrt(tr P / N)``); ``ylim`` / ``log_ylim``: the limits of the
    linear and the log panel; ``notes``: what leaves them.
    """

    name: str
    label: str
    components: tuple[str, ...]
    error: Array
    sigma3: Array
    signed: bool
    magnitude: Array
    magnitude_sigma3: Array
    ylim: Span
    log_ylim: Span
    notes: tuple[str, str]


def _block_key(lay, name: str) -> tuple[str, float]:
    if name in metrics.QUANTITIES:
        return metrics.QUANTITIES[name]
    if lay.block(name).kind == "quat":
        return f"{name}_deg", float(np.degrees(1.0))
    return name, 1.0


def error_panels(
    history,
    x_true: Array,
    *,
    occlusions: Sequence[Span] = (),
    window: Span | None = None,
) -> list[ErrorPanel]:
    """One :class:`ErrorPanel` per block of ``history.layout`` (every block, in layout order).

    Y-limits come from the steady state (see :func:`settled_mask`: ``window`` if given, else
    after the first fifth of the estimate; without occlusions and spans without updates) as
    1.25 times the 95th percentile of ``max(|error|, 3 sigma)``: the band and the error both
    fit, and a blow-up in an occlusion or the start transient is clipped and said so in
    ``notes`` instead of flattening the steady state.
    """
    lay = history.layout
    t = np.asarray(history.t, dtype=float)
    dx = lay.boxminus(x_true, history.x)
    sig = np.sqrt(np.maximum(np.diagonal(history.P, axis1=1, axis2=2), 0.0))
    active = np.all(np.isfinite(dx), axis=1)
    no_upd = no_update_spans(t, history.nis_dof, active)
    settled = settled_mask(t, active, window, [*occlusions, *no_upd])
    panels = []
    for b in lay.blocks:
        key, scale = _block_key(lay, b.name)
        label = quantity_label(key)
        e = scale * dx[:, lay.err(b.name)]
        s3 = 3.0 * scale * sig[:, lay.err(b.name)]
        if b.name == "features" and b.size % 3 == 0:
            e3, s33 = e.reshape(len(t), -1, 3), s3.reshape(len(t), -1, 3)
            comp, comp_s = np.sqrt(np.mean(e3**2, axis=1)), np.sqrt(np.mean(s33**2, axis=1))
            mag = np.sqrt(np.mean(np.sum(e3**2, axis=-1), axis=1))
            mag_s = np.sqrt(np.mean(np.sum(s33**2, axis=-1), axis=1))
            names: tuple[str, ...] = ("x", "y", "z")
            signed = False
            label = f"{label}\n(over {e3.shape[1]} features)"
        else:
            comp, comp_s = e, s3
            mag, mag_s = np.linalg.norm(e, axis=1), np.sqrt(np.sum(s3**2, axis=1))
            xyz = b.size == 3 and b.name != "inertia"
            names = ("x", "y", "z") if xyz else tuple(f"#{i + 1}" for i in range(b.size))
            signed = True
        lim = robust_limit(np.fmax(np.abs(comp), comp_s), settled)
        unit = "" if quantity_unit(key) == "-" else f" {quantity_unit(key)}"
        note = _off_scale_note(t[active], comp[active], comp_s[active], lim, unit)
        both = np.concatenate([mag[active], mag_s[active]])
        settled_both = np.concatenate([mag[settled], mag_s[settled]])
        log_lim = _log_limits(both, settled_both)
        log_note = ""
        if len(both) and np.nanmax(np.where(np.isfinite(both), both, -np.inf)) > log_lim[1]:
            log_note = f"off scale: up to {np.nanmax(both[np.isfinite(both)]):.3g}"
        panels.append(
            ErrorPanel(
                name=b.name,
                label=label,
                components=names,
                error=comp,
                sigma3=comp_s,
                signed=signed,
                magnitude=mag,
                magnitude_sigma3=mag_s,
                ylim=(-lim, lim) if signed else (0.0, lim),
                log_ylim=log_lim,
                notes=(note, log_note),
            )
        )
    return panels


def error_history_figure(
    history,
    x_true: Array,
    title: str = "",
    *,
    occlusions: Sequence[Span] = (),
    window: Span | None = None,
) -> plt.Figure:
    """The figure of :func:`plot_error_history`, open (axes carry gids ``<block>:components``
    and ``<block>:magnitude``)."""
    t = np.asarray(history.t, dtype=float)
    panels = error_panels(history, x_true, occlusions=occlusions, window=window)
    dx_ok = np.all(np.isfinite(history.layout.boxminus(x_true, history.x)), axis=1)
    no_upd = no_update_spans(t, history.nis_dof, dx_ok)
    # an occlusion the caller names is shaded as such, not again as a span without updates
    no_upd = [s for s in no_upd if not in_spans(np.array([0.5 * (s[0] + s[1])]), occlusions)[0]]
    n = len(panels)
    fig, axes = plt.subplots(
        n,
        2,
        figsize=(13, 1.9 * n + 1.4),
        sharex=True,
        squeeze=False,
        gridspec_kw={"width_ratios": [2.2, 1]},
        layout="constrained",
    )
    for (axl, axr), p in zip(axes, panels, strict=True):
        axl.set_gid(f"{p.name}:components")
        axr.set_gid(f"{p.name}:magnitude")
        for j, c in enumerate(p.components):
            col = _COLORS[j % len(_COLORS)]
            axl.plot(t, p.error[:, j], color=col, lw=0.8, label=c)
            axl.plot(t, p.sigma3[:, j], color=col, lw=0.7, ls="--")
            if p.signed:
                axl.plot(t, -p.sigma3[:, j], color=col, lw=0.7, ls="--")
        axr.plot(t, p.magnitude, color="k", lw=0.8)
        axr.plot(t, p.magnitude_sigma3, color="0.35", lw=0.8, ls="--")
        axl.set_ylim(*p.ylim)
        _log_axis(axr, p.log_ylim)
        axl.set_ylabel(p.label, fontsize=8)
        for ax, note in ((axl, p.notes[0]), (axr, p.notes[1])):
            _shade(ax, occlusions, no_upd)
            ax.grid(alpha=0.3, which="both" if ax is axr else "major")
            ax.tick_params(labelsize=7)
            _note(ax, note, 6.5)
        if p.components != ("x", "y", "z"):
            axl.legend(loc="upper right", fontsize=6, ncol=len(p.components), framealpha=0.7)
    axes[0, 0].set_title(
        "components: error (solid) within ±3σ (dashed)"
        if all(p.signed for p in panels)
        else "components: error (solid), 3σ (dashed); features: RMS over features per axis",
        fontsize=8,
    )
    axes[0, 1].set_title("magnitude, log scale: |error| (solid), 3√(tr P) (dashed)", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("time [s]")
    sub = ""
    if dx_ok.any():
        t_on = t[dx_ok]
        axes[0, 0].set_xlim(t_on[0], t_on[-1])
        if t_on[0] > t[0]:
            sub = f"\nestimate from t = {t_on[0]:.4g} s"
    else:
        sub = "\nno estimate in this run (the estimator never started)"
    handles: list[Artist] = [
        Line2D([], [], color=c, lw=1.2, label=a)
        for c, a in zip(_COLORS, ("x", "y", "z"), strict=False)
    ]
    handles += [
        Line2D([], [], color="k", lw=0.8, label="error"),
        Line2D([], [], color="k", lw=0.8, ls="--", label="3σ of the filter"),
        *_shading_handles(occlusions, no_upd),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8)
    fig.suptitle((title or "estimation errors") + sub, fontsize=11)
    return fig


def plot_error_history(
    history,
    x_true: Array,
    path: str | Path,
    title: str = "",
    *,
    occlusions: Sequence[Span] = (),
    window: Span | None = None,
) -> Path:
    """Errors of one run against the filter's 3 sigma: one row per block of the layout.

    Left, the components (signed error within ±3σ; for ``features`` the RMS over the features
    per axis) on a linear axis whose limits follow the steady state (:func:`error_panels`);
    right, the block's error magnitude against ``3 sqrt(tr P)`` on a log axis. The two columns
    answer the two questions a GNC engineer asks: is the error inside its bound, component by
    component (linear, where a sign or a bias shows), and by how much, when the 3σ is ten
    times the error (a conservative inertia or feature covariance) or an occlusion grows both
    by decades (log, where both stay readable). Occlusions the caller names (``occlusions``,
    s; e.g. :func:`occlusion_windows`) are hatched, spans without measurement updates found
    in ``history.nis_dof`` are shaded grey; ``window`` (s), if given, sets the limits.
    """
    return save(
        error_history_figure(history, x_true, title, occlusions=occlusions, window=window), path
    )


# ---------------------------------------------------------------------------------------------
# campaigns


def _draw_curve(ax: plt.Axes, t: Array, y: Array, **kw) -> list[Line2D]:
    tt, yy = finite_series(t, y)
    sparse = np.isfinite(yy).sum() < 400
    return ax.plot(tt, yy, marker="." if sparse else None, ms=2.5, **kw)


def rmse_figure(
    curves: Mapping[str, tuple[Array, Array]],
    ylabel: str,
    title: str = "",
    log: bool = True,
    window: Span | None = None,
    occlusions: Sequence[Span] = (),
) -> plt.Figure:
    """The figure of :func:`plot_rmse`, open."""
    fig, ax = plt.subplots(figsize=(8.5, 4.2), layout="constrained")
    colors: dict[str, ColorType] = {}
    values, settled = [], []
    for label, (t, y) in curves.items():
        base = label.rsplit(" ", 1)[0] if label.endswith((" RMSE", " median")) else label
        style = "--" if label.endswith(" median") else "-"
        line = _draw_curve(ax, t, y, lw=1.0, ls=style, label=label, color=colors.get(base))
        colors.setdefault(base, line[0].get_color())
        y = np.asarray(y, dtype=float)
        values.append(y)
        t = np.asarray(t, dtype=float)
        on = np.isfinite(y)
        settled.append(y[settled_mask(t, on, exclude=occlusions)])
    v, s = np.concatenate(values or [np.zeros(0)]), np.concatenate(settled or [np.zeros(0)])
    note = ""
    if log:
        lo, hi = _log_limits(v, s)
        if np.isfinite(v).any() and np.nanmax(v) > hi:
            note = f"off scale: up to {np.nanmax(v):.3g}"
    else:
        lo, hi = 0.0, robust_limit(s[:, None], np.ones(len(s), dtype=bool), q=99, margin=1.2)
        if np.isfinite(v).any() and np.nanmax(v) > hi:
            note = f"off scale: up to {np.nanmax(v):.3g}"
    if log:
        _log_axis(ax, (lo, hi))
    elif np.isfinite(v).any():
        ax.set_ylim(lo, hi)
    _note(ax, note, 7)
    if window:
        ax.axvspan(*window, zorder=0, label="steady-state window", **_WINDOW)
    _shade(ax, occlusions, ())
    handles, _ = ax.get_legend_handles_labels()
    ax.set_xlabel("time [s]")
    ax.set_ylabel(quantity_label(ylabel))
    ax.grid(alpha=0.3, which="both")
    ax.legend(handles=handles + _shading_handles(occlusions, ()), fontsize=7)
    ax.set_title(title, fontsize=9)
    return fig


def plot_rmse(
    curves: Mapping[str, tuple[Array, Array]],
    ylabel: str,
    path: str | Path,
    title: str = "",
    log: bool = True,
    window: Span | None = None,
    occlusions: Sequence[Span] = (),
) -> Path:
    """Monte Carlo RMSE over runs vs time (Hu 2024 eq. 45) for several cases.

    A label ending in " median" is drawn dashed in the colour of its " RMSE" companion.
    ``ylabel`` is a quantity key (``attitude_deg``) or a label (:func:`quantity_label`).
    NaN samples are skipped (:func:`finite_series`); the y-limits follow the settled part (log:
    at most six decades above its low end), the steady-state ``window`` (s) is shaded and the
    ``occlusions`` (s) hatched.
    """
    return save(rmse_figure(curves, ylabel, title, log, window, occlusions), path)


@dataclass(frozen=True)
class ConsistencyPanel:
    """One panel of a consistency figure: curves (label -> (n,) run-averaged value / dof, NaN
    where none) and their two-sided 95% chi-square bounds."""

    ylabel: str
    curves: Mapping[str, Array]
    bounds: Span | None = None


def consistency_figure(
    t: Array,
    panels: Sequence[ConsistencyPanel],
    title: str = "",
    *,
    window: Span | None = None,
    occlusions: Sequence[Span] = (),
) -> plt.Figure:
    """The figure of :func:`plot_consistency`, open."""
    t = np.asarray(t, dtype=float)
    fig, axes = plt.subplots(
        len(panels),
        1,
        figsize=(9, 3.3 * len(panels)),
        sharex=True,
        squeeze=False,
        layout="constrained",
    )
    for ax, p in zip(axes[:, 0], panels, strict=True):
        values, settled = [], []
        for label, v in p.curves.items():
            v = np.asarray(v, dtype=float)
            settled.append(v[settled_mask(t, np.isfinite(v), exclude=occlusions)])
            text = label
            if window is not None:
                w = metrics.window_mask(t, window) & np.isfinite(v)
                if w.any():
                    text += f" (mean {np.mean(v[w]):.3g} over {window[0]:g}-{window[1]:g} s)"
            _draw_curve(ax, t, v, lw=0.9, label=text)
            values.append(v)
        v = np.concatenate(values) if values else np.zeros(0)
        s = np.concatenate(settled) if settled else np.zeros(0)
        if p.bounds is not None:
            lo, hi = p.bounds
            ax.axhspan(lo, hi, color="tab:green", alpha=0.2, label=f"95% bounds {lo:.3g}-{hi:.3g}")
        ax.axhline(1.0, color="k", lw=0.5)
        pos = v[np.isfinite(v) & (v > 0)]
        lo_b, hi_b = p.bounds if p.bounds is not None else (1.0, 1.0)
        lo, hi = _log_limits(v, s)
        _log_axis(ax, (min(lo, 0.7 * lo_b), max(hi, 1.4 * hi_b)) if len(pos) else None)
        if not len(pos):
            ax.text(0.5, 0.5, "no values", transform=ax.transAxes, ha="center", color="0.4")
        if window:
            ax.axvspan(*window, zorder=0, label="steady-state window", **_WINDOW)
        _shade(ax, occlusions, ())
        handles, _ = ax.get_legend_handles_labels()
        ax.legend(handles=handles + _shading_handles(occlusions, ()), fontsize=7, loc="best")
        ax.set_ylabel(p.ylabel)
        ax.grid(alpha=0.3, which="both")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(title, fontsize=10)
    return fig


def plot_consistency(
    t: Array,
    values: Mapping[str, Array] | Sequence[ConsistencyPanel],
    bounds: Span | None,
    path: str | Path,
    title: str = "",
    *,
    window: Span | None = None,
    occlusions: Sequence[Span] = (),
) -> Path:
    """Run-averaged normalised NEES / NIS vs time with the 95% chi-square bounds, log scale.

    ``values``: label -> (n,) curve, drawn in one panel with ``bounds``; or a sequence of
    :class:`ConsistencyPanel` (then ``bounds`` is not used), one panel each.  Curves stored
    sparsely (NaN between samples) are drawn through their finite samples; the legend gives
    each curve's mean over the steady-state ``window`` (s), which is shaded.
    """
    if isinstance(values, Mapping):
        values = [ConsistencyPanel("run average / dof", values, bounds)]
    fig = consistency_figure(t, values, title, window=window, occlusions=occlusions)
    return save(fig, path)


def plot_depth(meas, path: str | Path, title: str = "") -> Path:
    """First point cloud seen from the sensor (x-z, coloured by range) and returns per scan."""
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5), gridspec_kw={"width_ratios": [1, 1.3]})
    k = int(np.argmax(meas.observed.any(axis=1))) if meas.observed.any() else 0
    p = meas.points[k][meas.observed[k]]
    if len(p):
        sc = ax0.scatter(p[:, 0], p[:, 2], c=p[:, 1], s=2, cmap="viridis")
        fig.colorbar(sc, ax=ax0, label="range along boresight y [m]")
    ax0.set_aspect("equal")
    ax0.set_xlabel("x_S [m]")
    ax0.set_ylabel("z_S [m]")
    ax0.set_title(f"point cloud at t = {meas.t[k]:g} s")
    fig.subplots_adjust(wspace=0.5)
    ax1.plot(meas.t, meas.observed.sum(axis=1), lw=1)
    ax1.set_xlabel("time [s]")
    ax1.set_ylabel("returns per scan")
    ax1.grid(alpha=0.3)
    fig.suptitle(title or "depth measurements")
    return save(fig, path)


def plot_axis_spread(
    t: Array,
    components: Mapping[str, Array],
    path: str | Path,
    title: str = "",
    window: Span | None = None,
    max_runs_drawn: int = 30,
) -> Path:
    """Per-axis errors of a campaign (Chang 2021 Figs. 17 and 19): every run thin, their mean
    and the mean +-3 standard deviations over runs, one row per quantity and one column per
    axis. ``components``: quantity key -> (runs, n, 3)."""
    keys = [
        k for k in ("attitude_deg", "rate_deg_s", "position_m", "velocity_m_s") if k in components
    ]
    fig, axes = plt.subplots(
        len(keys), 3, figsize=(12, 2.6 * max(len(keys), 1)), sharex=True, squeeze=False
    )
    t = np.asarray(t, dtype=float)
    for row, key in enumerate(keys):
        c = np.asarray(components[key], dtype=float)
        with warnings.catch_warnings():  # all-NaN epochs: before any run has an estimate
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(c, axis=0)
            std = np.nanstd(c, axis=0)
        for col, ax_name in enumerate("xyz"):
            ax = axes[row, col]
            for run in c[:max_runs_drawn, :, col]:
                ax.plot(t, run, color="0.7", lw=0.5)
            ax.plot(t, mean[:, col], color="C0", lw=1.2, label="mean over runs")
            ax.plot(
                t, mean[:, col] + 3 * std[:, col], "--", color="C3", lw=1, label="±3σ over runs"
            )
            ax.plot(t, mean[:, col] - 3 * std[:, col], "--", color="C3", lw=1)
            if window is not None:
                ax.axvspan(window[0], window[1], color="0.93", zorder=-1)
                w = (t >= window[0]) & (t <= window[1])
                span = np.nanmax(np.abs(c[:, w, col])) if np.isfinite(c[:, w, col]).any() else None
                if span:
                    ax.set_ylim(-1.3 * span, 1.3 * span)
            ax.grid(alpha=0.3)
            ax.set_title(f"{quantity_label(key)}, {ax_name}", fontsize=9)
            if row == len(keys) - 1:
                ax.set_xlabel("time [s]")
        axes[row, 0].legend(loc="upper right", fontsize=7)
    fig.suptitle(title or "errors per axis over runs")
    fig.tight_layout()
    return save(fig, path)


def plot_feature_counts(
    t: Array, counts: Mapping[str, Array], path: str | Path, title: str = ""
) -> Path:
    """Features over time in the image front end (held, tracked, matched, new, ...)."""
    fig, ax = plt.subplots(figsize=(10, 3.8))
    for label, v in counts.items():
        ax.plot(t, v, lw=1, label=label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("features")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8, ncol=3)
    ax.set_title(title or "features in the image front end")
    return save(fig, path)


def plot_tracked_frame(
    images: tuple[NDArray[np.uint8], NDArray[np.uint8]],
    uv: Array,
    tails: Array | None,
    path: str | Path,
    title: str = "",
    epilines: Array | None = None,
) -> Path:
    """One stereo frame with its features (Chang 2021 Figs. 14-15): the left image with each
    tracked feature and its track over the last frames (``tails``: (frames, 2... m, 2) left
    pixels, NaN where none), the right image with the matched features, the same colour per
    feature; ``epilines`` (m, 3) optional lines a u + b v + c = 0 in the right image."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.8))
    m = uv.shape[1]
    colours = plt.get_cmap("hsv")(np.linspace(0, 1, max(m, 1), endpoint=False))
    for cam, name in enumerate(("left", "right")):
        ax = axes[cam]
        img = images[cam]
        h, w = img.shape
        ax.imshow(img, cmap="gray", vmin=0, vmax=255, origin="lower", extent=(0, w, 0, h))
        ax.scatter(
            uv[cam, :, 0], uv[cam, :, 1], s=14, facecolors="none", edgecolors=colours, lw=0.8
        )
        if cam == 0 and tails is not None:
            for j in range(m):
                ax.plot(tails[:, j, 0], tails[:, j, 1], "-", color=colours[j], lw=0.8)
        if cam == 1 and epilines is not None:
            for j, (a, b, c) in enumerate(epilines[:12]):
                if abs(b) > 1e-12:
                    us = np.array([0.0, w])
                    ax.plot(us, -(a * us + c) / b, "-", color=colours[j], lw=0.5, alpha=0.7)
        ax.set_xlim(0, w)
        ax.set_ylim(0, h)  # v up the scene (see plot_image_pair)
        ax.set_xlabel("u [px]")
        ax.set_ylabel("v [px]")
        ax.set_title(f"{name}: {m} {'tracked' if cam == 0 else 'matched'} features", fontsize=9)
    fig.suptitle(title or "tracked and matched features")
    fig.tight_layout()
    return save(fig, path)


def plot_estimates(history, path: str | Path, title: str = "", max_features: int = 3) -> Path:
    """The estimates with their ±3σ bands, one panel per block (for runs without a truth: a
    user's own data). The attitude is drawn as the rotation vector of the estimate relative to
    its first value (deg), with the error state's 3σ; features: the first ``max_features``."""
    from tumblenav import rotations as rot

    lay = history.layout
    t = np.asarray(history.t, float)
    names = [b.name for b in lay.blocks]
    fig, axes = plt.subplots(
        len(names), 1, figsize=(11, 2.4 * len(names)), sharex=True, squeeze=False
    )
    started = np.isfinite(history.x).all(axis=1)
    for ax, b in zip(axes[:, 0], lay.blocks, strict=True):
        key, scale = metrics.QUANTITIES.get(b.name, (b.name, 1.0))  # summary units
        unit = next((u for suf, u in _UNITS if key.endswith(suf) and len(key) > len(suf)), "-")
        x = history.x[:, lay.nom(b.name)]
        sig = scale * history.sigma(b.name) if history.P_every == 1 else None
        if b.kind == "quat":
            first = x[np.argmax(started)] if started.any() else rot.IDENTITY
            x = rot.log_quat(rot.quat_multiply(x, rot.quat_conjugate(first)))
            label = f"{b.name} (rotation from its first estimate) [{unit}]"
        else:
            label = f"{b.name} [{unit}]"
        x = scale * x
        n = x.shape[1] if b.name != "features" else min(x.shape[1], 3 * max_features)
        for i in range(n):
            c = f"C{i % 3}" if b.name != "features" else f"C{i // 3}"
            ax.plot(t, x[:, i], color=c, lw=1, label="xyz"[i % 3] if i < 3 else None)
            if sig is not None:
                ax.fill_between(
                    t, x[:, i] - 3 * sig[:, i], x[:, i] + 3 * sig[:, i], color=c, alpha=0.15, lw=0
                )
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=8, ncol=3, title="shaded: ±3σ", title_fontsize=7)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(title or "estimates and ±3σ")
    fig.tight_layout()
    return save(fig, path)
