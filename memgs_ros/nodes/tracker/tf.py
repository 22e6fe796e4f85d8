"""The tracker's TF (REP-105): ``map -> base_link`` per tracked frame on ``/tf``, at the frame's
stamp; ``map -> <world_frame>`` (the SLAM world: the first camera's optical frame) and
``base_link -> <camera optical frame>`` (the mount, unless the robot publishes it) on
``/tf_static``. Both topics are relative (``<namespace>/tf`` under a namespace, as multi-robot
Nav2 launches remap them). With an ``odom_frame``, ``map -> odom`` instead of ``map -> base_link``, from the
``odom -> base_link`` a flight controller or wheel odometry publishes (interpolated to the
frame's stamp, or the nearest within ``odom_tolerance_s``). Where the robot publishes the camera (``publish_camera_tf``
false), the mount is read from ``tf_static`` (``StaticTree``) and fixed before the first pose goes
out; the ``camera_mount_*`` parameters stand in after ``camera_mount_wait_s``.

``tf2_msgs`` comes with ROS; where the PyPI wheels stand in for it, ``python -m
memgs_ros.ros.tf2_msgs_build`` generates it. Without it the node says so once and publishes no TF
(everything else is unchanged).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import Transform, TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from memgs_ros.core.geometry.frames import FrameConvention
from memgs_ros.core.geometry.transform_buffers import PoseWindow, StaticFrames
from memgs_ros.errors import MessageError
from memgs_ros.ros.codecs import pose_fields_to_matrix, set_pose_fields, set_stamp, stamp_to_ns

__all__ = ["OdomTrack", "StaticTree", "TfOutbox", "tf_message_type", "tf_qos", "tf_static_qos"]


def tf_message_type() -> Any | None:
    """``tf2_msgs/msg/TFMessage``, or None where it is not installed."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return TFMessage


def tf_qos() -> QoSProfile:
    """What tf2_ros's broadcaster and listener use on ``/tf``: reliable, volatile, keep last 100."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def tf_static_qos() -> QoSProfile:
    """tf2_ros's ``/tf_static``: reliable, transient local, keep last 1 (one message, all statics)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _transform(T: np.ndarray, stamp_ns: int, parent: str, child: str) -> TransformStamped:
    msg = TransformStamped()
    set_stamp(msg.header.stamp, stamp_ns)
    msg.header.frame_id, msg.child_frame_id = parent, child
    set_pose_fields(msg.transform.translation, msg.transform.rotation, T)
    return msg


def _matrix(tf: Transform) -> np.ndarray | None:
    """A received transform as [4, 4], or None when it is not finite (another node's bad message
    is skipped, not a crash of this one)."""
    try:
        return pose_fields_to_matrix(tf.translation, tf.rotation)
    except MessageError:
        return None


class OdomTrack:
    """The ``odom -> base`` transforms seen on ``/tf``, in a ``PoseWindow``."""

    def __init__(self, odom_frame: str, base_frame: str, window: int = 400) -> None:
        self.odom_frame, self.base_frame = odom_frame, base_frame
        self.window = PoseWindow(window)

    def add(self, msg: Any) -> None:
        for t in msg.transforms:
            ours = t.header.frame_id.lstrip("/") == self.odom_frame and t.child_frame_id.lstrip("/") == self.base_frame
            if ours and (T := _matrix(t.transform)) is not None:
                self.window.add(stamp_to_ns(t.header.stamp), T)

    def at(self, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        """``T_odom_base`` at ``stamp_ns`` (``PoseWindow.at``)."""
        return self.window.at(stamp_ns, tolerance_ns)


class StaticTree(StaticFrames):
    """The static transforms seen on ``tf_static`` (``StaticFrames``)."""

    def add(self, msg: Any) -> None:
        for t in msg.transforms:
            if (T := _matrix(t.transform)) is not None:
                self.set(t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/"), T)


class TfOutbox:
    """The tracker's transforms (see the module docstring); ``available`` is False without tf2_msgs."""

    def __init__(self, node: Node, frames: FrameConvention, map_frame: str, world_frame: str, base_frame: str,
                 camera_frame: str, publish_camera_tf: bool, odom_frame: str = "",
                 odom_tolerance_s: float = 0.05) -> None:
        self.frames, self.map_frame, self.world_frame = frames, map_frame, world_frame
        self.base_frame, self.publish_camera_tf = base_frame, publish_camera_tf
        self.camera_frame = ""
        self.odom_frame, self._odom_tol_ns = odom_frame, int(odom_tolerance_s * 1e9)
        msg_type = tf_message_type()
        self.available = msg_type is not None
        if msg_type is None:
            node.get_logger().warning("tf2_msgs is not installed: publishing no /tf (ROS installs it; with the "
                                      "PyPI wheels run python -m memgs_ros.ros.tf2_msgs_build)")
            return
        self._type = msg_type
        # Relative: /tf in the root namespace; under a namespace (a second drone) <ns>/tf, as Nav2's
        # multi-robot launches remap it, so two graphs on one domain never mix their transforms.
        self.pub = node.create_publisher(msg_type, "tf", tf_qos())
        self.pub_static = node.create_publisher(msg_type, "tf_static", tf_static_qos())
        self.odom: OdomTrack | None = None
        if odom_frame:
            self.odom = OdomTrack(odom_frame, base_frame)
            node.create_subscription(msg_type, "tf", self.odom.add, tf_qos())
        self.statics: StaticTree | None = None
        if not publish_camera_tf:  # the robot publishes the camera: read its mount there
            self.statics = StaticTree()
            node.create_subscription(msg_type, "tf_static", self.statics.add, tf_static_qos())
        self._stamp_ns = node.get_clock().now().nanoseconds

    def mount(self, camera_frame: str) -> np.ndarray | None:
        """The camera's optical frame in the body as TF has it [4, 4] (None: not (yet) on tf_static)."""
        return None if self.statics is None else self.statics.lookup(self.base_frame, camera_frame)

    def set_camera_frame(self, camera_frame: str) -> None:
        """(Re)publish the statics, naming the images' optical frame (the first frame's header),
        once the mount is settled (``frames``)."""
        if not self.available or camera_frame == self.camera_frame:
            return
        self.camera_frame = camera_frame
        statics = [_transform(self.frames.T_map_world, self._stamp_ns, self.map_frame, self.world_frame)]
        if self.publish_camera_tf and camera_frame:
            statics.append(_transform(self.frames.T_base_optical, self._stamp_ns, self.base_frame, camera_frame))
        self.pub_static.publish(self._type(transforms=statics))

    def tracked(self, T_wc: np.ndarray, stamp_ns: int) -> bool:
        """Broadcast a tracked frame's body pose; False when it could not (no tf2_msgs, or no
        odometry near the stamp with an ``odom_frame``)."""
        if not self.available:
            return False
        T_map_base = self.frames.base_in_map(T_wc)
        if self.odom is None:
            tf = _transform(T_map_base, stamp_ns, self.map_frame, self.base_frame)
        else:
            T_odom_base = self.odom.at(stamp_ns, self._odom_tol_ns)
            if T_odom_base is None:
                return False
            tf = _transform(T_map_base @ np.linalg.inv(T_odom_base), stamp_ns, self.map_frame, self.odom_frame)
        self.pub.publish(self._type(transforms=[tf]))
        return True
