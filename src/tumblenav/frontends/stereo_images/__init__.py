"""Stereo-image front end of Chang 2021 (Sec. 2.3-2.4, 3.3): FAST corners in the left image,
pyramidal LK tracking, left -> right matching along the calibrated rig's epipolar line, two-ray
triangulation and Chang's feature management; its output is the stereo feature-track
measurement (:class:`~tumblenav.measurements.StereoMeasurements`) that the synthetic stereo
sensor gives.

Pixels are in the tumblenav convention throughout (pixel centres at ``i + 0.5``;
``u = u_opencv + 0.5``).
"""

from tumblenav.frontends.stereo_images.geometry import EpipolarGeometry
from tumblenav.frontends.stereo_images.matching import MatchStatus, StereoMatcher
from tumblenav.frontends.stereo_images.run import FrontEndStats, track_images
from tumblenav.frontends.stereo_images.tracker import (
    FrameStats,
    ImageTracker,
    TrackedFrame,
    most_tracked_to_remove,
)
from tumblenav.frontends.stereo_images.tuning import ImageFrontEndTuning

__all__ = [
    "EpipolarGeometry",
    "FrameStats",
    "FrontEndStats",
    "ImageFrontEndTuning",
    "ImageTracker",
    "MatchStatus",
    "StereoMatcher",
    "TrackedFrame",
    "most_tracked_to_remove",
    "track_images",
]
