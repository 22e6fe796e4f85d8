"""Front-end visual odometry (feature tracker for RGB-D and monocular cameras).

``make_tracker(cfg, camera)`` returns a :class:`Tracker`: ``track(frame) -> TrackResult``,
``poll_refined_keyframes()``, ``map_stats()``, ``ba_time_s`` and ``close()``. ``warm_up()``
loads (or on first use compiles) the compiled kernels ahead of the first frame.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.tracking.config import KeyframeInfo, TrackerConfig, TrackingState, TrackResult
from memgs_ros.core.tracking.protocol import SparseMapStats, Tracker

if TYPE_CHECKING:
    from memgs_ros.core.tracking.frontend.feature_tracker import FeatureTracker

__all__ = [
    "FeatureTracker",
    "KeyframeInfo",
    "SparseMapStats",
    "TrackResult",
    "Tracker",
    "TrackerConfig",
    "TrackingState",
    "make_tracker",
    "warm_up",
]


def __getattr__(name: str) -> Any:
    """The compiled kernels (numba, scipy) load when first asked for: nodes that only read the
    tracker's parameters (every node's parameter table names it) do not pay ~100 MB for them."""
    if name == "FeatureTracker":
        from memgs_ros.core.tracking.frontend.feature_tracker import FeatureTracker

        return FeatureTracker
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def warm_up() -> None:
    """Import the trackers' modules (scipy's optimisers among them: 0.2-0.3 s that the first frame of
    a live camera paid while its next frames queued) and load, or compile, their kernels and the
    bundle adjustments'."""
    from memgs_ros.core.tracking.backend import ba_kernels
    from memgs_ros.core.tracking.frontend import monocular, rgbd  # noqa: F401 - imported now, not at the first frame
    from memgs_ros.core.tracking.kernel_calls import warm_up as load_kernels

    load_kernels()
    ba_kernels.warm_up()  # the first local BA runs beside the frames that follow its keyframe


def make_tracker(cfg: TrackerConfig, camera: PinholeCamera) -> Tracker:
    """The tracker ``cfg`` asks for: RGB-D or monocular features."""
    if cfg.mode == "mono":
        from memgs_ros.core.tracking.frontend.monocular import MonocularTracker

        return MonocularTracker(cfg, camera)
    from memgs_ros.core.tracking.frontend.rgbd import RGBDTracker

    return RGBDTracker(cfg, camera)
