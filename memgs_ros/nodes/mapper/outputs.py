"""Everything the mapper node publishes: map deltas and snapshots (rows the session's outbox
thread made), rendered views, and the replay's acknowledgements. What the session's threads
produce is handed over to the executor's thread and published there, in the order handed over
(deltas, snapshots and the final flush leave in seq order)."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header

from memgs_ros.core.mapper_service.session_records import RenderedView
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import make_header, structured_to_pointcloud2
from memgs_ros.ros.hand_over import HandOver
from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image

__all__ = ["MapperOutbox"]

_NO_WAIT = Duration(nanoseconds=0)


class MapperOutbox:
    """The mapper node's publishers: ``memgs/map/delta``, ``memgs/mapper/snapshot`` (latched),
    ``memgs/render/{color,depth,camera_info}`` and ``ack_topic``; maps in ``world_frame``."""

    def __init__(self, node: Node, world_frame: str, ack_topic: str) -> None:
        self._node, self.world_frame = node, world_frame
        self.delta = node.create_publisher(PointCloud2, "memgs/map/delta", qos.reliable(50))
        self.snapshot = node.create_publisher(PointCloud2, "memgs/mapper/snapshot", qos.latched())
        self.color = node.create_publisher(Image, "memgs/render/color", qos.reliable(2))
        self.depth = node.create_publisher(Image, "memgs/render/depth", qos.reliable(2))
        self.info = node.create_publisher(CameraInfo, "memgs/render/camera_info", qos.reliable(2))
        self.acks = node.create_publisher(Header, ack_topic, qos.reliable(100))
        self.hand_over = HandOver(node)

    def receivers_acked(self) -> bool:
        """Whether every delta receiver acknowledged every delta sent (never waits)."""
        return self.delta.wait_for_all_acked(_NO_WAIT)

    def delta_rows(self, rows: np.ndarray) -> None:
        """A delta message's rows (on the session's outbox thread)."""
        self.hand_over(lambda: self.delta.publish(self._cloud(rows)))

    def snapshot_rows(self, rows: np.ndarray) -> None:
        """A snapshot message's rows (on the session's outbox thread)."""
        self.hand_over(lambda: self.snapshot.publish(self._cloud(rows)))

    def view_at(self, stamp_ns: int) -> Callable[[RenderedView], None]:
        """What publishes the view rendered for the pose of ``stamp_ns`` (on the session's worker)."""
        def send(view: RenderedView) -> None:
            self.color.publish(numpy_to_image(view.rgb, "rgb8", stamp_ns, "render_camera"))
            self.depth.publish(depth_to_image(view.depth, "32FC1", stamp_ns, "render_camera"))
            self.info.publish(camera_to_camera_info(view.camera, stamp_ns, "render_camera"))

        return lambda view: self.hand_over(lambda: send(view))

    def ack(self, stamp_ns: int) -> None:
        """Acknowledge an acknowledged frame to the player."""
        self.acks.publish(make_header(stamp_ns, "mapper"))

    def _cloud(self, rows: np.ndarray) -> PointCloud2:
        return structured_to_pointcloud2(rows, self._node.get_clock().now().nanoseconds, self.world_frame)
