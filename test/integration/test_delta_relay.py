"""The lossy delta link the system tests put beside a graph, on real DDS: it forwards the mapper's
deltas to the merger's topic minus every n-th, bytes unchanged."""
from __future__ import annotations

import os
import threading
import time

import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from memgs_ros.orchestration.processes import spin_in_background, stop_spinning  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.testing.delta_relay import DELTA_TOPIC, LOSSY_DELTA_TOPIC, lossy_deltas  # noqa: E402

pytestmark = pytest.mark.ros


def test_relay_drops_every_nth_delta_and_forwards_the_rest(ros_domain_id: int) -> None:
    ns = f"/relay_{os.getpid()}"
    context = rclpy.Context()
    rclpy.init(args=["--ros-args", "-r", f"__ns:={ns}"], context=context, domain_id=ros_domain_id)
    node = rclpy.create_node("relay_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    got: list[int] = []
    all_in = threading.Event()
    sent = 9

    def on_lossy(msg: PointCloud2) -> None:
        got.append(msg.width)
        if len(got) == sent - sent // 3:
            all_in.set()

    node.create_subscription(PointCloud2, LOSSY_DELTA_TOPIC, on_lossy, qos.reliable(50))
    pub = node.create_publisher(PointCloud2, DELTA_TOPIC, qos.reliable(50))
    thread = spin_in_background(executor)
    try:
        with lossy_deltas(ros_domain_id, ns, every=3) as relay:
            # Publish once the relay hears us and we hear it (graph discovery, polled up to 10 s).
            deadline = time.monotonic() + 10.0
            while not (pub.get_subscription_count() >= 1 and relay.readers() >= 1):
                assert time.monotonic() < deadline, "the relay never matched"
                all_in.wait(0.05)
            for i in range(1, sent + 1):
                pub.publish(PointCloud2(width=i))
            assert all_in.wait(20.0), got
            # The 9th, dropped, may still be on its way to the relay when the 6th forwarded arrives here.
            while relay.forwarded + relay.dropped < sent:
                assert time.monotonic() < deadline + 20.0, (relay.forwarded, relay.dropped)
                all_in.wait(0.05)
            assert (relay.forwarded, relay.dropped) == (6, 3)
        assert got == [1, 2, 4, 5, 7, 8]  # the 3rd, 6th and 9th never arrived
    finally:
        stop_spinning(executor, thread)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
