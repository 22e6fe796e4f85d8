"""The tracker's camera input (subscribed by ``ros/images.subscribe_camera``, paired by
``ros/stamp_sync.RgbdPairing``): compressed messages turned into the Images the frame path reads, and
the frame made of them once its stamp is taken."""
from __future__ import annotations

from typing import Any

from sensor_msgs.msg import Image

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.core.tracking.frame_gate import StampRules
from memgs_ros.errors import DataError, MessageError
from memgs_ros.io.image_decoding import depth_view, rgb_view
from memgs_ros.nodes.tracker.stats import TrackerStats
from memgs_ros.ros.codecs import stamp_to_ns
from memgs_ros.ros.images import compressed_to_image

__all__ = ["decompressed", "to_frame"]


def decompressed(color: Any, depth: Any | None, depth_scale: float, stats: TrackerStats
                 ) -> tuple[Image, Image | None] | None:
    """A compressed colour (and depth) message pair as the Images the tracker reads; None when one
    does not decode (counted in ``stats``: frames_in, problem.bad_image). Decoded only once a frame
    is taken: a stale one is never decoded."""
    try:
        return (compressed_to_image(color, depth_scale),
                None if depth is None else compressed_to_image(depth, depth_scale))
    except MessageError as err:
        stats.frames_in += 1
        stats.problem("bad_image", f"compressed frame {stamp_to_ns(color.header.stamp)} refused: {err}")
        return None


def to_frame(color: Image, depth: Image | None, camera: PinholeCamera, stamps: StampRules, now_ns: int,
             depth_scale: float, stats: TrackerStats) -> Frame | None:
    """The frame to track, or None (counted, logged once) when its stamp (``stamps`` at ``now_ns``)
    or its images are refused."""
    stamp = stamp_to_ns(color.header.stamp)
    verdict = stamps.check(stamp, now_ns)
    if verdict.problem is not None:
        stats.problem(verdict.problem, verdict.message)
    if not verdict.take:
        return None
    try:
        # Views on the messages: the tracker reads the grey of one and the depth at its keypoints.
        units = None if depth is None else DepthUnits(*depth_view(depth, depth_scale))
        frame = Frame(stamp, rgb_view(color), units, camera)
    except (MessageError, DataError) as err:
        stats.problem("bad_image", f"frame {stamp} refused: {err}")
        return None
    if units is not None and not units.has_valid():
        stats.problem("empty_depth", f"frame {stamp} has no valid depth")
    stamps.took(stamp)
    return frame
