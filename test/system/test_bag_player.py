"""bag_player: lockstep and real-time replay over DDS, in-process and as a separate process."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

import rclpy  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Bool, Header  # noqa: E402

from memgs_ros.core.geometry.camera import PinholeCamera  # noqa: E402
from memgs_ros.core.geometry.frame import Frame  # noqa: E402
from memgs_ros.core.geometry.poses import pose_from_tq  # noqa: E402
from memgs_ros.errors import ConfigError, DataError  # noqa: E402
from memgs_ros.io.image_decoding import decode_camera_info, decode_depth, decode_rgb, image_to_numpy  # noqa: E402
from memgs_ros.nodes.bag_player.node import BagPlayer  # noqa: E402
from memgs_ros.ros import codecs, qos  # noqa: E402

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[2]
CAM = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
KINDS = ("color", "depth", "info", "gt")


def make_frames(n: int, period_ns: int = 33_333_333, start_ns: int = 1_000_000_000) -> list[Frame]:
    rng = np.random.default_rng(n)
    return [
        Frame(
            stamp_ns=start_ns + i * period_ns,
            rgb=rng.integers(0, 256, (CAM.height, CAM.width, 3), dtype=np.uint8),
            depth_m=rng.uniform(0.5, 4.0, (CAM.height, CAM.width)).astype(np.float32),
            camera=CAM,
            T_wc_gt=pose_from_tq(np.array([0.1 * i, 0.0, 1.0]), np.array([0.0, 0.0, np.sin(0.05 * i), np.cos(0.05 * i)])),
        )
        for i in range(n)
    ]


class Receiver(Node):
    """Subscribes to everything the player publishes; acks a stamp once all four messages are in."""

    def __init__(self, context: rclpy.Context, ack: bool = True, namespace: str = "") -> None:
        super().__init__("receiver", context=context, namespace=namespace)
        self.ack = ack
        self.color: list[tuple[int, Image]] = []
        self.depth: list[tuple[int, Image]] = []
        self.info: list[tuple[int, CameraInfo]] = []
        self.gt: list[tuple[int, PoseStamped]] = []
        self.arrival_s: list[float] = []
        self.done: list[bool] = []
        self.acked: list[int] = []
        self.sensor_qos_count = 0
        self._parts: dict[int, set[str]] = {}
        self._ack_pub = self.create_publisher(Header, "memgs/frame_ack", qos.reliable(10))
        self.create_subscription(Image, "color/image_raw", lambda m: self._got("color", m), qos.reliable(10))
        self.create_subscription(Image, "depth/image_raw", lambda m: self._got("depth", m), qos.reliable(10))
        self.create_subscription(CameraInfo, "color/camera_info", lambda m: self._got("info", m), qos.reliable(10))
        self.create_subscription(PoseStamped, "groundtruth/pose", lambda m: self._got("gt", m), qos.reliable(10))
        self.create_subscription(Bool, "memgs/player/done", lambda m: self.done.append(m.data), qos.latched())
        # What a tracker does: sensor-data QoS must receive from the player's RELIABLE publisher.
        self.create_subscription(Image, "color/image_raw", self._got_sensor, qos.sensor())

    def _got_sensor(self, msg: Image) -> None:
        self.sensor_qos_count += 1

    def _got(self, kind: str, msg: object) -> None:
        stamp = codecs.stamp_to_ns(msg.header.stamp)
        getattr(self, kind).append((stamp, msg))
        if kind == "color":
            self.arrival_s.append(time.monotonic())
        parts = self._parts.setdefault(stamp, set())
        parts.add(kind)
        if self.ack and parts == set(KINDS):
            self._ack_pub.publish(Header(stamp=msg.header.stamp, frame_id="test"))
            self.acked.append(stamp)


def _params(**kw: object) -> list[Parameter]:
    kw.setdefault("start_delay_s", 5.0)
    return [Parameter(k, value=v) for k, v in kw.items()]


def play_in_process(frames: Iterable[Frame], domain_id: int, ack: bool = True, timeout_s: float = 30.0,
                    **params: object) -> tuple[BagPlayer, Receiver]:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=ctx)
    player = receiver = None
    try:
        receiver = Receiver(ctx, ack=ack)
        player = BagPlayer(frames, context=ctx, parameter_overrides=_params(**params))
        executor.add_node(receiver)
        executor.add_node(player)
        executor.spin_until_future_complete(player.finished, timeout_sec=timeout_s)
        assert player.finished.done(), f"player did not finish within {timeout_s} s"
        end = time.monotonic() + 2.0
        while not receiver.done and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        return player, receiver
    finally:
        executor.shutdown()
        for node in (player, receiver):
            if node is not None:
                node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _assert_frame_equal(receiver: Receiver, i: int, frame: Frame, stamp_ns: int) -> None:
    s, img = receiver.color[i]
    assert s == stamp_ns and img.encoding == "rgb8" and img.header.frame_id == "camera_color_optical_frame"
    np.testing.assert_array_equal(decode_rgb(img), frame.rgb)
    s, dimg = receiver.depth[i]
    assert s == stamp_ns and dimg.encoding == "32FC1"
    np.testing.assert_array_equal(decode_depth(dimg), frame.depth_m)
    assert receiver.info[i][0] == stamp_ns and decode_camera_info(receiver.info[i][1]) == CAM
    s, pose = receiver.gt[i]
    assert s == stamp_ns and pose.header.frame_id == "world"
    np.testing.assert_allclose(codecs.pose_to_matrix(pose.pose), frame.T_wc_gt, atol=1e-9)


def test_lockstep_delivers_every_frame_once_in_order(ros_domain_id: int) -> None:
    frames = make_frames(8)
    player, rx = play_in_process(frames, ros_domain_id, pacing="lockstep")
    stamps = [f.stamp_ns for f in frames]
    for kind in KINDS:
        assert [s for s, _ in getattr(rx, kind)] == stamps, kind
    assert rx.acked == stamps
    for i, f in enumerate(frames):
        _assert_frame_equal(rx, i, f, f.stamp_ns)
    assert rx.done == [True] and player.finished.result() is True
    assert rx.sensor_qos_count > 0


def test_loop_keeps_stamps_increasing_and_stops_at_max_frames(ros_domain_id: int) -> None:
    frames = make_frames(4, period_ns=100_000_000)
    _, rx = play_in_process(frames, ros_domain_id, pacing="lockstep", loop=True, max_frames=10)
    got = [s for s, _ in rx.color]
    # Each pass is shifted by its span (0.3 s) plus one period (0.1 s).
    expected = [frames[0].stamp_ns + k * 100_000_000 for k in range(10)]
    assert got == expected
    for k in range(10):
        _assert_frame_equal(rx, k, frames[k % 4], expected[k])
    assert rx.done == [True]


def test_real_time_paces_by_stamps_over_rate(ros_domain_id: int) -> None:
    frames = make_frames(6, period_ns=100_000_000)  # 0.5 s of stamps
    _, rx = play_in_process(frames, ros_domain_id, pacing="live", rate=2.0)
    assert [s for s, _ in rx.color] == [f.stamp_ns for f in frames]
    span = rx.arrival_s[-1] - rx.arrival_s[0]
    # 0.25 s at x2 (unpaced it would be a few ms); first-message latency may eat a little of it,
    # a loaded machine may add delay.
    assert 0.15 <= span < 2.5, span
    assert rx.done == [True]


def test_lockstep_without_acks_times_out_and_goes_on(ros_domain_id: int) -> None:
    frames = make_frames(3)
    player, rx = play_in_process(frames, ros_domain_id, ack=False, pacing="lockstep", ack_timeout_s=0.2)
    assert [s for s, _ in rx.color] == [f.stamp_ns for f in frames]
    assert player.acks.timeouts == 3 and player.stats.values["frames_published"] == 3 and rx.done == [True]


class Bystander(Node):
    """Reads the frames and could ack (a Rerun bridge beside the tracker), but acks nothing."""

    def __init__(self, context: rclpy.Context) -> None:
        super().__init__("bystander", context=context)
        self.color: list[int] = []
        self.create_publisher(Header, "memgs/frame_ack", qos.reliable(10))
        self.create_subscription(Image, "color/image_raw", lambda m: self.color.append(codecs.stamp_to_ns(m.header.stamp)),
                                 qos.reliable(10))
        self.create_subscription(CameraInfo, "color/camera_info", lambda m: None, qos.reliable(10))


def _play_with_late_receiver(frames: list[Frame], domain_id: int, receiver_after_s: float | None,
                             **params: object) -> tuple[BagPlayer, Bystander, Receiver | None]:
    """A bystander reads the frames from the start; the acking receiver appears only after
    ``receiver_after_s`` (never when None)."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=ctx)
    nodes: list[Node] = []
    receiver = None
    try:
        bystander = Bystander(ctx)
        player = BagPlayer(frames, context=ctx, parameter_overrides=_params(**params))
        nodes += [bystander, player]
        executor.add_node(bystander)
        executor.add_node(player)
        t0 = time.monotonic()
        while not player.finished.done() and time.monotonic() - t0 < 30.0:
            if receiver is None and receiver_after_s is not None and time.monotonic() - t0 >= receiver_after_s:
                receiver = Receiver(ctx)
                nodes.append(receiver)
                executor.add_node(receiver)
            executor.spin_once(timeout_sec=0.02)
        assert player.finished.done(), "player did not finish within 30 s"
        return player, bystander, receiver
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_first_frame_waits_for_the_named_reader_not_any_reader(ros_domain_id: int) -> None:
    """Another reader and ack publisher are up at once; the named node (the tracker in a run)
    comes 1.5 s later and must still get every lockstep frame, with no ack timeout. Without
    wait_for_readers the player starts after 0.5 s of steady counts and frame 1 is lost."""
    frames = make_frames(4)
    player, bystander, rx = _play_with_late_receiver(frames, ros_domain_id, 1.5, pacing="lockstep", ack_timeout_s=3.0,
                                                     wait_for_readers="receiver", start_delay_s=20.0)
    stamps = [f.stamp_ns for f in frames]
    assert rx is not None and [s for s, _ in rx.color] == stamps
    assert rx.acked == stamps and player.acks.timeouts == 0
    assert bystander.color == stamps


def test_a_named_reader_that_never_comes_delays_the_start_by_start_delay_s_only(ros_domain_id: int) -> None:
    frames = make_frames(2)
    t0 = time.monotonic()
    player, bystander, _ = _play_with_late_receiver(frames, ros_domain_id, None, pacing="lockstep", ack_timeout_s=0.2,
                                                    wait_for_readers="tracker", start_delay_s=1.5)
    assert time.monotonic() - t0 >= 1.5
    assert bystander.color == [f.stamp_ns for f in frames] and player.acks.timeouts == 2


def test_depth_as_16uc1_millimetres(ros_domain_id: int) -> None:
    frames = make_frames(2)
    _, rx = play_in_process(frames, ros_domain_id, pacing="lockstep", depth_encoding="16UC1")
    assert [img.encoding for _, img in rx.depth] == ["16UC1", "16UC1"]
    mm = image_to_numpy(rx.depth[1][1])
    np.testing.assert_array_equal(mm, np.rint(frames[1].depth_m.astype(np.float64) * 1000.0).astype(np.uint16))


@pytest.mark.parametrize(
    "params,fragment",
    [
        ({"rate": 0.0}, "'rate'"),
        ({"rate": 2}, "parameter 'rate' must be of type float"),
        ({"depth_encoding": "mono8"}, "parameter 'depth_encoding' = 'mono8' is not one of"),
        ({"max_frames": -1}, "'max_frames'"),
    ],
)
def test_bad_parameters_are_refused_by_name(ros_domain_id: int, params: dict, fragment: str) -> None:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    try:
        with pytest.raises(ConfigError, match=fragment):
            BagPlayer(make_frames(1), context=ctx, parameter_overrides=_params(**params))
    finally:
        rclpy.try_shutdown(context=ctx)


class _BrokenSource:
    """Two good frames, then the reader fails the way a truncated bag does."""

    def __init__(self, frames: list[Frame]) -> None:
        self.frames = frames

    def __iter__(self) -> Iterator[Frame]:
        yield from self.frames[:2]
        raise DataError("test.bag: truncated chunk at byte 1234")


def test_source_failure_ends_with_done_false(ros_domain_id: int) -> None:
    frames = make_frames(4)
    player, rx = play_in_process(_BrokenSource(frames), ros_domain_id, pacing="lockstep")
    assert [s for s, _ in rx.color] == [f.stamp_ns for f in frames[:2]]
    assert rx.done == [False] and player.finished.result() is False


class _OnceSource:
    """A source that can be read once (a live stream would be): a replay of it after preloading
    must not read it again."""

    def __init__(self, frames: list[Frame]) -> None:
        self.frames, self.reads = frames, 0

    def __iter__(self) -> Iterator[Frame]:
        self.reads += 1
        yield from self.frames


def test_preloaded_replay_publishes_the_same_frames_from_memory(ros_domain_id: int) -> None:
    frames = make_frames(6)
    source = _OnceSource(frames)
    player, rx = play_in_process(source, ros_domain_id, pacing="lockstep", preload_mb=1)
    assert source.reads == 1 and rx.done == [True]
    for i, f in enumerate(frames):
        _assert_frame_equal(rx, i, f, f.stamp_ns)


def test_preload_refuses_a_source_over_its_budget_and_keeps_a_read_error_in_place() -> None:
    from memgs_ros.io.replay import Preloaded

    frames = make_frames(4)  # 32x24: 2304 + 3072 bytes a frame, 186 in 1 MB
    with pytest.raises(ConfigError, match=r"preload_mb=1 MB \(186 frames did\)"):
        Preloaded(make_frames(200), budget_mb=1)
    assert len(Preloaded(frames, budget_mb=1, max_frames=3)) == 3
    broken = Preloaded(_BrokenSource(frames), budget_mb=1)  # two frames, then a truncated chunk
    it = iter(broken)
    assert [next(it).stamp_ns, next(it).stamp_ns] == [f.stamp_ns for f in frames[:2]]
    with pytest.raises(DataError, match="truncated chunk"):
        next(it)


def test_missing_source_path_is_a_data_error(ros_domain_id: int, tmp_path: Path) -> None:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    try:
        with pytest.raises(DataError, match="nope.bag: no such file"):
            BagPlayer(context=ctx, parameter_overrides=_params(source=str(tmp_path / "nope.bag")))
    finally:
        rclpy.try_shutdown(context=ctx)


# ----------------------------------------------------------------------------- separate processes


def _env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def test_process_refuses_bad_parameter_with_exit_code_2(ros_domain_id: int) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "memgs_ros.nodes.bag_player.node", "--ros-args", "-p", "rate:=0.0"],
        env=_env(ros_domain_id), capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert "parameter 'rate'" in proc.stderr


def test_process_lockstep_replay_of_synthetic_source(ros_domain_id: int, tmp_path: Path) -> None:
    from memgs_ros.io.synthetic import generate_frames, parse_spec

    spec = "synthetic:w=64,h=48,n=20,seed=0"
    expected = list(generate_frames(parse_spec(spec)))
    params = tmp_path / "player.yaml"
    params.write_text(
        "/**:\n  ros__parameters:\n    pacing: lockstep\n    start_delay_s: 30.0\n    ack_timeout_s: 30.0\n"
        "    frame_id: cam\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "memgs_ros.nodes.bag_player.node", "--ros-args", "--params-file", str(params),
         "-r", "__ns:=/uav1", "-p", f"source:={spec}"],
        env=_env(ros_domain_id), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    rx = None
    try:
        rx = Receiver(ctx, namespace="/uav1")  # relative topic names follow the player's namespace
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(rx)
        deadline = time.monotonic() + 60.0
        while not rx.done and time.monotonic() < deadline and proc.poll() is None:
            executor.spin_once(timeout_sec=0.1)
        executor.shutdown()
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if rx is not None:
            rx.destroy_node()
        rclpy.try_shutdown(context=ctx)
    assert proc.returncode == 0, out
    assert rx.done == [True], out
    stamps = [f.stamp_ns for f in expected]
    for kind in KINDS:
        assert [s for s, _ in getattr(rx, kind)] == stamps, (kind, out)
    assert rx.acked == stamps
    for (s, img), f in zip(rx.color, expected):
        assert img.header.frame_id == "cam"
        np.testing.assert_array_equal(decode_rgb(img), f.rgb)
    np.testing.assert_array_equal(decode_depth(rx.depth[-1][1]), expected[-1].depth_m)
    assert "done: 20 frames" in out



# ----------------------------------------------------------------------------- params and QoS helpers


def test_declare_documents_range_and_refuses_runtime_changes(ros_domain_id: int) -> None:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from memgs_ros.ros.params import ParamSpec, declare, declare_all

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    node = Node("params_test", context=ctx, parameter_overrides=[Parameter("rate", value=2.5)])
    try:
        assert declare(node, "rate", 1.0, "replay speed", range=(0.1, 10.0)) == 2.5
        desc = node.describe_parameter("rate")
        assert desc.description == "replay speed" and desc.read_only
        assert (desc.floating_point_range[0].from_value, desc.floating_point_range[0].to_value) == (0.1, 10.0)
        assert not node.set_parameters([Parameter("rate", value=3.0)])[0].successful
        got = declare_all(node, [ParamSpec("n", 3, "count", (0, 5)), ParamSpec("mode", "a", "m", choices=("a", "b"))])
        assert got == {"n": 3, "mode": "a"}
        assert node.describe_parameter("n").integer_range[0].to_value == 5
        assert "one of: a, b" in node.describe_parameter("mode").description
        with pytest.raises(ConfigError, match="parameter 'bad': a range needs a numeric default"):
            declare(node, "bad", "x", "d", range=(0, 1))
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    assert qos.sensor().reliability == ReliabilityPolicy.BEST_EFFORT
    assert qos.reliable(5).reliability == ReliabilityPolicy.RELIABLE and qos.reliable(5).depth == 5
    latched = qos.latched()
    assert latched.durability == DurabilityPolicy.TRANSIENT_LOCAL and latched.depth == 1
    with pytest.raises(ValueError, match="depth must be >= 1"):
        qos.reliable(0)


@pytest.mark.parametrize("strict", [False, True], ids=["skip", "strict"])
def test_frames_going_backwards_or_changing_camera_are_skipped_and_counted(ros_domain_id: int, strict: bool) -> None:
    """A stamp that does not follow the last one and a frame whose camera is not the first
    frame's: skipped, counted by kind in the stats, and the replay goes on; strict ends it at
    the first (done False)."""
    from dataclasses import replace

    frames = make_frames(6)
    other = replace(CAM, fx=CAM.fx * 1.5)
    bad = [*frames[:2], replace(frames[0], stamp_ns=frames[0].stamp_ns - 1), *frames[2:4],
           replace(frames[4], camera=other), frames[5]]
    player, rx = play_in_process(bad, ros_domain_id, pacing="lockstep", strict=strict)
    sent = [s for s, _ in rx.color]
    if strict:
        assert sent == [f.stamp_ns for f in frames[:2]] and rx.done == [False]
        return
    assert sent == [f.stamp_ns for f in (*frames[:4], frames[5])] and rx.done == [True]
    assert player.stats.values["skipped.stamp_backwards"] == 1
    assert player.stats.values["skipped.camera_changed"] == 1
