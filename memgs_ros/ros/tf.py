"""TF on the wire, for every node that broadcasts or listens (tracker, merger): tf2_ros's QoS,
``tf2_msgs/TFMessage`` where installed, a transform message of a [4, 4] matrix and back, and two
listeners: the ``odom -> base`` track a flight controller publishes (``OdomTrack``) and the static
tree (``StaticTree``). Topics are relative (``tf``, ``tf_static``): ``<namespace>/tf`` under a
namespace, as multi-robot Nav2 launches remap them, so two graphs never mix their transforms.

``tf2_msgs`` comes with ROS; where the PyPI wheels stand in for it, ``python -m
memgs_ros.ros.tf2_msgs_build`` generates it.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import Transform, TransformStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from memgs_ros.core.geometry.transform_buffers import PoseWindow, StaticFrames
from memgs_ros.errors import MessageError
from memgs_ros.ros.codecs import pose_fields_to_matrix, set_pose_fields, set_stamp, stamp_to_ns

__all__ = ["TF_MISSING", "OdomTrack", "StaticTree", "tf_message_type", "tf_qos", "tf_static_qos",
           "transform_matrix", "transform_msg"]

# Said once by the tracker, and by ``memgs doctor``, where tf_message_type() is None.
TF_MISSING = ("tf2_msgs is missing: the tracker publishes no /tf (apt's ROS has it; with the PyPI wheels run "
              "python -m memgs_ros.ros.tf2_msgs_build)")


def tf_message_type() -> Any | None:
    """``tf2_msgs/msg/TFMessage``, or None where it is not installed (or does not import: a
    generated package without its type support)."""
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


def transform_msg(T: np.ndarray, stamp_ns: int, parent: str, child: str) -> TransformStamped:
    msg = TransformStamped()
    set_stamp(msg.header.stamp, stamp_ns)
    msg.header.frame_id, msg.child_frame_id = parent, child
    set_pose_fields(msg.transform.translation, msg.transform.rotation, T)
    return msg


def transform_matrix(tf: Transform) -> np.ndarray | None:
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
            if ours and (T := transform_matrix(t.transform)) is not None:
                self.window.add(stamp_to_ns(t.header.stamp), T)

    def at(self, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        """``T_odom_base`` at ``stamp_ns`` (``PoseWindow.at``)."""
        return self.window.at(stamp_ns, tolerance_ns)


class StaticTree(StaticFrames):
    """The static transforms seen on ``tf_static`` (``StaticFrames``)."""

    def add(self, msg: Any) -> None:
        for t in msg.transforms:
            if (T := transform_matrix(t.transform)) is not None:
                self.set(t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/"), T)
