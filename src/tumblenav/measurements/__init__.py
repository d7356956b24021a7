"""Measurement types: the sensor data that front ends and estimators consume, whether
simulated (:mod:`tumblenav.simulation`) or a user's own, each with its file format
(``to_dataset`` / ``from_dataset``, docs/formats.md).

- :class:`StereoMeasurements` (``stereo-tracks``): pixel pairs per feature ID, a visibility
  mask, the rig's calibration and the chaser's own attitude.
- :class:`DepthMeasurements` (``depth-clouds``): one point cloud per epoch in the sensor frame.
"""

from tumblenav.measurements.depth import DepthMeasurements
from tumblenav.measurements.stereo import StereoMeasurements

# the type names estimators and front ends declare they consume or produce
STEREO_TRACKS = "stereo-tracks"
DEPTH_CLOUDS = "depth-clouds"
KINDS = {"stereo": STEREO_TRACKS, "depth": DEPTH_CLOUDS}  # sensor kind -> what it gives

__all__ = ["DEPTH_CLOUDS", "KINDS", "STEREO_TRACKS", "DepthMeasurements", "StereoMeasurements"]
