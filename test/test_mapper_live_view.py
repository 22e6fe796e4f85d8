"""The mapper's live render: a new view when the pose or the map changed, never the same one again
(after the last frame it would share a slow link with the final flush). A real mapper process."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402
from test_shutdown_saves import _Peer, _start, _terminate  # noqa: E402

from memgs_ros.io.synthetic import generate_frames, parse_spec  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.codecs import (  # noqa: E402
    camera_to_camera_info, depth_to_image, matrix_to_pose_stamped, numpy_to_image, structured_to_pointcloud2,
)
from memgs_ros.ros.seed_cloud import encode_seeds  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_live_render_skips_an_unchanged_view_of_an_unchanged_map(tmp_path: Path, ros_domain_id: int) -> None:
    log = tmp_path / "mapper.log"
    # Lockstep without acknowledgements: the map does not train, so only the pose can change it.
    params = {"lockstep": True, "render_rate_hz": 20.0, "mapping.min_keyframes": 1,
              "device": "cpu"}
    proc = _start("memgs_ros.nodes.mapper", ros_domain_id, params, log)
    peer = _Peer(ros_domain_id, "mapper")
    renders: list[Image] = []
    try:
        frame = next(iter(generate_frames(parse_spec("synthetic:w=64,h=48,n=1,seed=4"))))
        stamp = frame.stamp_ns
        kf = qos.keyframes()
        pubs = {name: peer.node.create_publisher(t, f"memgs/keyframe/{name}", kf) for name, t in
                (("color", Image), ("depth", Image), ("camera_info", CameraInfo), ("pose", PoseStamped),
                 ("seeds", PointCloud2))}
        pose_pub = peer.node.create_publisher(PoseStamped, "memgs/pose", qos.reliable(5))
        peer.node.create_subscription(Image, "memgs/render/color", renders.append, qos.reliable(5))
        v, u = np.mgrid[2:48:4, 2:64:4]
        d = frame.depth_m[v.ravel(), u.ravel()]
        pts = frame.camera.backproject(u.ravel(), v.ravel(), d) @ frame.T_wc_gt[:3, :3].T + frame.T_wc_gt[:3, 3]
        cols = frame.rgb[v.ravel(), u.ravel()] / 255.0
        msgs = {
            "color": numpy_to_image(frame.rgb, "rgb8", stamp, "cam"),
            "depth": depth_to_image(frame.depth_m, "32FC1", stamp, "cam"),
            "camera_info": camera_to_camera_info(frame.camera, stamp, "cam"),
            "pose": matrix_to_pose_stamped(frame.T_wc_gt, stamp, "map"),
            "seeds": structured_to_pointcloud2(encode_seeds(pts, cols, np.zeros(len(pts), np.uint8)), stamp, "map"),
        }
        peer.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), proc, log)
        for name, p in pubs.items():
            p.publish(msgs[name])
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
