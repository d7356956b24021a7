"""Sensor models: stereo rig projection and noise, visibility masks, rig pointing."""

from tumblenav.sensors.occlusion import loss_from_mask, scheduled_mask, self_occlusion_mask
from tumblenav.sensors.pointing import fixed_R_LC, target_pointing_R_LC
from tumblenav.sensors.stereo import (
    Camera,
    StereoMeasurement,
    StereoRig,
    angular_noise_to_px,
    chang2021_rig,
    chang2021_text_rig,
    convergent_rig,
    disparity,
    make_rig,
    measure,
    parallel_rig,
    project,
)

__all__ = [
    "Camera",
    "StereoMeasurement",
    "StereoRig",
    "angular_noise_to_px",
    "chang2021_rig",
    "chang2021_text_rig",
    "convergent_rig",
    "disparity",
    "fixed_R_LC",
    "loss_from_mask",
    "make_rig",
    "measure",
    "parallel_rig",
    "project",
    "scheduled_mask",
    "self_occlusion_mask",
    "target_pointing_R_LC",
]
