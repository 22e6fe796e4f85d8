"""The mapper's live render: a new view when the pose or the map changed, never the same one again
(after the last frame it would share a slow link with the final flush). A real mapper process."""
from __future__ import annotations

import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from test_shutdown_saves import _Peer, _start, _terminate, send_one_keyframe  # noqa: E402

from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.codecs import matrix_to_pose_stamped  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_live_render_skips_an_unchanged_view_of_an_unchanged_map(tmp_path: Path, ros_domain_id: int) -> None:
    log = tmp_path / "mapper.log"
    # Lockstep without acknowledgements: the map does not train, so only the pose can change it.
    params = {"pacing": "lockstep", "render_rate_hz": 20.0, "mapping.min_keyframes": 1, "device": "cpu"}
    proc = _start("memgs_ros.nodes.mapper.node", ros_domain_id, params, log)
    peer = _Peer(ros_domain_id, "mapper")
    renders: list[Image] = []
    try:
        pose_pub = peer.node.create_publisher(PoseStamped, "memgs/pose", qos.reliable(5))
        peer.node.create_subscription(Image, "memgs/render/color", renders.append, qos.reliable(5))
        frame, _, msgs = send_one_keyframe(peer, proc, log)
        stamp = frame.stamp_ns
        peer.spin_until(lambda: int(peer.stats.get("keyframes", "0")) >= 1, proc, log)
        peer.spin_until(lambda: pose_pub.get_subscription_count() > 0, proc, log)
        pose_pub.publish(msgs["pose"])
        peer.spin_until(lambda: len(renders) >= 1, proc, log)
        end = time.monotonic() + 1.5  # 30 ticks of the live view at 20 Hz
        peer.spin_until(lambda: time.monotonic() > end, proc, log)
        assert len(renders) == 1, len(renders)
        pose_pub.publish(matrix_to_pose_stamped(frame.T_wc_gt, stamp + 1, "map"))  # a new frame: a new view
        peer.spin_until(lambda: len(renders) >= 2, proc, log)
        end = time.monotonic() + 1.0
        peer.spin_until(lambda: time.monotonic() > end, proc, log)
        assert len(renders) == 2, len(renders)
        _terminate(proc, log)
    finally:
        if proc.poll() is None:
            proc.kill()
        peer.close()
