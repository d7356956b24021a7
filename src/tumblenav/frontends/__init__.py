"""Measurement front-ends: stereo triangulation, photogrammetric frame G, inertia and DPACF.

Implements Hu 2024 Sec. 2.1 (eq. 1) and Sec. 3 (eq. 6-17); see each module for the
corrections made to the paper's extracted equations.
"""

from tumblenav.frontends.inertia import (
    InertiaAccumulator,
    InertiaEstimate,
    InertiaIdentification,
    accumulate,
    identify_inertia,
    inertia_design,
    inertia_ratios,
    principal_frame,
    principal_moments,
    solve,
)
from tumblenav.frontends.photogrammetric import (
    GAlignment,
    best_triplet,
    features_in_G,
    g_frame_from_points,
    rate_from_attitudes,
    recover_G,
    triplet_score,
)
from tumblenav.frontends.triangulation import (
    triangulate_parallel,
    triangulate_two_ray,
    triangulation_covariance,
    triangulation_jacobian,
)

__all__ = [
    "GAlignment",
    "InertiaAccumulator",
    "InertiaEstimate",
    "InertiaIdentification",
    "accumulate",
    "best_triplet",
    "features_in_G",
    "g_frame_from_points",
    "identify_inertia",
    "inertia_design",
    "inertia_ratios",
    "principal_frame",
    "principal_moments",
    "rate_from_attitudes",
    "recover_G",
    "solve",
    "triangulate_parallel",
    "triangulate_two_ray",
    "triangulation_covariance",
    "triangulation_jacobian",
    "triplet_score",
]
