"""The camera topics a replay publishes, one shared header stamp per frame: ``color/image_raw``
(rgb8), ``depth/image_raw`` (32FC1 metres or 16UC1 units), ``color/camera_info`` and, when
the source has ground truth, ``groundtruth/pose`` (PoseStamped, camera in world).

Depth crosses once: as 16UC1 a frame that holds its depth as stored (a TUM folder's 16-bit PNG,
``DepthUnits``) goes out as it is, in the units the camera wrote (the tracker reads them with its
``depth_scale``: ``memgs run`` sets it, ``io.sources.player_depth_units``); other depth is encoded, in
REP-118's millimetres or metres, by the compiled encoder, which the player then loads
(:meth:`FrameOutbox.prepare`)."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.view import DepthUnits, load_kernels
from memgs_ros.ros import codecs, images, qos

__all__ = ["FrameOutbox"]


class FrameOutbox:
    """Publishes frames as camera topics (relative names: they follow the node's namespace)."""

    def __init__(self, node: Node, frame_id: str, world_frame_id: str, depth_encoding: str) -> None:
        self._node = node
        self._frame_id, self._world_frame_id = frame_id, world_frame_id
        self._depth_encoding = depth_encoding
        self.color = node.create_publisher(Image, "color/image_raw", qos.reliable(5))
        self.depth = node.create_publisher(Image, "depth/image_raw", qos.reliable(5))
        self.info = node.create_publisher(CameraInfo, "color/camera_info", qos.reliable(5))
        self.gt = node.create_publisher(PoseStamped, "groundtruth/pose", qos.reliable(10))

    def _as_published(self, depth: np.ndarray | DepthUnits | None) -> bool:
        """Whether ``depth`` goes out as it is: 16-bit units as stored, published as 16UC1."""
        return isinstance(depth, DepthUnits) and self._depth_encoding == "16UC1" and depth.raw.dtype == np.uint16

    def prepare(self, first: Frame) -> None:
        """Before the first frame (``first``) goes out: load the compiled depth passes when frames
        like it need converting (not on a frame whose replay runs against the clock)."""
        if first.depth_m is not None and not self._as_published(first.depth_m):
            load_kernels()

    def publish(self, frame: Frame, stamp_ns: int) -> None:
        fid = self._frame_id
        self.color.publish(images.numpy_to_image(frame.rgb, "rgb8", stamp_ns, fid))
        if self._as_published(frame.depth_m):
            assert isinstance(frame.depth_m, DepthUnits)
            self.depth.publish(images.numpy_to_image(frame.depth_m.raw, "16UC1", stamp_ns, fid))
        elif (depth_m := frame.depth_metres()) is not None:
            self.depth.publish(images.depth_to_image(depth_m, self._depth_encoding, stamp_ns, fid))  # 16UC1: mm
        self.info.publish(images.camera_to_camera_info(frame.camera, stamp_ns, fid))
        if frame.T_wc_gt is not None:
            self.gt.publish(codecs.matrix_to_pose_stamped(frame.T_wc_gt, stamp_ns, self._world_frame_id))

    def match_counts(self) -> tuple[int, ...]:
        """Matched subscriptions of color, depth, camera_info and ground truth, in that order."""
        return tuple(p.get_subscription_count() for p in (self.color, self.depth, self.info, self.gt))

    def unmatched_readers(self, nodes: tuple[str, ...]) -> list[str]:
        """What still keeps the first frame from ``nodes``: a node whose color or camera_info reader
        the graph does not show yet, or a reader the graph shows that is not matched yet."""
        missing = []
        for pub in (self.color, self.info) if nodes else ():
            readers = self._node.get_subscriptions_info_by_topic(pub.topic_name)
            names = {r.node_name for r in readers}
            missing += [f"{n}'s reader on '{pub.topic_name}'" for n in nodes if n not in names]
            if pub.get_subscription_count() < len(readers):
                missing.append(f"a match for all {len(readers)} readers on '{pub.topic_name}'")
        return missing
