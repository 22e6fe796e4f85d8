"""The runner's observer over real DDS: the corrected path it decodes only now and then."""
from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")

from nav_msgs.msg import Path as NavPath  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402

from memgs_ros.orchestration.graph_watch import GraphObserver  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.codecs import matrix_to_pose_stamped  # noqa: E402

pytestmark = [pytest.mark.ros]


def _path(poses: dict[int, np.ndarray]) -> NavPath:
    msg = NavPath()
    msg.header.frame_id = "map"
    msg.poses = [matrix_to_pose_stamped(T, stamp, "map") for stamp, T in poses.items()]
    return msg


def _translation(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_the_newest_path_is_decoded_at_the_end_and_older_corrections_kept(context) -> None:
    """The first path is decoded as it comes; a second within the decode period waits, serialized,
    until corrected_poses() (the run's end); poses that left the path keep their last correction."""
    obs = GraphObserver(context)
    talker = Node("path_talker", context=context)
    pub = talker.create_publisher(NavPath, "memgs/path", qos.reliable(5))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(obs.node)
    executor.add_node(talker)

    def spin_until(done, what: str, timeout_s: float = 20.0) -> None:  # noqa: ANN001
        end = time.monotonic() + timeout_s
        while not done():
            assert time.monotonic() < end, f"timed out waiting for {what}"
            executor.spin_once(timeout_sec=0.05)

    try:
        spin_until(lambda: pub.get_subscription_count() > 0, "the observer's subscription")
        pub.publish(_path({1: _translation(0.1), 2: _translation(0.2)}))
        spin_until(lambda: len(obs.corrected) == 2, "the first path, decoded on arrival")
        # Pose 2 corrected again, pose 1 out of the path's window, pose 3 new.
        pub.publish(_path({2: _translation(0.25), 3: _translation(0.3)}))
        spin_until(lambda: obs._path_raw is not None, "the second path, kept serialized")
        assert len(obs.corrected) == 2  # not decoded yet: within the decode period
        poses = obs.corrected_poses()
        assert sorted(poses) == [1, 2, 3]
        assert [poses[s][0, 3] for s in (1, 2, 3)] == pytest.approx([0.1, 0.25, 0.3])
        assert obs._path_raw is None  # decoded once
    finally:
        executor.shutdown()
        talker.destroy_node()
        obs.node.destroy_node()
