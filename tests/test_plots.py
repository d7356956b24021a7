"""Figures: labels, y-limits, shading and sparse curves, checked on what matplotlib would draw.

Synthetic histories (seeded) stand in for estimator runs so that each test takes well under a
second; the figures are inspected open (``*_figure``), not saved, except for the campaign test.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from tumblenav import pipeline, plots
from tumblenav.estimators.base import Block, EstimateHistory, StateLayout
from tumblenav.evaluation import metrics

LAYOUT = StateLayout(
    (
        Block("attitude", "quat", 3),
        Block("rate", "vector", 3),
        Block("inertia", "vector", 3),
        Block("position", "vector", 3),
        Block("offset", "vector", 3),
        Block("features", "vector", 6),
    )
)


def _history(
    rng: np.random.Generator,
    sigma_e: float = 1e-3,
    ratio: float = 10.0,
    n: int = 400,
    blowup: tuple[int, int] | None = None,
    start: int = 20,
) -> tuple[EstimateHistory, np.ndarray]:
    """A 1 Hz history whose error is N(0, sigma_e) and whose filter sigma is ``ratio`` times
    that (a conservative covariance); during ``blowup`` (samples) no update happens and error
    and sigma grow a hundredfold. No estimate before ``start``."""
    lay = LAYOUT
    t = np.arange(n, dtype=float)
    x_true = np.zeros((n, lay.nominal_dim))
    x_true[:, lay.nom("attitude")] = [0.0, 0.0, 0.0, 1.0]
    grow = np.ones(n)
    if blowup is not None:
        grow[blowup[0] : blowup[1]] = 100.0
    dx = sigma_e * grow[:, None] * rng.standard_normal((n, lay.dim))
    x_hat = lay.boxplus(x_true, -dx)  # so that boxminus(x_true, x_hat) = dx
    P = np.zeros((n, lay.dim, lay.dim))
    P[:, np.arange(lay.dim), np.arange(lay.dim)] = (ratio * sigma_e * grow[:, None]) ** 2
    nis_dof = np.full(n, 6.0)
    if blowup is not None:
        nis_dof[blowup[0] : blowup[1]] = 0.0
    x_hat[:start], P[:start], nis_dof[:start] = np.nan, np.nan, 0.0
    nis = np.where(nis_dof > 0, nis_dof, np.nan)
    return EstimateHistory(t, x_hat, P, lay, nis, nis_dof), x_true


def _axes(fig: plt.Figure) -> dict[str, plt.Axes]:
    return {ax.get_gid(): ax for ax in fig.axes if ax.get_gid()}


def test_labels_cover_every_quantity_with_units():
    keys = [key for key, _ in metrics.QUANTITIES.values()] + ["dpacf_attitude_deg"]
    for key in keys:
        label = plots.quantity_label(key)
        assert key in plots.LABELS
        assert "_" not in label and label.endswith("]") and "[" in label, label
    assert plots.quantity_label("attitude_deg") == "attitude error [deg]"
    assert plots.quantity_label("inertia") == "inertia-ratio error [-]"
    # not in the map: a readable fallback that names the unit by the key's suffix
    assert plots.quantity_label("spin_axis_deg_s") == "spin axis error [deg/s]"
    assert plots.quantity_label("gyro_bias") == "gyro bias error [-]"
    # a label is left as it is
    assert plots.quantity_label("attitude RMSE [deg]") == "attitude RMSE [deg]"
    assert plots.quantity_unit("velocity_m_s") == "m/s"


def test_every_block_has_a_panel_offset_included():
    h, x_true = _history(np.random.default_rng(1))
    fig = plots.error_history_figure(h, x_true)
    axes = _axes(fig)
    for name in LAYOUT.names():
        assert f"{name}:components" in axes and f"{name}:magnitude" in axes
    assert axes["offset:components"].get_ylabel() == "mass-centre offset error [m]"
    assert axes["attitude:components"].get_ylabel() == "attitude error [deg]"
    assert axes["features:components"].get_ylabel().startswith("features RMS error [m]")
    plt.close(fig)


def test_limits_hold_a_conservative_3sigma_and_keep_the_error_readable():
    """3 sigma ten times the error: the linear panel holds the band, the log panel both."""
    sigma_e = 1e-3
    h, x_true = _history(np.random.default_rng(2), sigma_e=sigma_e, ratio=10.0)
    fig = plots.error_history_figure(h, x_true)
    axes = _axes(fig)
    s3 = 3 * 10 * sigma_e  # the band, in m for the position block
    lo, hi = axes["position:components"].get_ylim()
    assert lo <= -s3 and hi >= s3
    assert hi < 2 * s3  # and is not much wider than the band
    lo, hi = axes["position:magnitude"].get_ylim()
    assert axes["position:magnitude"].get_yscale() == "log"
    assert lo < np.sqrt(3) * sigma_e / 3  # the error magnitude (about sqrt(3) sigma_e) shows
    assert hi > np.sqrt(3) * s3  # and so does 3 sqrt(tr P)
    # attitude in degrees: the same in display units
    lo, hi = axes["attitude:components"].get_ylim()
    assert hi >= np.degrees(s3)
    plt.close(fig)


def test_an_occlusion_blowup_is_clipped_shaded_and_said():
    sigma_e = 1e-3
    h, x_true = _history(np.random.default_rng(3), sigma_e=sigma_e, ratio=3.0, blowup=(200, 260))
    assert plots.no_update_spans(h.t, h.nis_dof, np.isfinite(h.x).all(axis=1)) == [(200.0, 260.0)]
    panels = {p.name: p for p in plots.error_panels(h, x_true)}
    lo, hi = panels["position"].ylim
    assert 3 * 3 * sigma_e <= hi < 3 * 3 * 3 * sigma_e  # steady band, not the 100x blow-up
    assert panels["position"].notes[0].startswith("off scale")
    fig = plots.error_history_figure(h, x_true)
    labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert "no measurement update" in labels
    ax = _axes(fig)["position:components"]
    assert any("off scale" in t.get_text() for t in ax.texts)
    plt.close(fig)
    # a scheduled occlusion the caller names is hatched and labelled as such
    fig = plots.error_history_figure(h, x_true, occlusions=[(200.0, 260.0)])
    labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert "occlusion (scheduled)" in labels and "no measurement update" not in labels
    plt.close(fig)


def test_sparse_updates_are_not_shaded_as_gaps():
    t = np.arange(300.0)
    dof = np.where(np.arange(300) % 5 == 0, 6.0, 0.0)  # an update every 5th epoch
    assert plots.no_update_spans(t, dof) == []
    dof[100:200] = 0.0
    assert plots.no_update_spans(t, dof) == [(96.0, 200.0)]


def test_a_history_that_never_started_still_gives_a_figure():
    h, x_true = _history(np.random.default_rng(4), start=400)
    fig = plots.error_history_figure(h, x_true, "never")
    assert "never started" in fig.get_suptitle()
    plt.close(fig)


def test_finite_series_draws_through_nan_and_breaks_long_holes():
    t = np.arange(0.0, 200.0, 0.1)
    y = np.full(len(t), np.nan)
    y[::10] = 1.0 + 0.1 * np.random.default_rng(5).standard_normal(len(t[::10]))
    tt, yy = plots.finite_series(t, y)
    assert np.isfinite(yy).sum() == np.isfinite(y).sum() and np.isnan(yy).sum() == 0
    y[600:1200] = np.nan  # a 60 s hole in a 1 Hz series
    tt, yy = plots.finite_series(t, y)
    assert np.isnan(yy).sum() == 1 and 59.0 < tt[np.isnan(yy)][0] < 120.0


def test_nees_stored_sparsely_is_drawn_with_its_window_mean():
    t = np.arange(0.0, 200.0, 0.1)
    nees = np.full(len(t), np.nan)
    nees[::10] = np.exp(0.1 * np.random.default_rng(6).standard_normal(len(t[::10])))
    nis = np.exp(0.1 * np.random.default_rng(7).standard_normal(len(t)))
    panels = [
        plots.ConsistencyPanel("NEES / dof", {"run-average NEES / dof": nees}, (0.8, 1.2)),
        plots.ConsistencyPanel("NIS / dof", {"run-average NIS / dof": nis}, (0.7, 1.3)),
    ]
    fig = plots.consistency_figure(t, panels, window=(150.0, 200.0))
    ax = fig.axes[0]
    line = next(ln for ln in ax.get_lines() if ln.get_label().startswith("run-average NEES"))
    y = np.asarray(line.get_ydata(), dtype=float)
    assert np.sum(np.isfinite(y[:-1]) & np.isfinite(y[1:])) == np.isfinite(nees).sum() - 1
    mean = np.mean(nees[(t >= 150.0) & np.isfinite(nees)])
    assert f"mean {mean:.3g} over 150-200 s" in line.get_label()
    assert ax.get_yscale() == "log"
    lo, hi = ax.get_ylim()
    assert lo < 0.8 and hi > 1.2  # the bounds are on the chart
    assert fig.axes[1].get_ylabel() == "NIS / dof"
    plt.close(fig)


def test_rmse_figure_uses_human_labels_and_steady_limits():
    t = np.arange(0.0, 300.0)
    y = 0.1 * np.ones_like(t)
    y[:10] = np.nan  # not started
    y[100:120] = 1e9  # an occlusion's blow-up, twelve decades above the steady state
    fig = plots.rmse_figure({"ekf RMSE": (t, y)}, "rate_deg_s", occlusions=[(100.0, 120.0)])
    ax = fig.axes[0]
    assert ax.get_ylabel() == "rate error [deg/s]"
    lo, hi = ax.get_ylim()
    assert lo < 0.1 and hi <= 0.1 * 1e6  # at most six decades: the steady state stays visible
    assert any("off scale" in txt.get_text() for txt in ax.texts)
    plt.close(fig)


def test_campaign_figures_write_rmse_and_nees_with_nis(tmp_path: Path, monkeypatch):
    rng = np.random.default_rng(8)
    runs, n = 4, 201
    t = np.arange(n, dtype=float)
    errs = {"attitude_deg": np.abs(rng.standard_normal((runs, n)))}
    nees = np.full((runs, n), np.nan)
    nees[:, ::10] = rng.chisquare(9, (runs, len(t[::10])))
    nis_dof = np.where(rng.random((runs, n)) < 0.1, 0.0, 6.0)
    nis = np.where(nis_dof > 0, rng.chisquare(6, (runs, n)), np.nan)
    cons = {"nees": nees, "nees_dof": 9, "nis": nis, "nis_dof": nis_dof, "runs": list(range(runs))}
    monkeypatch.setattr(pipeline.runner, "collect", lambda store, k: (t, errs, dict(cons)))
    _, curves, out = pipeline.campaign_curves(tmp_path, runs)
    expected = np.nanmean(np.where(nis_dof > 0, nis / np.where(nis_dof > 0, nis_dof, 1), np.nan), 0)
    np.testing.assert_allclose(out["nis_per_dof"], expected)
    assert np.isfinite(out["nees_per_dof"]).sum() == len(t[::10])

    class _Scenario:  # what campaign_figures reads of a Scenario
        name, window_s, duration_s = "synthetic", (150.0, 200.0), 200.0

        class occlusion:  # noqa: N801
            windows, loss_from_s = [], 180.0

    pipeline.campaign_figures(tmp_path, _Scenario(), "ekf", runs)
    assert (tmp_path / "rmse_attitude_deg.png").stat().st_size > 0
    assert (tmp_path / "nees.png").stat().st_size > 0


def test_robust_limit_ignores_a_short_excursion():
    a = np.ones((1000, 3))
    a[10:20] = 1e6  # 1% of the samples
    assert plots.robust_limit(a, np.ones(1000, dtype=bool), q=95.0, margin=1.0) == 1.0
