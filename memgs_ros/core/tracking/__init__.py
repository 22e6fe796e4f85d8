"""Front-end visual odometry (feature tracker for RGB-D and monocular cameras).

``make_tracker(cfg, camera)`` returns an object with ``track(frame) -> TrackResult``,
``poll_refined_keyframes()`` and ``close()``.
"""
from __future__ import annotations

from memgs_ros.core.camera import PinholeCamera
from memgs_ros.core.tracking.config import KeyframeInfo, TrackerConfig, TrackingState, TrackResult
from memgs_ros.core.tracking.frontend import FeatureTracker

__all__ = ["KeyframeInfo", "TrackResult", "TrackerConfig", "TrackingState", "FeatureTracker", "make_tracker"]


def make_tracker(cfg: TrackerConfig, camera: PinholeCamera) -> FeatureTracker:
    """The tracker ``cfg`` asks for: RGB-D or monocular features, or ORB-SLAM3 when configured."""
    if cfg.backend == "orbslam3":
        from memgs_ros.core.tracking.orbslam3_backend import OrbSlam3Tracker

        return OrbSlam3Tracker(cfg, camera)  # type: ignore[return-value]
    if cfg.mode == "mono":
        from memgs_ros.core.tracking.monocular import MonocularTracker

        return MonocularTracker(cfg, camera)
    from memgs_ros.core.tracking.rgbd import RGBDTracker

    return RGBDTracker(cfg, camera)
