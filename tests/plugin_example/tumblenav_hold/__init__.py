"""hold-centroid: the target's position held at the first triangulated centroid.

A deliberately crude estimator, to show the interface: it takes the centroid of the
features triangulated at the first epoch with at least three of them, rotates it into the
chaser's LVLH frame L, and holds it, with zero velocity and a constant covariance.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.estimators.base import Block, EstimateHistory, StateLayout, parse_tuning
from tumblenav.frontends.stereo_points import triangulate

LAYOUT = StateLayout((Block("position", "vector", 3), Block("velocity", "vector", 3)))


class Tuning(BaseModel):
    """scenario.estimator.tuning keys of hold-centroid."""

    model_config = ConfigDict(extra="forbid")  # a misspelt key is an error
    sigma_position_m: float = 1.0  # 1-sigma claimed for the held position, m
    sigma_velocity_m_s: float = 1.0  # 1-sigma claimed for the (zero) velocity, m/s


class HoldCentroid:
    name = "hold-centroid"
    consumes = ("stereo-tracks",)  # measurement types it runs on (tumblenav.measurements)
    needs = "stereo feature tracks (stereo sensor), at least three features at one epoch"
    description = "position held at the first triangulated centroid (an example plugin)"

    def check(self, context: Any) -> None:
        if context.sensor.kind != "stereo":
            raise InputError(
                f"{self.name} needs a stereo sensor; scenario {context.name} has "
                f"a {context.sensor.kind} sensor"
            )
        parse_tuning(context.estimator.tuning, Tuning)

    def run(self, context: Any, measurements: Any, rng: np.random.Generator) -> EstimateHistory:
        tun = parse_tuning(context.estimator.tuning, Tuning)
        t = measurements.t
        n = len(t)
        # front end: features triangulated in the rig frame C, (runs=1, n, N, 3) m
        p_C, _cov_C, usable, skipped = triangulate([measurements])
        p_C, usable = p_C[0], usable[0]
        x = np.full((n, LAYOUT.nominal_dim), np.nan)
        P = np.full((n, LAYOUT.dim, LAYOUT.dim), np.nan)
        ready = np.flatnonzero(usable.sum(axis=1) >= 3)
        if len(ready):
            k0 = ready[0]
            centroid_C = p_C[k0, usable[k0]].mean(axis=0)
            R_LC = rot.quat_to_matrix(measurements.q_CL[k0]).T  # q_CL maps L into C
            x[k0:, LAYOUT.nom("position")] = R_LC @ centroid_C
            x[k0:, LAYOUT.nom("velocity")] = 0.0
            P[k0:] = np.diag([tun.sigma_position_m**2] * 3 + [tun.sigma_velocity_m_s**2] * 3)
        return EstimateHistory(
            t=t,
            x=x,
            P=P,
            layout=LAYOUT,
            nis=np.full(n, np.nan),  # no measurement update, so no innovation
            nis_dof=np.zeros(n),
            skipped={k: int(v[0]) for k, v in skipped.items()},
            info={"start_condition": "(no epoch with three triangulated features)"},
        )
