"""Fault injection for the Chang 2021 image pipeline (renderer -> image front end -> ekf-pose):
black frames (eclipse), the target out of view, motion blur, all features lost, too few
matched features. The front end re-detects, the filter propagates and counts what it skipped;
nothing crashes and no NaN reaches the state."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from tumblenav.campaign.store import run_seed
from tumblenav.estimators import base as est_base
from tumblenav.estimators.context import context_from_scenario
from tumblenav.frontends import stages
from tumblenav.measurements import StereoImageMeasurements
from tumblenav.scenario import load_scenario
from tumblenav.simulation import run_streams, simulate


@dataclass(frozen=True)
class Faulty:
    """A frame source with faults injected at chosen epochs."""

    inner: object
    faults: dict[int, str]

    def __len__(self) -> int:
        return len(self.inner)  # type: ignore[arg-type]

    def pair(self, k: int):
        left, right = self.inner.pair(k)  # type: ignore[attr-defined]
        kind = self.faults.get(k)
        if kind == "black":  # eclipse: only the sensor's dark noise
            left, right = (np.minimum(img, 3) // 2 for img in (left, right))
        elif kind == "out_of_view":  # the target left the field of view: black space
            left, right = np.zeros_like(left), np.zeros_like(right)
        elif kind == "motion_blur":  # a 25 px streak along u
            kernel = np.full((1, 25), 1 / 25)
            left, right = (cv2.filter2D(img, -1, kernel) for img in (left, right))
        elif kind == "right_lost":  # the right camera sees nothing: no match at all
            right = np.zeros_like(right)
        elif kind == "two_corners":  # only a couple of tiny blobs remain in view
            left, right = np.zeros_like(left), np.zeros_like(right)
            for img in (left, right):
                img[500:504, 500:504] = 200
                img[520:524, 560:564] = 200
        return left, right


@pytest.fixture(scope="module")
def short_close():
    sc = load_scenario("chang2021_close").with_updates(
        duration_s=14.0,
        steady_state_window_s=[10.0, 14.0],
        **{"estimator.tuning": {"init_frames": 15}},
    )
    ss = run_seed(sc.montecarlo.seed, 0)
    truth, meas = simulate(sc, ss)
    return sc, ss, truth, meas


FAULTS = {
    25: "black",
    26: "black",
    30: "out_of_view",
    31: "out_of_view",
    32: "out_of_view",
    38: "motion_blur",
    39: "motion_blur",
    44: "right_lost",
    50: "two_corners",
    51: "two_corners",
    60: "black",
}


def test_faults_are_survived_counted_and_never_reach_the_state(short_close):
    sc, ss, truth, meas = short_close
    assert isinstance(meas, StereoImageMeasurements)
    bad = StereoImageMeasurements(
        meas.t, meas.q_CL, meas.q_LI, meas.rig, meas.noise_px, Faulty(meas.source, FAULTS)
    )
    tracks, stats = stages.prepare(bad, ("stereo-tracks",), {})
    held = np.asarray(stats["counts"]["features"]) if "counts" in stats else None
    obs = tracks.observed.all(axis=1).sum(axis=1)
    for k in (25, 26, 30, 31, 32, 44, 50, 51, 60):
        assert obs[k] <= 2, (k, obs[k])  # nothing (or next to nothing) is matched there
    assert obs[34] >= 60 and obs[62] >= 60  # the front end re-detected after the faults
    assert np.all(np.isfinite(tracks.uv[tracks.observed]))  # observed pixels are numbers
    if held is not None:
        assert held.max() <= 120
    est = est_base.get("ekf-pose")
    hist = est.run(context_from_scenario(sc), tracks, run_streams(ss)["estimator"])
    started = np.isfinite(hist.x).all(axis=1)
    assert started[-1] and started.sum() > 20
    first = int(np.argmax(started))
    assert np.all(np.isfinite(hist.x[first:]))  # propagated through every fault, no NaN
    assert np.all(np.isfinite(hist.P[first:]))
    assert sum(hist.skipped.values()) >= 6  # the faulty epochs were counted, not fused
