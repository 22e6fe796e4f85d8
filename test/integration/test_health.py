"""Health on /diagnostics: a node's level judged on the current window (core/runtime/health.py), and
the tracker's ERROR when tracking is lost and OK once it relocalises, over real DDS."""
from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from memgs_ros.core.runtime.health import Level, assess


def test_the_level_follows_the_window_not_the_past() -> None:
    before = {"problem.bad_image": 1, "skipped.stale": 3, "tracking_state": "OK"}
    assert assess("tracker", {**before}, before).level is Level.OK  # an old problem: OK now
    h = assess("tracker", {**before, "problem.bad_image": 2}, before)
    assert h.level is Level.WARN and "bad_image" in h.message
    assert assess("tracker", {**before, "skipped.stale": 4}, before).level is Level.WARN
    assert assess("tracker", {**before, "tracking_state": "RECENTLY_LOST"}, before).level is Level.WARN
    lost = assess("tracker", {**before, "tracking_state": "LOST"}, before)
    assert lost.level is Level.ERROR and "lost" in lost.message
    assert assess("merger", {"problem.save_failed": 1}, None).level is Level.WARN  # the first window: all of it


def test_the_mapper_is_in_error_when_its_worker_stops_and_warns_when_behind() -> None:
    ok = {"alive": 1, "insert_queue": 0}
    assert assess("mapper", ok, ok).level is Level.OK
    assert assess("mapper", {**ok, "alive": 0}, ok).level is Level.ERROR
    assert assess("mapper", {**ok, "problem.command_failed": 1}, ok).level is Level.ERROR
    assert assess("mapper", {**ok, "insert_queue": 9}, ok).level is Level.WARN
    assert assess("mapper", {"alive": 0}, None).level is Level.OK  # not started yet: nothing stopped


@pytest.mark.ros
def test_diagnostics_say_lost_and_found_within_a_second(context) -> None:  # noqa: ANN001
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from tracker_harness import TrackerFeed

    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.ros import qos

    feed = TrackerFeed(context)
    node = feed.node
    odometry: list[Odometry] = []
    heard: list[tuple[float, int, str]] = []  # (arrival, level, message) of the tracker's status

    def on_diag(msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name == "memgs/tracker":
                heard.append((time.monotonic(), s.level[0], s.message))

    feed.peer.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos.reliable(10))
    spin_until = feed.spin_until
    try:
        feed.wait_for_inputs()
        frames = list(itertools.islice(generate_frames(parse_spec("synthetic:w=320,h=240,n=60,seed=2")), 8))
        feed.camera(frames[0].camera, frames[0].stamp_ns)
        stamp = frames[0].stamp_ns

        def send(rgb: np.ndarray, depth: np.ndarray) -> str:
            nonlocal stamp
            stamp += 33_333_333
            feed.send(rgb, depth, stamp)
            return str(node.stats.values["tracking_state"])

        for f in frames[:2]:
            assert send(f.rgb, f.depth_m) == "OK"
        # No one reads the odometry yet: no covariance is computed and no odometry built.
        assert node.stats.values["odometry_out"] == 0 and node.tracker is not None
        assert not node.tracker.covariance_wanted
        unread_ok = node.stats.values["state.OK"]
        feed.peer.create_subscription(Odometry, "memgs/odom", odometry.append, qos.reliable(100))
        assert spin_until(node.out.odometry_wanted, 5.0)
        for f in frames[2:4]:
            assert send(f.rgb, f.depth_m) == "OK"
        assert node.tracker.covariance_wanted
        black = np.zeros_like(frames[4].rgb)  # the lens covered: no features, depth still there
        while (state := send(black, frames[4].depth_m)) != "LOST":
            assert state == "RECENTLY_LOST"
        lost_at = time.monotonic()
        assert spin_until(lambda: any(t >= lost_at - 0.5 and lvl == 2 for t, lvl, _ in heard), 1.0), heard[-3:]
        error = next(m for t, lvl, m in heard if lvl == 2)
        assert "lost" in error
        for f in itertools.islice(itertools.cycle(frames[:4]), 20):  # back over the mapped room
            if send(f.rgb, f.depth_m) == "OK":  # relocalised
                break
        assert node.stats.values["tracking_state"] == "OK"
        found_at = time.monotonic()
        assert spin_until(lambda: any(t >= found_at - 0.5 and lvl == 0 for t, lvl, _ in heard), 1.0), heard[-3:]
        assert node.stats.values["resets"] == 1
        # Odometry: tracked frames only (none while coasting or lost), each with a covariance,
        # from the frame a subscriber came on
        assert spin_until(lambda: len(odometry) == node.stats.values["state.OK"] - unread_ok, 2.0), (
            len(odometry), node.stats.values["state.OK"], unread_ok)
        assert node.stats.values["state.RECENTLY_LOST"] > 0 and node.stats.values["state.LOST"] > 0
        covs = [np.array(o.pose.covariance).reshape(6, 6) for o in odometry]
        assert all(np.all(np.linalg.eigvalsh(c) > 0) for c in covs) and len({c[0, 0] for c in covs}) > 1
    finally:
        feed.close()


def test_pose_covariance_grows_with_fewer_points_and_turns_with_the_camera() -> None:
    from scipy.spatial.transform import Rotation

    from memgs_ros.core.geometry.poses import invert_pose
    from memgs_ros.core.tracking.backend.bundle_adjustment import pose_covariance

    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    p_c = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-0.7, 0.7, 200), rng.uniform(1, 4, 200)])
    depth, w = p_c[:, 2].copy(), np.ones(200)
    T_wc = np.eye(4)
    T_wc[:3, :3], T_wc[:3, 3] = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix(), [1.0, 2.0, 0.5]
    p_w = p_c @ T_wc[:3, :3].T + T_wc[:3, 3]
    T_cw = invert_pose(T_wc)
    full = pose_covariance(T_cw, p_w, depth, w, K, 40.0)
    few = pose_covariance(T_cw, p_w[:20], depth[:20], w[:20], K, 40.0)
    assert full is not None and few is not None and np.trace(few) > 5 * np.trace(full)
    assert np.trace(pose_covariance(T_cw, p_w, np.full(200, np.nan), w, K, 40.0)) > np.trace(full)  # no depth
    assert pose_covariance(T_cw, p_w[:2], depth[:2], w[:2], K, 40.0) is None
    # The same view from a camera turned in the world: the covariance turns with it (world frame).
    R0 = Rotation.from_rotvec([0.0, 0.0, 1.0]).as_matrix()
    T0 = np.eye(4)
    T0[:3, :3] = R0
    turned = pose_covariance(invert_pose(T0 @ T_wc), p_w @ R0.T, depth, w, K, 40.0)
    A = np.kron(np.eye(2), R0)
    assert np.allclose(turned, A @ full @ A.T, rtol=1e-6, atol=1e-12)
