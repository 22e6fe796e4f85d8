"""A TrackerNode under test, fed RGB-D frames over real DDS by a peer node on one executor.

    feed = TrackerFeed(context, [Parameter("autostart", value=False)])
    feed.wait_for_inputs(); feed.send(frame.rgb, frame.depth_m, frame.stamp_ns)
    ...
    feed.close()

The tracker listens on ``color/image_raw``, ``depth/image_raw`` and ``color/camera_info`` (exact
pairing, no staleness: every frame is taken); ``send`` returns once the tracker has answered the
frame on ``memgs/tracker/processed``. Import rclpy-dependent tests' modules only after
``pytest.importorskip("rclpy")``.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.nodes.tracker.node import TrackerNode
from memgs_ros.ros import qos
from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image

INPUT_PARAMS = (("color_topic", "color/image_raw"), ("depth_topic", "depth/image_raw"),
                ("camera_info_topic", "color/camera_info"), ("sync", "exact"), ("max_frame_age_s", 0.0))


class TrackerFeed:
    def __init__(self, context: Any, params: Sequence[Parameter] = (), frame_id: str = "cam") -> None:
        self.frame_id = frame_id
        self.node = TrackerNode(context=context, parameter_overrides=[
            *(Parameter(k, value=v) for k, v in INPUT_PARAMS), *params])
        self.peer = rclpy.create_node("feeder", context=context)
        self.color = self.peer.create_publisher(Image, "color/image_raw", qos.reliable(50))
        self.depth = self.peer.create_publisher(Image, "depth/image_raw", qos.reliable(50))
        self.info = self.peer.create_publisher(CameraInfo, "color/camera_info", qos.reliable(5))
        self.processed: list[Header] = []
        self.peer.create_subscription(Header, "memgs/tracker/processed", self.processed.append, qos.reliable(100))
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.peer)
        self.sent = 0

    def spin_until(self, cond: Callable[[], Any], timeout_s: float = 20.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.02)
            if cond():
                return True
        return False

    def inputs_matched(self) -> bool:
        return bool(self.color.get_subscription_count() and self.depth.get_subscription_count()
                    and self.info.get_subscription_count())

    def wait_for_inputs(self) -> None:
        """The tracker subscribes to all three inputs and has its kernels in."""
        assert self.spin_until(self.inputs_matched) and self.node.wait_until_warm(120)

    def camera(self, camera: PinholeCamera, stamp_ns: int) -> None:
        self.info.publish(camera_to_camera_info(camera, stamp_ns, self.frame_id))

    def send(self, rgb: np.ndarray, depth_m: np.ndarray, stamp_ns: int) -> None:
        """Publish one frame; return once the tracker answered it."""
        self.color.publish(numpy_to_image(rgb, "rgb8", stamp_ns, self.frame_id))
        self.depth.publish(depth_to_image(depth_m, "32FC1", stamp_ns, self.frame_id))
        self.sent += 1
        assert self.spin_until(lambda n=self.sent: len(self.processed) >= n), f"frame {self.sent} was never answered"

    def close(self) -> None:
        self.node.close()
        self.ex.shutdown()
        self.node.destroy_node()
        self.peer.destroy_node()
