"""ukf-gp where a single GP predicts: its pseudo-measurements' R matched to the innovations
(ukf_gp._matched_single_gp, covariance matching), checked on a filter stand-in whose NIS/dof
is the pseudo-measurements' true error variance over the stated R (what a filter dominated by
R gives), with a true variance that changes over the loss."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tumblenav.estimators.kabir2025 import ukf_gp


def _setup(rng):
    n, N = 600, 3
    t = np.arange(n, dtype=float)
    z = np.full((n, N, 9), np.nan)
    z[:300] = 0.0  # really measured before the loss at 300 s
    zp = z.copy()
    zp[300:, 0, :] = 0.0  # one GP (feature 0) predicts through the loss
    pseudo = np.zeros(n, bool)
    pseudo[300:] = True
    R0 = np.full((n, N, 9), 1e-10)
    true_var = 1e-10 * (0.12 + 0.08 * np.sin(2 * np.pi * t / 200.0))  # changes over the loss
    calls = []

    def rerun(Rp):  # the filter's NIS where R dominates its innovations' covariance
        calls.append(Rp.copy())
        dof = np.where(np.isfinite(zp[:, 0, 0]), 9, 0)
        ratio = true_var / Rp[:, 0, 0]
        nis = np.where(dof > 0, dof * ratio * rng.chisquare(9, n) / 9, np.nan)
        return SimpleNamespace(t=t, nis=nis, nis_dof=dof)

    hist = rerun(R0)
    args = dict(
        rerun=rerun,
        z=z,
        zp=zp,
        Rp=R0,
        extra=np.zeros_like(R0),
        pseudo=pseudo,
        window=21,
    )
    return hist, args, true_var, calls


def test_single_gp_r_matched_to_its_innovations():
    rng = np.random.default_rng(18)
    hist, args, true_var, calls = _setup(rng)
    want = np.mean(true_var[300:]) / 1e-10  # the sensor's R: NIS/dof ~0.1, as measured
    assert np.nansum(hist.nis[300:]) / hist.nis_dof[300:].sum() == pytest.approx(want, rel=0.1)
    passes = ukf_gp.UKFGPTuning().gp_single_match_passes  # the default: 3
    h, Rp = ukf_gp._matched_single_gp(hist, passes=passes, **args)
    assert len(calls) == 4  # the given pass and three matching passes
    ratio = Rp[300:, 0, 0] / true_var[300:]
    assert np.median(np.abs(ratio - 1.0)) < 0.1  # follows the change over the loss
    nis = h.nis[300:].sum() / h.nis_dof[300:].sum()
    assert nis == pytest.approx(1.0, abs=0.05)
    # only the single GP's pseudo-measurements change; the real ones and the others keep R
    assert np.all(Rp[:300] == 1e-10) and np.all(Rp[:, 1:] == 1e-10)


def test_single_gp_matching_off_or_not_single():
    rng = np.random.default_rng(19)
    hist, args, _, calls = _setup(rng)
    h, Rp = ukf_gp._matched_single_gp(hist, passes=0, **args)
    assert h is hist and np.all(Rp == args["Rp"]) and len(calls) == 1
    # where gp_inconsistency measured the GPs' own error (extra > 0) nothing is matched
    args["extra"] = np.where(np.isfinite(args["zp"]) & ~np.isfinite(args["z"]), 1e-11, 0.0)
    h, Rp = ukf_gp._matched_single_gp(hist, passes=3, **args)
    assert h is hist and len(calls) == 1


def test_moving_ratio_is_the_windowed_ratio():
    num = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    den = np.array([1.0, 1.0, 0.0, 1.0, 1.0])
    r = ukf_gp._moving_ratio(num, den, 3)
    assert r[0] == pytest.approx(3.0 / 2.0)
    assert r[2] == pytest.approx(9.0 / 2.0)
    assert r[4] == pytest.approx(9.0 / 2.0)
    assert np.isnan(ukf_gp._moving_ratio(num, np.zeros(5), 3)).all()
