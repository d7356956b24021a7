"""Dynamics of the target and the chaser: torque-free attitude and relative orbit motion."""

from tumblenav.dynamics.relative_orbit import (
    RelativeTrajectory,
    circular_orbit_state,
    cw_propagate,
    cw_stm,
    hill_matrix,
    mean_motion,
    nonlinear_relative,
    propagate_orbit,
)
from tumblenav.dynamics.rigid_body import (
    euler_rhs,
    jacobi_omega,
    polhode_period,
    propagate_attitude,
)

__all__ = [
    "RelativeTrajectory",
    "circular_orbit_state",
    "cw_propagate",
    "cw_stm",
    "euler_rhs",
    "hill_matrix",
    "jacobi_omega",
    "mean_motion",
    "nonlinear_relative",
    "polhode_period",
    "propagate_attitude",
    "propagate_orbit",
]
