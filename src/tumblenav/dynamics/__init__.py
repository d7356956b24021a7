"""Dynamics of the target and the chaser: torque-free attitude and relative orbit motion,
and the fixed-step integration the filters use (:mod:`.integrators`, compiled twin in
:mod:`.compiled`)."""

from tumblenav.dynamics.integrators import discretise, rk4_step
from tumblenav.dynamics.relative_orbit import (
    RelativeTrajectory,
    circular_orbit_state,
    cw_discrete,
    cw_propagate,
    cw_stm,
    hill_matrix,
    mean_motion,
    nonlinear_relative,
    propagate_orbit,
)
from tumblenav.dynamics.rigid_body import (
    euler_coefficients,
    euler_rhs,
    euler_rhs_coefficients,
    jacobi_omega,
    polhode_period,
    propagate_attitude,
)

__all__ = [
    "RelativeTrajectory",
    "circular_orbit_state",
    "cw_discrete",
    "cw_propagate",
    "cw_stm",
    "discretise",
    "euler_coefficients",
    "euler_rhs",
    "euler_rhs_coefficients",
    "hill_matrix",
    "jacobi_omega",
    "mean_motion",
    "nonlinear_relative",
    "polhode_period",
    "propagate_attitude",
    "propagate_orbit",
    "rk4_step",
]
