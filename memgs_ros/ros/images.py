"""Image messages: arrays encoded as sensor_msgs/Image and cameras as CameraInfo, image_transport's
compressed messages turned into the Images a node reads, depth put in REP-118's units, and the
subscription to a camera's raw or compressed topics.

cv_bridge is not on PyPI, so the packing lives here. Decoding is the one decoder's,
:mod:`memgs_ros.io.image_decoding` (shared with the bag reader, which needs no ROS). Every
conversion that can fail raises :class:`MessageError` naming the field, encoding or size that is wrong.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.errors import MessageError
from memgs_ros.io.image_decoding import (
    IMAGE_ENCODINGS,
    compressed_is_depth,
    decode_compressed_depth,
    decode_compressed_rgb,
    depth_view,
    metres_to_depth_units,
)
from memgs_ros.ros.codecs import bytes_array, make_header, stamp_to_ns

__all__ = [
    "IMAGE_ENCODINGS",
    "camera_to_camera_info",
    "compressed_to_image",
    "depth_to_image",
    "numpy_to_image",
    "rep118_depth",
    "subscribe_camera",
]


def numpy_to_image(arr: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> Image:
    """Encode an array as an Image (little-endian, no row padding).

    arr: [H, W] or [H, W, C] with the dtype and channel count of ``encoding``
    (uint8 for rgb8/bgr8/rgba8/bgra8/mono8, uint16 for 16UC1/mono16, float32 for 32FC1).
    """
    if encoding not in IMAGE_ENCODINGS:
        raise MessageError(f"unsupported image encoding '{encoding}' (supported: {', '.join(IMAGE_ENCODINGS)})")
    dtype, channels = IMAGE_ENCODINGS[encoding]
    a = np.asarray(arr)
    if a.ndim == 3 and channels == 1 and a.shape[2] == 1:
        a = a[:, :, 0]
    expected = "[H, W]" if channels == 1 else f"[H, W, {channels}]"
    if (channels == 1 and a.ndim != 2) or (channels > 1 and (a.ndim != 3 or a.shape[2] != channels)):
        raise MessageError(f"{encoding} needs an array {expected}, got shape {a.shape}")
    if a.dtype.newbyteorder("=") != dtype.newbyteorder("="):
        raise MessageError(f"{encoding} needs dtype {dtype}, got {a.dtype}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise MessageError(f"{encoding} image has no pixels, shape {a.shape}")
    a = a.astype(dtype.newbyteorder("<"), copy=False)
    msg = Image()
    msg.header = make_header(stamp_ns, frame_id)
    msg.height, msg.width = int(a.shape[0]), int(a.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = msg.width * channels * dtype.itemsize
    msg.data = bytes_array(a)
    return msg


def depth_to_image(
    depth_m: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, depth_scale: float = 1000.0
) -> Image:
    """[H, W] metres -> 32FC1 (NaN invalid) or 16UC1 (``depth_scale`` units per metre, 0 invalid).

    For 16UC1, depths that round to 0 or exceed 65535 units are written as 0 (invalid)
    rather than clamped, so no wrong depth reaches the tracker.
    """
    d = np.asarray(depth_m, dtype=np.float32)
    if d.ndim != 2:
        raise MessageError(f"depth must be [H, W], got shape {d.shape}")
    if encoding == "32FC1":
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d) & (d > 0)
        return numpy_to_image(np.where(valid, d, np.float32(np.nan)).astype(np.float32), encoding, stamp_ns, frame_id)
    if encoding == "16UC1":
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise MessageError(f"depth_scale must be a positive number of units per metre, got {depth_scale}")
        return numpy_to_image(metres_to_depth_units(d, depth_scale), encoding, stamp_ns, frame_id)
    raise MessageError(f"depth encoding must be 32FC1 or 16UC1, got '{encoding}'")


def compressed_to_image(msg: Any, depth_scale: float = 1000.0) -> Image:
    """A sensor_msgs/CompressedImage (image_transport's ``compressed`` colour or ``compressedDepth``)
    as the Image the tracker reads: rgb8, or 32FC1 metres; MessageError when it does not decode."""
    stamp_ns, frame_id = stamp_to_ns(msg.header.stamp), str(msg.header.frame_id)
    if compressed_is_depth(msg):
        return depth_to_image(decode_compressed_depth(msg, depth_scale), "32FC1", stamp_ns, frame_id)
    return numpy_to_image(decode_compressed_rgb(msg), "rgb8", stamp_ns, frame_id)


def rep118_depth(msg: Image, depth_scale: float) -> Image:
    """Depth in REP-118's units: 16UC1 millimetres or 32FC1 metres. ``msg`` in those goes on as
    it is; 16-bit depth of another scale (``depth_scale`` units a metre: TUM's 5000) becomes 32FC1
    metres, exactly (millimetres would round TUM's 0.2 mm steps). The tracker, the graph's entry,
    sends keyframe depth this way, so no node after it needs the camera's scale."""
    from memgs_ros.core.geometry.view import depth_to_metres  # compiled: only the tracker loads it

    raw, scale = depth_view(msg, depth_scale)
    if raw.dtype != np.uint16 or scale == 1000.0:
        return msg
    return depth_to_image(depth_to_metres(raw, scale), "32FC1", stamp_to_ns(msg.header.stamp), str(msg.header.frame_id))


def camera_to_camera_info(cam: PinholeCamera, stamp_ns: int, frame_id: str) -> CameraInfo:
    """PinholeCamera -> CameraInfo (plumb_bob or rational_polynomial, R identity, P = [K | 0])."""
    msg = CameraInfo()
    msg.header = make_header(stamp_ns, frame_id)
    msg.width, msg.height = int(cam.width), int(cam.height)
    msg.distortion_model = cam.distortion_model
    msg.d = [float(x) for x in cam.dist]
    msg.k = [float(cam.fx), 0.0, float(cam.cx), 0.0, float(cam.fy), float(cam.cy), 0.0, 0.0, 1.0]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [float(cam.fx), 0.0, float(cam.cx), 0.0, 0.0, float(cam.fy), float(cam.cy), 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def subscribe_camera(node: Node, color_topic: str, depth_topic: str | None, compressed: bool,
                     on_color: Callable[..., None], on_depth: Callable[[Any], None], qos: QoSProfile) -> str:
    """Subscribe to colour (and depth unless None): raw Images, or with ``compressed`` the
    CompressedImages on ``<color_topic>/compressed`` and ``<depth_topic>/compressedDepth``.
    Returns a line naming the topics, resolved."""
    kind = CompressedImage if compressed else Image
    color = f"{color_topic}/compressed" if compressed else color_topic
    node.create_subscription(kind, color, on_color, qos)
    line = node.resolve_topic_name(color)
    if depth_topic is not None:
        depth = f"{depth_topic}/compressedDepth" if compressed else depth_topic
        node.create_subscription(kind, depth, on_depth, qos)
        line += f" + {node.resolve_topic_name(depth)}"
    return line
