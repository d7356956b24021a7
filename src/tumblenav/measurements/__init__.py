"""Measurement types: the sensor data that front ends and estimators consume, whether
simulated (:mod:`tumblenav.simulation`) or a user's own, each with its file format
(``to_dataset`` / ``from_dataset``, docs/formats.md).

- :class:`StereoMeasurements` (``stereo-tracks``): pixel pairs per feature ID, a visibility
  mask, the rig's calibration and the chaser's own attitude.
- :class:`DepthMeasurements` (``depth-clouds``): one point cloud per epoch in the sensor frame.
- :class:`StereoImageMeasurements` (``stereo-images``): image pairs with the rig's calibration;
  the image front end turns them into stereo tracks for any estimator that consumes those.
"""

from tumblenav.measurements.depth import DepthMeasurements
from tumblenav.measurements.images import StereoImageMeasurements
from tumblenav.measurements.stereo import StereoMeasurements

# the type names estimators and front ends declare they consume or produce
STEREO_TRACKS = "stereo-tracks"
DEPTH_CLOUDS = "depth-clouds"
STEREO_IMAGES = "stereo-images"
KINDS = {"stereo": STEREO_TRACKS, "depth": DEPTH_CLOUDS}  # sensor kind -> what it gives
# what a front end can turn a measurement type into before an estimator sees it
CONVERTS = {STEREO_IMAGES: STEREO_TRACKS}


def kind_of(sensor) -> str:
    """The measurement type a scenario's ``sensor`` settings give (a stereo rig with
    ``images`` set gives image pairs)."""
    if getattr(sensor, "images", None) is not None:
        return STEREO_IMAGES
    return KINDS.get(sensor.kind, sensor.kind)


def runs_on(consumes: tuple[str, ...], given: str) -> bool:
    """Whether an estimator consuming ``consumes`` can run on measurements of type ``given``
    (directly, or after the front end of :data:`CONVERTS`)."""
    return given in consumes or CONVERTS.get(given) in consumes


__all__ = [
    "CONVERTS",
    "DEPTH_CLOUDS",
    "KINDS",
    "STEREO_IMAGES",
    "STEREO_TRACKS",
    "DepthMeasurements",
    "StereoImageMeasurements",
    "StereoMeasurements",
    "kind_of",
    "runs_on",
]
