"""Evaluation: the stage after the estimator, the one path for single runs and campaigns.

It owns the comparison with the truth (:mod:`.alignment`: each estimator's state convention,
principal frames, symmetries), the errors, RMSE, NEES and NIS with their chi-square bounds
(:mod:`.metrics`). No estimator imports it (an import contract in ``make test`` holds that).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tumblenav.errors import InputError
from tumblenav.estimators.base import EstimateHistory, parse_tuning
from tumblenav.estimators.yu2019.tuning import DepthTuning, _sigma_inertia
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


# ekf-depth's half turns about x, y, z (its symmetric frames) flip these signs of the
# products of inertia [Ixy, Ixz, Iyz]; the diagonal ratios stay
_HALF_TURN_PRODUCT_SIGNS = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)


def states_prior(tuning: dict[str, Any] | None) -> bool:
    """True when ``tuning`` states a prior :func:`assumption_warnings` checks."""
    tuning = tuning or {}
    return tuning.get("inertia_init") == "given" or any(
        tuning.get(k) is not None for k in ASSUMPTIONS
    )


def _inertia_ratio_warning(tuning: dict[str, Any], truth: Any) -> list[str]:
    """ekf-depth's given inertia ratios (``inertia_init: given``, Yu 2019 eq. 29's
    [Iyy/Ixx, Izz/Ixx, Ixy/Ixx, Ixz/Ixx, Iyz/Ixx]) against the truth's, in the closest of the
    model's half-turn frames: with ``inertia_init_perturb`` (Yu's protocol, the truth plus an
    error drawn from P0) they stand for the truth, so any difference over 1e-3 contradicts it;
    without, they are a prior, contradicted beyond 3 of its stated sigma. A copied scenario
    whose target was changed keeps the old ratios, and the filter trusts them."""
    if tuning.get("inertia_init") != "given":
        return []
    try:  # the settings as ekf-depth reads them (its defaults and its P0 rule)
        tun = parse_tuning(tuning, DepthTuning)
    except InputError:
        return []  # not ekf-depth's: the estimator says what is wrong with them
    stated = np.asarray(tun.inertia_init_ratios, dtype=float)
    J = np.asarray(truth.inertia_T, dtype=float)
    J = J / J[0, 0]
    diag, prod = np.array([J[1, 1], J[2, 2]]), np.array([J[0, 1], J[0, 2], J[1, 2]])
    sigma = _sigma_inertia(tun)
    off = min(
        float(np.max(np.abs(stated - np.r_[diag, signs * prod])))
        for signs in _HALF_TURN_PRODUCT_SIGNS
    )
    if off <= (1e-3 if tun.inertia_init_perturb else 3.0 * sigma):
        return []
    true = np.round(np.r_[diag, prod], 4).tolist()
    said = (
        "with inertia_init_perturb they stand for the truth (the start adds an error drawn "
        f"from P0, sigma {sigma:g})"
        if tun.inertia_init_perturb
        else f"more than 3 times their stated sigma {sigma:g}"
    )
    return [
        f"estimator.tuning.inertia_init_ratios {np.round(stated, 4).tolist()} differ from the "
        f"simulated target's {true} (target.inertia_kg_m2) by up to {off:.3g}; {said}, and "
        "the filter starts from them as known to that sigma (inertia_init: given): if the "
        "target's inertia is not meant to be known, set inertia_init: sphere, otherwise give "
        "the target's ratios"
    ]


def assumption_warnings(tuning: dict[str, Any] | None, truth: Any) -> list[str]:
    """Priors a user stated in an estimator's settings that the simulated truth contradicts
    (one line each). A simulation may test a wrong prior on purpose, so this only warns:
    Kabir 2025's known mass centre (``mass_centre_L_m``, ``mass_centre_velocity_L_m_s``)
    against the truth's ``r_L``, ``v_L`` at the first epoch; ekf-depth's given inertia
    ratios against the truth's inertia."""
    tuning = tuning or {}
    out = _inertia_ratio_warning(tuning, truth)
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
