"""The ``camera.*`` parameters: a calibration given in the config instead of camera_info.

TUM's ROS 1 bags (and many drivers) publish a placeholder camera_info, so the configs carry the
published calibration (:class:`memgs_ros.core.geometry.camera.CameraCalibration`). The tracker uses it in
place of camera_info when ``camera_info_override`` is true; the bag player uses it as the camera of
a TUM folder that names none.
"""
from __future__ import annotations

from rclpy.node import Node

from memgs_ros.core.geometry.camera import CAMERA_PREFIX, CameraCalibration, PinholeCamera
from memgs_ros.ros.config_params import declare_config

__all__ = ["CAMERA_PREFIX", "declare_calibration"]



def declare_calibration(node: Node) -> PinholeCamera | None:
    """Declare ``camera.width`` ... ``camera.k6``; the configured camera, or None when none is set.
    ConfigError (naming the parameters) when only part of a calibration is set."""
    return declare_config(node, CameraCalibration, CAMERA_PREFIX).camera()
