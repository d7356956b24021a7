"""Figures (PNG) for truth, measurements and estimates; matplotlib with the Agg backend."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tumblenav.io import _atomic  # noqa: E402


def save(fig: plt.Figure, path: str | Path) -> Path:
    """Save a figure atomically and close it."""
    path = Path(path)

    def _write(tmp: Path) -> None:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")

    out = _atomic(path, _write)
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
