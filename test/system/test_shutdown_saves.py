"""SIGTERM (a supervisor, systemd, a launch file ending) saves what a node holds: the merger its
map PLY, the mapper its checkpoint. Real node processes, real DDS."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402

from memgs_ros.core.gaussians.gaussian_map import GaussianMap  # noqa: E402
from memgs_ros.core.map_io.map_delta import DeltaOutbox  # noqa: E402
from memgs_ros.core.map_io.ply import load_ply  # noqa: E402
from memgs_ros.core.mapping import checkpoint  # noqa: E402
from memgs_ros.io.synthetic import generate_frames, parse_spec  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.codecs import matrix_to_pose_stamped, structured_to_pointcloud2  # noqa: E402
from memgs_ros.ros.diagnostics import stats_values  # noqa: E402
from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image  # noqa: E402
from memgs_ros.ros.seed_cloud import encode_seeds  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def _start(module: str, domain: int, params: dict[str, str], log: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", module, "--ros-args"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={v}"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
    return subprocess.Popen(cmd, stdout=open(log, "wb"), stderr=subprocess.STDOUT, env=env)  # noqa: SIM115


class _Peer:
    """A test-side node that publishes inputs and reads a node's stats."""

    def __init__(self, domain: int, node: str) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node("shutdown_test_peer", context=self.ctx)
        self.stats: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, f"memgs/{node}/stats",
                                      lambda m: self.stats.update(stats_values(m)), qos.reliable(5))
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)

    def spin_until(self, cond, proc: subprocess.Popen, log: Path, timeout_s: float = 60.0) -> None:  # noqa: ANN001
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
            if cond():
                return
            assert proc.poll() is None, log.read_text()[-3000:]
        pytest.fail(f"condition not met in {timeout_s} s; stats {self.stats}\n{log.read_text()[-3000:]}")

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _terminate(proc: subprocess.Popen, log: Path) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"no exit within 30 s of SIGTERM:\n{log.read_text()[-3000:]}")
    assert proc.returncode == 0, log.read_text()[-3000:]


def send_one_keyframe(peer: _Peer, proc: subprocess.Popen, log: Path) -> tuple:
    """Publish one synthetic keyframe (its five parts, seeds on a 4-pixel grid) to a mapper once
    it listens: (frame, seed points, the messages sent)."""
    frame = next(iter(generate_frames(parse_spec("synthetic:w=64,h=48,n=1,seed=4"))))
    stamp = frame.stamp_ns
    kf = qos.keyframes()
    pubs = {name: peer.node.create_publisher(t, f"memgs/keyframe/{name}", kf) for name, t in
            (("color", Image), ("depth", Image), ("camera_info", CameraInfo), ("pose", PoseStamped),
             ("seeds", PointCloud2))}
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
    return frame, pts, msgs


def test_merger_saves_its_map_on_sigterm(tmp_path: Path, ros_domain_id: int) -> None:
    ply = tmp_path / "map.ply"
    log = tmp_path / "merger.log"
    proc = _start("memgs_ros.nodes.merger.node", ros_domain_id, {"map_path": str(ply), "save_period_s": 3600.0}, log)
    peer = _Peer(ros_domain_id, "merger")
    try:
        g = GaussianMap(max_sh_degree=0)
        rng = np.random.default_rng(0)
        g.add_from_points(rng.uniform(-1, 1, (300, 3)), rng.uniform(0, 1, (300, 3)), keyframe_id=0, iteration=0)
        records = g.to_records()
        pub = peer.node.create_publisher(PointCloud2, "memgs/mapper/snapshot", qos.latched())
        pub.publish(structured_to_pointcloud2(DeltaOutbox(0, epoch=5).snapshot(records), 1, "map"))
        peer.spin_until(lambda: peer.stats.get("gaussians") == "300", proc, log)
        assert not ply.exists()  # the periodic save is an hour away: only the signal can save it
        _terminate(proc, log)
        back = load_ply(ply)
        assert np.array_equal(np.sort(back.ids), np.sort(records.ids))
        assert np.allclose(back.xyz[np.argsort(back.ids)], records.xyz[np.argsort(records.ids)])
    finally:
        if proc.poll() is None:
            proc.kill()
        peer.close()


def test_mapper_writes_its_checkpoint_on_sigterm(tmp_path: Path, ros_domain_id: int) -> None:
    ck = tmp_path / "mapper.npz"
    log = tmp_path / "mapper.log"
    params = {"checkpoint_path": str(ck), "checkpoint_period_s": 0.0, "render_rate_hz": 0.0,
              "mapping.min_keyframes": 1, "device": "cpu"}
    proc = _start("memgs_ros.nodes.mapper.node", ros_domain_id, params, log)
    peer = _Peer(ros_domain_id, "mapper")
    try:
        frame, pts, msgs = send_one_keyframe(peer, proc, log)
        stamp = frame.stamp_ns
        peer.spin_until(lambda: int(peer.stats.get("iteration", "0")) >= 5, proc, log)
        assert not ck.exists()  # no periodic checkpoints: only the signal can write it
        _terminate(proc, log)
        back = checkpoint.load(ck)
        assert len(back.keyframes) == 1 and back.keyframes[0].stamp_ns == stamp
        assert len(back.gaussians) >= len(pts) - 5 and back.iteration >= 5
        assert back.extra["keyframe_stamps"] == {str(stamp): 0}
    finally:
        if proc.poll() is None:
            proc.kill()
        peer.close()
