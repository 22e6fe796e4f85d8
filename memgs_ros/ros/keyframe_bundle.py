"""A keyframe bundle (tracker -> sampler, mapper), both ends: the tracker's ``KeyframeOutbox``
sends it (colour, depth, camera_info, pose and keypoints sharing the keyframe's stamp, plus the
refined, loop-corrected and culled poses of earlier keyframes), and ``decode_keyframe_images``
reads its common part (camera, images and pose) in the sampler and the mapper.

Both consumers refuse a bad keyframe whole and count the problem by kind, so the decoder says
which check failed: ``camera_info``, ``bad_image``, ``size_mismatch``, ``empty_depth`` or
``bad_pose`` (see the nodes' docstrings).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.publisher import Publisher
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.mapping.keyframe_input import KeyframeInput
from memgs_ros.core.tracking.config import TrackResult
from memgs_ros.errors import DataError, MessageError
from memgs_ros.io.image_decoding import (
    DEFAULT_DEPTH_SCALE as REP118_MM,  # 16UC1 in REP-118: millimetres
)
from memgs_ros.io.image_decoding import (
    check_image_sizes,
    decode_camera_info,
    depth_view,
    has_valid_depth,
    rgb_view,
)
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import matrix_to_pose_stamped, pose_to_matrix, set_stamp, structured_to_pointcloud2
from memgs_ros.ros.images import camera_to_camera_info, rep118_depth


class KeyframeBundleError(MessageError):
    """A keyframe bundle refused; ``kind`` is the problem kind it is counted under."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def decode_keyframe_images(bundle: Mapping[str, Any], stamp_ns: int, decided_ns: int = 0) -> KeyframeInput:
    """Decode ``camera_info``, ``color``, ``pose`` and, when present, ``depth`` of the bundle of
    keyframe ``stamp_ns`` (no seeds: the mapper adds the sampler's).

    The images stay as the tracker forwarded them: colour a read-only view on the message where
    it is rgb8, depth in REP-118's units as the tracker sends it (16UC1 millimetres or 32FC1
    metres, ``images.rep118_depth``). The
    bundle's messages must outlive the returned keyframe's use (the caller holds them).
    Raises KeyframeBundleError naming the kind of the first check that fails.
    """
    kind = "camera_info"
    try:
        camera = decode_camera_info(bundle["camera_info"])
        kind = "bad_image"
        rgb = rgb_view(bundle["color"])
        depth, scale = depth_view(bundle["depth"], REP118_MM) if "depth" in bundle else (None, 1.0)
        kind = "size_mismatch"
        check_image_sizes(rgb, depth, camera)
        if depth is not None and not has_valid_depth(depth):
            kind = "empty_depth"
            raise MessageError("depth has no valid pixel (all zero, NaN, inf or negative)")
        kind = "bad_pose"
        T_wc = pose_to_matrix(bundle["pose"].pose)
    except (MessageError, DataError) as err:
        raise KeyframeBundleError(kind, str(err)) from err
    return KeyframeInput(stamp_ns, T_wc, rgb, depth, camera, depth_scale=scale, decided_ns=decided_ns)


# The keypoints message: undistorted pixel position, depth of its map point (NaN: none), in the map.
KEYPOINT_DTYPE = np.dtype([("u", np.float32), ("v", np.float32), ("depth", np.float32), ("active", np.uint8)])


class KeyframeOutbox:
    """The keyframe topics of ``node`` (transient local: a restarted sampler or mapper gets them
    again) and the keyframe-id -> stamp table that names refined and loop-corrected poses."""

    def __init__(self, node: Node, world_frame: str, depth_scale: float) -> None:
        kf = qos.keyframes()
        self.world_frame, self.depth_scale = world_frame, depth_scale  # the camera's 16-bit units a metre
        self.color = node.create_publisher(Image, "memgs/keyframe/color", kf)
        self.depth = node.create_publisher(Image, "memgs/keyframe/depth", kf)
        self.info = node.create_publisher(CameraInfo, "memgs/keyframe/camera_info", kf)
        self.pose = node.create_publisher(PoseStamped, "memgs/keyframe/pose", kf)
        self.keypoints = node.create_publisher(PointCloud2, "memgs/keyframe/keypoints", kf)
        self.refined = node.create_publisher(Path, "memgs/keyframe/refined_poses", qos.reliable(20))
        self.loop = node.create_publisher(Path, "memgs/keyframe/loop_corrected_poses", qos.reliable(20))
        self.culled = node.create_publisher(Path, "memgs/keyframe/culled", qos.reliable(20))
        self.stamps: dict[int, int] = {}
        self._poses = Path()
        self._poses.header.frame_id = world_frame

    def publish(self, result: TrackResult, camera: PinholeCamera, camera_frame: str, color: Image,
                depth: Image | None) -> None:
        """The keyframe ``result`` made. Its colour goes out as it came in (each consumer decodes
        and undistorts it once), its depth in REP-118's units (``rep118_depth``: as it came in
        unless the camera's 16-bit scale is not millimetres); a depth paired from another stamp
        takes the colour's, which names the keyframe's bundle."""
        kf = result.keyframe
        assert kf is not None
        stamp = result.stamp_ns
        kps = np.zeros(len(kf.keypoints_uv), dtype=KEYPOINT_DTYPE)
        kps["u"], kps["v"] = kf.keypoints_uv[:, 0], kf.keypoints_uv[:, 1]
        kps["depth"], kps["active"] = kf.keypoint_depth, kf.keypoint_active
        self.info.publish(camera_to_camera_info(camera, stamp, camera_frame))
        self.color.publish(color)
        if depth is not None:
            depth = rep118_depth(depth, self.depth_scale)
            depth.header.stamp = color.header.stamp
            self.depth.publish(depth)
        self.keypoints.publish(structured_to_pointcloud2(kps, stamp, camera_frame))
        self.pose.publish(matrix_to_pose_stamped(kf.T_wc, stamp, self.world_frame))
        self.stamps[kf.keyframe_id] = stamp

    def publish_poses(self, poses: list[tuple[int, np.ndarray]], pub: Publisher, frame_ns: int) -> int:
        """Keyframe poses [(keyframe id, T_wc)] as one Path on ``pub`` (``refined`` or ``loop``),
        by the keyframes' stamps, the Path stamped with the frame they went out with (``frame_ns``:
        an acknowledged replay's mapper trains that frame after them); returns how many (ids it
        never published are left out)."""
        msgs = [matrix_to_pose_stamped(T, self.stamps[i], self.world_frame) for i, T in poses if i in self.stamps]
        if msgs:
            self._poses.poses = msgs
            set_stamp(self._poses.header.stamp, frame_ns)
            pub.publish(self._poses)
        return len(msgs)

    def publish_culled(self, culled: list[tuple[int, int, np.ndarray]], frame_ns: int) -> int:
        """Keyframes culling removed, by stamp (their last poses), on ``memgs/keyframe/culled``; the
        table forgets them. Returns how many went out."""
        n = self.publish_poses([(k, T) for k, _, T in culled], self.culled, frame_ns)
        for k, _, _ in culled:
            self.stamps.pop(k, None)
        return n

    def forget(self, kept_ids: set[int] | frozenset[int], map_keyframes: int) -> None:
        """Drop the stamps of keyframes the map no longer holds (bundle adjustment refines only
        kept ones), once the table has grown well past the map."""
        if len(self.stamps) > 2 * map_keyframes + 64:
            self.stamps = {i: s for i, s in self.stamps.items() if i in kept_ids}
