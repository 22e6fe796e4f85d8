"""The tracker's TF (REP-103/105): ``map -> base_link`` (or ``map -> odom``) per tracked frame on ``tf``,
``map -> <world_frame>`` and the camera's mount on ``tf_static``. What each frame is and the parameters:
README, "Frames and TF"; docs/design.md's topic table. The wire (QoS, messages, the listeners) is
``ros/tf.py``'s; without ``tf2_msgs`` the node says so once and publishes no TF.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
from rclpy.node import Node

from memgs_ros.core.geometry.frames import FrameConvention, MountWait
from memgs_ros.ros.tf import (
    TF_MISSING,
    OdomTrack,
    StaticTree,
    tf_message_type,
    tf_qos,
    tf_static_qos,
    transform_msg,
)

__all__ = ["TfOutbox"]


class TfOutbox:
    """The tracker's transforms (see the module docstring); ``available`` is False without tf2_msgs."""

    def __init__(self, node: Node, params: Any) -> None:
        """``params``: the node's TrackerParams (frames, mount, odometry)."""
        self.frames: FrameConvention = params.frame_convention()
        self.map_frame, self.world_frame, self.base_frame = params.map_frame, params.world_frame, params.base_frame
        self.publish_camera_tf, self.camera_frame = params.publish_camera_tf, ""
        self.odom_frame, self._odom_tol_ns = params.odom_frame, int(params.odom_tolerance_s * 1e9)
        self._log = node.get_logger()
        msg_type = tf_message_type()
        self.available = msg_type is not None
        # Where the robot publishes the camera, its mount is read from tf_static (within camera_mount_wait_s).
        self.mount_wait = MountWait(int(params.camera_mount_wait_s * 1e9),
                                    settled=msg_type is None or params.publish_camera_tf)
        if msg_type is None:
            self._log.warning(TF_MISSING)
            return
        self._type = msg_type
        # Relative: /tf in the root namespace; under a namespace (a second drone) <ns>/tf, as Nav2's
        # multi-robot launches remap it, so two graphs on one domain never mix their transforms.
        self.pub = node.create_publisher(msg_type, "tf", tf_qos())
        self.pub_static = node.create_publisher(msg_type, "tf_static", tf_static_qos())
        self.odom: OdomTrack | None = None
        if self.odom_frame:
            self.odom = OdomTrack(self.odom_frame, self.base_frame)
            node.create_subscription(msg_type, "tf", self.odom.add, tf_qos())
        self.statics: StaticTree | None = None
        if not self.publish_camera_tf:  # the robot publishes the camera: read its mount there
            self.statics = StaticTree()
            node.create_subscription(msg_type, "tf_static", self.statics.add, tf_static_qos())
        self._stamp_ns = node.get_clock().now().nanoseconds

    def settle_mount(self, camera_frame: str) -> bool:
        """Whether the camera's mount is settled (``MountWait``); from tf_static when it has it (the
        frames then follow it), else from the parameters after the wait (warned)."""
        E = self.mount(camera_frame) if not self.mount_wait.settled else None
        how = self.mount_wait.settle(time.monotonic_ns(), E)
        if how == "tf" and E is not None:
            self.frames = FrameConvention(E)
            self._log.info(f"camera mount from tf_static: {self.base_frame} -> {camera_frame} at "
                           f"{np.round(E[:3, 3], 3).tolist()} m")
        elif how == "parameters":
            self._log.warning(f"no {self.base_frame} -> {camera_frame} on tf_static within the wait: using the "
                              "camera_mount_* parameters (set publish_camera_tf true if nothing publishes it)")
        return self.mount_wait.settled

    def mount(self, camera_frame: str) -> np.ndarray | None:
        """The camera's optical frame in the body as TF has it [4, 4] (None: not (yet) on tf_static)."""
        return None if self.statics is None else self.statics.lookup(self.base_frame, camera_frame)

    def set_camera_frame(self, camera_frame: str) -> None:
        """(Re)publish the statics, naming the images' optical frame (the first frame's header),
        once the mount is settled (``frames``)."""
        if not self.available or camera_frame == self.camera_frame:
            return
        self.camera_frame = camera_frame
        statics = [transform_msg(self.frames.T_map_world, self._stamp_ns, self.map_frame, self.world_frame)]
        if self.publish_camera_tf and camera_frame:
            statics.append(transform_msg(self.frames.T_base_optical, self._stamp_ns, self.base_frame, camera_frame))
        self.pub_static.publish(self._type(transforms=statics))

    def tracked(self, T_wc: np.ndarray, stamp_ns: int) -> bool:
        """Broadcast a tracked frame's body pose; False when it could not (no tf2_msgs, or no
        odometry near the stamp with an ``odom_frame``)."""
        if not self.available:
            return False
        T_map_base = self.frames.base_in_map(T_wc)
        if self.odom is None:
            tf = transform_msg(T_map_base, stamp_ns, self.map_frame, self.base_frame)
        else:
            T_odom_base = self.odom.at(stamp_ns, self._odom_tol_ns)
            if T_odom_base is None:
                return False
            tf = transform_msg(T_map_base @ np.linalg.inv(T_odom_base), stamp_ns, self.map_frame, self.odom_frame)
        self.pub.publish(self._type(transforms=[tf]))
        return True
