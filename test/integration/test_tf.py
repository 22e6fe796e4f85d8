"""REP-103/105 frames and TF: the body's pose in a z-up map, the camera mount, the covariance
carried to the body, and /tf + /tf_static with the standard tf2_msgs/TFMessage on real DDS."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from memgs_ros.core.geometry.frames import OPTICAL_IN_BODY, FrameConvention, FrameError, mount_transform
from memgs_ros.core.geometry.poses import invert_pose, rotmat_to_rotvec
from memgs_ros.errors import ConfigError
from memgs_ros.nodes.params import TrackerParams


def _rot(axis: str, angle: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_euler(axis, angle).as_matrix()


def _T(R: np.ndarray, t) -> np.ndarray:  # noqa: ANN001
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_the_map_is_z_up_at_the_body_and_follows_the_camera() -> None:
    fc = FrameConvention(mount_transform([0, 0, 0, 0, 0, 0]))
    assert np.allclose(fc.base_in_map(np.eye(4)), np.eye(4))  # the first body pose is the map's origin
    # The camera moves 1 m along its optical z (forward) and 0.5 m along its y (down): the body
    # moves 1 m along map x and 0.5 m down map z.
    T = fc.base_in_map(_T(np.eye(3), [0, 0.5, 1.0]))
    assert np.allclose(T[:3, 3], [1.0, 0.0, -0.5]) and np.allclose(T[:3, :3], np.eye(3))
    # Turning left (a yaw, +z in REP-103) is a turn about the optical -y axis.
    T = fc.base_in_map(_T(_rot("y", -0.3), [0, 0, 0]))
    assert np.allclose(rotmat_to_rotvec(T[:3, :3]), [0, 0, 0.3])
    # map -> world_frame is the optical rotation: optical z (forward) is map x, optical y (down) is -z.
    assert np.allclose(fc.T_map_world[:3, :3] @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(fc.T_map_world[:3, :3] @ [0, 1, 0], [0, 0, -1])


def test_a_mounted_camera_moves_the_body_by_its_lever_arm() -> None:
    # Looking 30 degrees down (pitch +0.52 in REP-103), 20 cm ahead of and 10 cm below the body's origin.
    E = mount_transform([0.2, 0.0, -0.1, 0.0, np.deg2rad(30), 0.0])
    assert np.allclose(E[:3, 3], [0.2, 0, -0.1]) and np.allclose(E[:3, :3], _rot("y", np.deg2rad(30)) @ OPTICAL_IN_BODY)
    fc = FrameConvention(E)
    rng = np.random.default_rng(0)
    for _ in range(5):
        T_wc = _T(_rot("xyz", rng.normal(0, 0.4, 3)), rng.normal(0, 1, 3))
        T_mb = fc.base_in_map(T_wc)
        # The camera seen through TF (map -> base -> optical) is the camera seen through the static
        # map -> world_frame and the tracked pose.
        assert np.allclose(T_mb @ E, fc.T_map_world @ T_wc)
    with pytest.raises(FrameError, match="camera_mount"):
        mount_transform([0, 0, 0, 0, float("nan"), 0])
    with pytest.raises(ConfigError, match="distinct"):
        TrackerParams(base_frame="map")


def test_the_covariance_follows_the_body_numerically() -> None:
    """The body pose's covariance equals the camera pose's pushed through the frame change (a
    Monte-Carlo estimate of world-frame perturbations), lever arm included."""
    fc = FrameConvention(mount_transform([0.3, -0.1, 0.05, 0.1, 0.4, -0.2]))
    T_wc = _T(_rot("xyz", [0.2, -0.5, 0.3]), [0.4, -0.2, 1.5])
    A = np.random.default_rng(1).normal(0, 1, (6, 6))
    cov = 1e-6 * (A @ A.T + np.eye(6))
    xs = np.random.default_rng(2).multivariate_normal(np.zeros(6), cov, 20000)
    base = fc.base_in_map(T_wc)
    out = np.empty_like(xs)
    for i, x in enumerate(xs):
        from scipy.spatial.transform import Rotation
        T = T_wc.copy()
        T[:3, :3] = Rotation.from_rotvec(x[3:]).as_matrix() @ T_wc[:3, :3]  # world-frame rotation
        T[:3, 3] = T_wc[:3, 3] + x[:3]
        Tb = fc.base_in_map(T)
        out[i, :3] = Tb[:3, 3] - base[:3, 3]
        out[i, 3:] = rotmat_to_rotvec(Tb[:3, :3] @ base[:3, :3].T)
    mc = np.cov(out.T)
    assert np.allclose(fc.covariance_in_map(cov, T_wc), mc, atol=0.05 * np.abs(mc).max())


def test_tf_and_odometry_on_real_dds(context) -> None:  # noqa: ANN001
    rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        pytest.fail("tf2_msgs is missing: ROS installs it; with the PyPI wheels run "
                    "python -m memgs_ros.ros.tf2_msgs_build (the README's test command does)")
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from tracker_harness import TrackerFeed

    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.ros import qos
    from memgs_ros.ros.codecs import pose_fields_to_matrix, pose_to_matrix, stamp_to_ns
    from memgs_ros.ros.tf import tf_qos, tf_static_qos

    mount = [0.1, 0.0, -0.05, 0.0, 0.2, 0.0]
    names = ("x", "y", "z", "roll", "pitch", "yaw")
    feed = TrackerFeed(context, [Parameter(f"camera_mount_{n}", value=float(v)) for n, v in zip(names, mount)],
                       frame_id="cam_optical")
    node = feed.node
    tf: list = []
    static: list = []
    odom: list[Odometry] = []
    poses: list[PoseStamped] = []
    feed.peer.create_subscription(TFMessage, "/tf", tf.append, tf_qos())
    feed.peer.create_subscription(Odometry, "memgs/odom", odom.append, qos.reliable(100))
    feed.peer.create_subscription(PoseStamped, "memgs/pose", poses.append, qos.reliable(100))
    try:
        feed.wait_for_inputs()
        frames = list(itertools.islice(generate_frames(parse_spec("synthetic:w=320,h=240,n=60,seed=2")), 20))
        feed.camera(frames[0].camera, frames[0].stamp_ns)
        for f in frames:
            feed.send(f.rgb, f.depth_m, f.stamp_ns)
        tracked = node.stats.values["state.OK"]
        assert tracked >= 15
        assert feed.spin_until(lambda: len(tf) >= tracked and len(odom) >= tracked - 1 and len(poses) >= tracked,
                               5.0)
        # A late joiner to /tf_static gets every static transform (transient local, one message).
        late = rclpy.create_node("late", context=context)
        late.create_subscription(TFMessage, "/tf_static", static.append, tf_static_qos())
        feed.ex.add_node(late)
        assert feed.spin_until(lambda: bool(static), 5.0)
        st = {(t.header.frame_id, t.child_frame_id): t for t in static[-1].transforms}
        assert set(st) == {("map", "map_optical"), ("base_link", "cam_optical")}
        E = mount_transform(mount)
        tf_mat = {k: pose_fields_to_matrix(v.transform.translation, v.transform.rotation) for k, v in st.items()}
        assert np.allclose(tf_mat[("base_link", "cam_optical")], E, atol=1e-9)
        assert np.allclose(tf_mat[("map", "map_optical")], E, atol=1e-9)
        # /tf: map -> base_link for every tracked frame, stamped with the frame's stamp.
        sent = [t for m in tf for t in m.transforms]
        assert all((t.header.frame_id, t.child_frame_id) == ("map", "base_link") for t in sent)
        stamps = {f.stamp_ns for f in frames}
        assert len(sent) == tracked and all(stamp_to_ns(t.header.stamp) in stamps for t in sent)
        assert node.stats.values["tf_out"] == tracked
        first = sent[0].transform
        assert np.allclose([first.translation.x, first.translation.y, first.translation.z], 0, atol=1e-9)
        assert np.isclose(first.rotation.w, 1.0)  # the body's first pose: level, at the origin: z up
        # The tree closes: map -> base_link -> camera == map -> map_optical -> camera (memgs/pose).
        by_stamp = {stamp_to_ns(p.header.stamp): pose_to_matrix(p.pose) for p in poses}
        for t in sent:
            T_mb = pose_fields_to_matrix(t.transform.translation, t.transform.rotation)
            assert np.allclose(T_mb @ E, E @ by_stamp[stamp_to_ns(t.header.stamp)], atol=1e-6)
        # Odometry: the body in map, child base_link, the same pose as TF.
        tf_by_stamp = {stamp_to_ns(t.header.stamp): t.transform for t in sent}
        for o in odom:
            assert (o.header.frame_id, o.child_frame_id) == ("map", "base_link")
            ref = tf_by_stamp[stamp_to_ns(o.header.stamp)]
            assert np.isclose(o.pose.pose.position.x, ref.translation.x)
            assert np.isclose(o.pose.pose.orientation.z, ref.rotation.z)
        assert poses[0].header.frame_id == "map_optical"
        T_last = invert_pose(by_stamp[frames[0].stamp_ns]) @ by_stamp[max(by_stamp)]
        assert np.linalg.norm(T_last[:3, 3]) > 0.01  # the camera moved: the checks above saw motion
    finally:
        feed.close()


def test_the_mount_is_read_from_the_robots_tf_static(context) -> None:  # noqa: ANN001
    """With publish_camera_tf false the robot publishes the camera (base_link -> camera_link ->
    the optical frame, as a URDF and realsense-ros do): the tracker reads the mount from there and
    anchors map by it, publishing no camera transform of its own."""
    rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from geometry_msgs.msg import TransformStamped
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from tf2_msgs.msg import TFMessage
    from tracker_harness import TrackerFeed

    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.ros import qos
    from memgs_ros.ros.codecs import pose_to_matrix, set_pose_fields, stamp_to_ns
    from memgs_ros.ros.tf import tf_static_qos

    def transform(parent: str, child: str, T: np.ndarray) -> TransformStamped:
        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = parent, child
        set_pose_fields(t.transform.translation, t.transform.rotation, T)
        return t

    link = mount_transform([0.2, 0.0, 0.1, 0.0, 0.3, 0.0]) @ invert_pose(_T(OPTICAL_IN_BODY, [0, 0, 0]))
    optical = _T(OPTICAL_IN_BODY, [0.0, 0.015, 0.0])  # camera_link -> its colour optical frame
    E = link @ optical
    feed = TrackerFeed(context, [Parameter("publish_camera_tf", value=False)], frame_id="cam_optical")
    robot = rclpy.create_node("robot_state_publisher", context=context)
    robot_static = robot.create_publisher(TFMessage, "/tf_static", tf_static_qos())
    robot_static.publish(TFMessage(transforms=[transform("base_link", "camera_link", link),
                                               transform("camera_link", "cam_optical", optical)]))
    feed.ex.add_node(robot)
    odom: list[Odometry] = []
    feed.peer.create_subscription(Odometry, "memgs/odom", odom.append, qos.reliable(100))
    statics: list = []
    feed.peer.create_subscription(TFMessage, "/tf_static", statics.append, tf_static_qos())
    try:
        feed.wait_for_inputs()
        assert feed.spin_until(lambda: feed.node.out.tf.mount("cam_optical") is not None, 10.0)
        frames = list(itertools.islice(generate_frames(parse_spec("synthetic:w=320,h=240,n=60,seed=2")), 8))
        feed.camera(frames[0].camera, frames[0].stamp_ns)
        for f in frames:
            feed.send(f.rgb, f.depth_m, f.stamp_ns)
        assert feed.node.out.mount_settled and np.allclose(feed.node.out.frames.T_base_optical, E, atol=1e-6)
        assert feed.spin_until(lambda: len(odom) >= 7 and any(
            t.child_frame_id == "map_optical" for m in statics for t in m.transforms), 5.0)
        ours = [t for m in statics for t in m.transforms if t.header.frame_id == "map"]
        assert [t.child_frame_id for t in ours] == ["map_optical"]  # the camera's is the robot's
        assert not any(t.header.frame_id == "base_link" and t.child_frame_id == "cam_optical"
                       for m in statics for t in m.transforms)
        by_stamp = {f.stamp_ns: f for f in frames}
        first = pose_to_matrix(odom[0].pose.pose)
        assert stamp_to_ns(odom[0].header.stamp) in by_stamp and np.isfinite(first).all()
        assert feed.node.stats.values["odometry_withheld"] == 0  # the robot's statics came first
    finally:
        feed.close()
        robot.destroy_node()


def test_odometry_from_tf_is_interpolated_to_the_frame_and_never_extrapolated() -> None:
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from types import SimpleNamespace

    from geometry_msgs.msg import TransformStamped

    from memgs_ros.ros.codecs import set_pose_fields, set_stamp
    from memgs_ros.ros.tf import OdomTrack

    def tf(stamp_ns: int, x: float, yaw: float, parent: str = "odom") -> TransformStamped:
        t = TransformStamped()
        set_stamp(t.header.stamp, stamp_ns)
        t.header.frame_id, t.child_frame_id = parent, "base_link"
        set_pose_fields(t.transform.translation, t.transform.rotation, _T(_rot("z", yaw), [x, 0, 0]))
        return t

    track = OdomTrack("odom", "base_link")
    broken = tf(1_060_000_000, 0.0, 0.0)
    broken.transform.translation.x = float("nan")  # another node's bad message: skipped, no crash
    track.add(SimpleNamespace(transforms=[tf(1_000_000_000, 0.0, 0.0), tf(1_100_000_000, 1.0, 0.2),
                                          tf(1_050_000_000, 9.0, 0.0, parent="map"), broken]))  # map: ignored
    assert len(track.window.stamps) == 2
    mid = track.at(1_050_000_000, 10_000_000)
    assert np.allclose(mid[:3, 3], [0.5, 0, 0]) and np.allclose(rotmat_to_rotvec(mid[:3, :3]), [0, 0, 0.1])
    assert np.allclose(track.at(1_120_000_000, 30_000_000)[:3, 3], [1.0, 0, 0])  # nearest, within tolerance
    assert track.at(1_200_000_000, 30_000_000) is None  # past the odometry: no extrapolation
    track.add(SimpleNamespace(transforms=[tf(500_000_000, 3.0, 0.0)]))  # time went back (a looped bag)
    assert track.at(1_050_000_000, 10_000_000) is None and np.allclose(track.at(500_000_000, 0)[:3, 3], [3, 0, 0])


def test_with_an_odom_frame_the_tracker_broadcasts_map_to_odom(context) -> None:  # noqa: ANN001
    """A flight controller publishes odom -> base_link; the tracker then broadcasts map -> odom so
    that map -> odom -> base_link is its own body pose (REP-105)."""
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from geometry_msgs.msg import PoseStamped, TransformStamped
    from rclpy.parameter import Parameter
    from tf2_msgs.msg import TFMessage
    from tracker_harness import TrackerFeed

    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.ros import qos
    from memgs_ros.ros.codecs import pose_fields_to_matrix, pose_to_matrix, set_pose_fields, set_stamp, stamp_to_ns
    from memgs_ros.ros.tf import tf_qos

    feed = TrackerFeed(context, [Parameter("odom_frame", value="odom")])
    heard: list = []
    poses: list[PoseStamped] = []
    pub = feed.peer.create_publisher(TFMessage, "/tf", tf_qos())
    feed.peer.create_subscription(TFMessage, "/tf", heard.append, tf_qos())
    feed.peer.create_subscription(PoseStamped, "memgs/pose", poses.append, qos.reliable(100))
    fc = feed.node.out.frames
    try:
        feed.wait_for_inputs()
        assert feed.spin_until(lambda: pub.get_subscription_count() >= 2)  # the tracker's and ours
        frames = list(itertools.islice(generate_frames(parse_spec("synthetic:w=320,h=240,n=60,seed=2")), 6))
        feed.camera(frames[0].camera, frames[0].stamp_ns)
        drift = {}
        for i, f in enumerate(frames):
            T = _T(_rot("z", 0.01 * i), [0.02 * i, 0.0, 0.0])  # the flight controller's drifting odometry
            drift[f.stamp_ns] = T
            t = TransformStamped()
            set_stamp(t.header.stamp, f.stamp_ns)
            t.header.frame_id, t.child_frame_id = "odom", "base_link"
            set_pose_fields(t.transform.translation, t.transform.rotation, T)
            pub.publish(TFMessage(transforms=[t]))
            assert feed.spin_until(lambda s=f.stamp_ns: s in feed.node.out.tf.odom.window.stamps, 5.0)  # the tracker has it
            feed.send(f.rgb, f.depth_m, f.stamp_ns)
        tracked = feed.node.stats.values["tf_out"]
        assert tracked >= 5 and feed.node.stats.values["tf_no_odom"] == 0
        assert feed.spin_until(lambda: len(poses) >= tracked and sum(
            t.header.frame_id == "map" for m in heard for t in m.transforms) >= tracked, 5.0)
        ours = [t for m in heard for t in m.transforms if t.header.frame_id == "map"]
        assert all(t.child_frame_id == "odom" for t in ours)
        camera = {stamp_to_ns(p.header.stamp): pose_to_matrix(p.pose) for p in poses}
        for t in ours:  # map -> odom -> base_link is the tracker's body pose
            T_map_odom = pose_fields_to_matrix(t.transform.translation, t.transform.rotation)
            stamp = stamp_to_ns(t.header.stamp)
            assert np.allclose(T_map_odom @ drift[stamp], fc.base_in_map(camera[stamp]), atol=1e-6)
    finally:
        feed.close()
