"""Evaluation: the stage after the estimator, the one path for single runs and campaigns.

It owns the comparison with the truth (:mod:`.alignment`: each estimator's state convention,
principal frames, symmetries), the errors, RMSE, NEES and NIS with their chi-square bounds
(:mod:`.metrics`). No estimator imports it (an import contract in ``make test`` holds that).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tumblenav.estimators.base import EstimateHistory
from tumblenav.evaluation.alignment import register_alignment, truth_state
from tumblenav.evaluation.metrics import RunErrors, attitude_error_rad, run_errors

__all__ = [
    "error_states",
    "evaluate_run",
    "nees_every",
    "register_alignment",
    "truth_state",
]


def nees_every(t: np.ndarray) -> int:
    """Epochs between NEES evaluations: about 1 Hz (every epoch for slower data). The NEES
    needs a solve with the full covariance; 1 Hz is plenty for its time average."""
    if len(t) < 2:
        return 1
    dt = float(np.median(np.diff(t)))
    return max(1, int(round(1.0 / dt))) if dt > 0 else 1


def evaluate_run(history: EstimateHistory, truth: Any) -> RunErrors:
    """The one evaluation of an estimator run against its truth, for ``estimate`` and for
    campaigns alike: errors of every block in the estimator's own convention
    (:func:`truth_state`), NEES at about 1 Hz (:func:`nees_every`), the run's NIS, plus the
    DPACF frame's own attitude error (``dpacf_attitude_deg``, Hu 2024 Fig. 5) when the run
    carries one (``info["dpacf_q_TI"]``)."""
    x_true = truth_state(truth, history)
    r = run_errors(history, x_true, nees_every(history.t))
    q_dpacf = history.info.get("dpacf_q_TI")
    if q_dpacf is not None:
        q_true = x_true[:, history.layout.nom("attitude")]
        r.errors["dpacf_attitude_deg"] = np.degrees(attitude_error_rad(q_true, q_dpacf))
    return r


def error_states(
    histories: list[EstimateHistory], truths: list[Any]
) -> tuple[np.ndarray, np.ndarray]:
    """The truths in each history's convention and the error states ``truth [-] estimate``:
    ``x_true`` (B, n, nominal_dim) and ``err`` (B, n, dim), for diagnostics over runs."""
    x_true = np.stack([truth_state(tr, h) for h, tr in zip(histories, truths, strict=True)])
    err = np.stack([h.layout.boxminus(xt, h.x) for h, xt in zip(histories, x_true, strict=True)])
    return x_true, err
