"""Figures (PNG) for truth, measurements and estimates; matplotlib with the Agg backend."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tumblenav.io import atomic_write  # noqa: E402


def save(fig: plt.Figure, path: str | Path) -> Path:
    """Save a figure atomically and close it."""
    path = Path(path)

    def _write(tmp: Path) -> None:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")

    out = atomic_write(path, _write)
    plt.close(fig)
    return out


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


_PANELS = (
    ("attitude", "attitude error [deg]", np.degrees(1.0)),
    ("rate", "rate error [deg/s]", np.degrees(1.0)),
    ("inertia", "inertia-parameter error [-]", 1.0),
    ("position", "position error [m]", 1.0),
    ("velocity", "velocity error [m/s]", 1.0),
    ("features", "feature 1 error [m]", 1.0),
)


def plot_error_history(history, x_true, path: str | Path, title: str = "") -> Path:
    """Error components of one run with the filter's +-3 sigma bounds (one panel per block)."""
    lay = history.layout
    dx = lay.boxminus(x_true, history.x)
    sig = np.sqrt(np.maximum(np.diagonal(history.P, axis1=1, axis2=2), 0.0))
    names = [p for p in _PANELS if p[0] in lay.names()]
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 2.1 * len(names)), sharex=True)
    axes = np.atleast_1d(axes)
    colors = ("tab:blue", "tab:orange", "tab:green")
    for ax, (name, label, scale) in zip(axes, names, strict=True):
        s = lay.err(name)
        idx = range(s.start, s.start + 3)
        for c, i in zip(colors, idx, strict=True):
            ax.plot(history.t, scale * dx[:, i], color=c, lw=0.9, label="xyz"[i - s.start])
            ax.plot(history.t, 3 * scale * sig[:, i], color=c, lw=0.6, ls="--")
            ax.plot(history.t, -3 * scale * sig[:, i], color=c, lw=0.6, ls="--")
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
        lim = np.nanpercentile(np.abs(scale * dx[:, s]), 99) if np.isfinite(dx[:, s]).any() else 1
        ax.set_ylim(-2.5 * lim - 1e-12, 2.5 * lim + 1e-12)
    axes[0].legend(
        loc="upper right",
        fontsize=7,
        ncol=3,
        title="solid: error, dashed: +-3 sigma",
        title_fontsize=7,
    )
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title or "estimation errors")
    return save(fig, path)


def plot_rmse(
    curves: dict[str, tuple],
    ylabel: str,
    path: str | Path,
    title: str = "",
    log: bool = True,
    window: tuple[float, float] | None = None,
) -> Path:
    """Monte Carlo RMSE over runs vs time (Hu 2024 eq. 45) for several cases; a label ending
    in " median" is drawn dashed in the colour of its " RMSE" companion."""
    fig, ax = plt.subplots(figsize=(8, 4))
    colors: dict[str, str] = {}
    for label, (t, y) in curves.items():
        base = label.rsplit(" ", 1)[0] if label.endswith((" RMSE", " median")) else label
        style = "--" if label.endswith(" median") else "-"
        line = ax.plot(t, y, lw=1.0, ls=style, label=label, color=colors.get(base))
        colors.setdefault(base, line[0].get_color())
    if log:
        ax.set_yscale("log")
    if window:
        ax.axvspan(*window, color="0.9", zorder=0, label="steady-state window")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=9)
    return save(fig, path)


def plot_consistency(
    t, values: dict[str, np.ndarray], bounds: tuple[float, float], path: str | Path, title: str = ""
) -> Path:
    """Run-averaged normalised NEES / NIS vs time with the 95% chi-square band."""
    fig, ax = plt.subplots(figsize=(8, 4))
    for label, v in values.items():
        ax.plot(t, v, lw=0.9, label=label)
    ax.axhspan(bounds[0], bounds[1], color="tab:green", alpha=0.2, label="95% bounds")
    ax.axhline(1.0, color="k", lw=0.5)
    ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("average / dof")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(title)
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
