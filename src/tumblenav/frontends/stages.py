"""Front ends as stages between the sensor and the estimator: what an estimator consumes, made
from what the sensor gave. Today one conversion exists: stereo image pairs (Chang 2021) become
stereo feature tracks through the image front end (:mod:`tumblenav.frontends.stereo_images`),
so that every estimator that runs on tracks (ekf-pose, ekf-dpacf, ukf, ...) runs on images.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from tumblenav.measurements import STEREO_IMAGES, StereoImageMeasurements


def image_frontend_tuning(raw: dict[str, Any] | None) -> Any:
    """The image front end's settings (``sensor.images.frontend``), validated; InputError
    naming the key otherwise."""
    from tumblenav.frontends.stereo_images import ImageFrontEndTuning
    from tumblenav.settings_rules import validate

    return validate(ImageFrontEndTuning, raw, "sensor.images.frontend")


def prepare(
    measurements: Any,
    consumes: tuple[str, ...],
    frontend: dict[str, Any] | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[Any, dict[str, Any] | None]:
    """``measurements`` as an estimator consuming ``consumes`` needs them, and the front end's
    statistics (None when nothing was converted). Image pairs go through the image front end
    (settings ``frontend``) unless the estimator consumes images itself."""
    if isinstance(measurements, StereoImageMeasurements) and STEREO_IMAGES not in consumes:
        from tumblenav.frontends.stereo_images import track_images

        m = measurements
        tracks, stats = track_images(
            m.pairs(),
            m.t,
            m.rig,
            m.q_CL,
            m.q_LI,
            m.noise_px,
            image_frontend_tuning(frontend),
            progress=progress,
        )
        return tracks, stats.to_dict()
    return measurements, None
