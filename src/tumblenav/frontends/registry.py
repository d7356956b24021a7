"""Which front end turns which measurement type into what (``tumblenav estimators`` lists
them). Third-party front ends register through the ``tumblenav.frontends`` entry-point group
(name: the front end's name; value: ``module:attribute``, a :class:`FrontEnd`).

Most built-in front ends are called by their estimators (ekf-dpacf runs the stereo-points
front end itself); the stereo-images front end is a stage of its own
(:mod:`tumblenav.frontends.stages`): it turns image pairs into the stereo tracks every
track-consuming estimator reads.
"""

from __future__ import annotations

from dataclasses import dataclass

from tumblenav.measurements import DEPTH_CLOUDS, STEREO_IMAGES, STEREO_TRACKS

ENTRY_POINT_GROUP = "tumblenav.frontends"


@dataclass(frozen=True)
class FrontEnd:
    name: str
    consumes: str  # a measurement type (tumblenav.measurements)
    produces: str  # what it gives its estimators, in words
    module: str  # where it lives
    description: str


BUILTIN = (
    FrontEnd(
        "stereo-images",
        STEREO_IMAGES,
        "stereo feature tracks (the stereo sensor's measurement type), for any estimator that "
        "runs on tracks",
        "tumblenav.frontends.stereo_images",
        "Chang 2021 Sec. 2.3-2.4: FAST, pyramidal LK with a forward-backward check, epipolar "
        "NCC matching, feature management",
    ),
    FrontEnd(
        "stereo-points",
        STEREO_TRACKS,
        "triangulated points with covariances, the photogrammetric frame G, inertia ratios "
        "and the DPACF attitude",
        "tumblenav.frontends.stereo_points",
        "Hu 2024 Sec. 2-3: triangulation, G frame, inertia least squares, DPACF",
    ),
    FrontEnd(
        "projections",
        STEREO_TRACKS,
        "normalised projections, disparity and optical flow per feature",
        "tumblenav.frontends.projections",
        "Kabir 2025 eq. 16-27",
    ),
    FrontEnd(
        "planes",
        DEPTH_CLOUDS,
        "pose fixes (attitude and centroid) from recognised rectangles",
        "tumblenav.frontends.depth_pose",
        "Yu 2019 Sec. 2-3: RANSAC planes, rectangle recognition, coarse pose",
    ),
)


def available() -> dict[str, FrontEnd]:
    """The built-in front ends and the installed plugins (a plugin that fails to load is
    left out)."""
    from importlib.metadata import entry_points

    out = {f.name: f for f in BUILTIN}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in out:
            continue
        try:
            fe = ep.load()
        except Exception:  # noqa: BLE001 - a broken plugin must not break the tool
            continue
        if isinstance(fe, FrontEnd):
            out[ep.name] = fe
    return out
