"""Evaluation: the stage after the estimator, the one path for single runs and campaigns.

It owns the comparison with the truth (:mod:`.alignment`: each estimator's state convention,
principal frames, symmetries), the errors, RMSE, NEES and NIS with their chi-square bounds
(:mod:`.metrics`). No estimator imports it (an import contract in ``make test`` holds that).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tumblenav.estimators.base import EstimateHistory
from tumblenav.estimators.yu2019.tuning import given_ratios_warning
from tumblenav.evaluation.alignment import (
    align,
    register_alignment,
    register_frame_alignment,
    truth_state,
)
from tumblenav.evaluation.metrics import RunErrors, attitude_error_rad, run_errors

__all__ = [
    "align",
    "error_states",
    "evaluate_run",
    "nees_every",
    "register_alignment",
    "register_frame_alignment",
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
    carries one (``info["dpacf_q_TI"]``). The truth is expressed in the symmetric frame the
    estimate is on, where the estimator declares its symmetries (:func:`align`); the run's
    ``branch`` says which."""
    a = align(truth, history)
    x_true = a.x
    r = run_errors(history, x_true, nees_every(history.t), branch=a.branch)
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


# settings that state a prior about the target, checked against the simulated truth:
# key -> (truth attribute, unit, tolerance)
ASSUMPTIONS = {
    "mass_centre_L_m": ("r_L", "m", 1e-3),
    "mass_centre_velocity_L_m_s": ("v_L", "m/s", 1e-5),
}


def states_prior(tuning: dict[str, Any] | None) -> bool:
    """True when ``tuning`` states a prior :func:`assumption_warnings` checks."""
    tuning = tuning or {}
    return tuning.get("inertia_init") == "given" or any(
        tuning.get(k) is not None for k in ASSUMPTIONS
    )


def assumption_warnings(tuning: dict[str, Any] | None, truth: Any) -> list[str]:
    """Priors a user stated in an estimator's settings that the simulated truth contradicts
    (one line each). A simulation may test a wrong prior on purpose, so this only warns:
    Kabir 2025's known mass centre (``mass_centre_L_m``, ``mass_centre_velocity_L_m_s``)
    against the truth's ``r_L``, ``v_L`` at the first epoch; ekf-depth's given inertia
    ratios against the truth's inertia."""
    tuning = tuning or {}
    out = given_ratios_warning(tuning, truth.inertia_T)
    for key, (attr, unit, tol) in ASSUMPTIONS.items():
        if tuning.get(key) is None:
            continue
        stated = np.asarray(tuning[key], dtype=float)
        true = np.asarray(getattr(truth, attr), dtype=float)[0]
        off = float(np.linalg.norm(stated - true))
        if off > tol + 1e-9 * float(np.linalg.norm(true)):
            out.append(
                f"estimator.tuning.{key} {np.round(stated, 6).tolist()} {unit} differs from "
                f"the simulated truth {np.round(true, 6).tolist()} {unit} by {off:.3g} {unit}: "
                "the filter takes it as known (Kabir 2025 Sec. 2.1); if that is not meant, set "
                "it to the scenario's target.r0_L_m / v0_L_m_s"
            )
    return out
