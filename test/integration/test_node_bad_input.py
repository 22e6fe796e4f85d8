"""Bad input to the nodes in-process (private rclpy context, real DDS): every bad keyframe, frame
stamp or map delta is refused and counted under one problem kind, the node keeps running, its
state (the map) is untouched by what it refused, and good input afterwards still goes in."""
from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from keyframe_bundles import SPEC, Bundle, _bundle, _without_field  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_spin import spin_until  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from memgs_ros.core.gaussians.gaussian_map import GaussianMap  # noqa: E402
from memgs_ros.core.geometry.frame import Frame  # noqa: E402
from memgs_ros.core.map_io.map_delta import DeltaOutbox, message_dtype  # noqa: E402
from memgs_ros.io.synthetic import generate_frames, parse_spec  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.codecs import matrix_to_pose_stamped, structured_to_pointcloud2  # noqa: E402
from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image  # noqa: E402
from memgs_ros.ros.keyframe_bundle import KEYPOINT_DTYPE  # noqa: E402

pytestmark = pytest.mark.ros



@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(generate_frames(parse_spec(SPEC)))


_spin_until = functools.partial(spin_until, timeout_s=15.0)


def _problems(counters) -> int:  # noqa: ANN001 - a Counter
    return sum(v for k, v in counters.items() if k.startswith("problem."))


def _truncate(msg: Image) -> Image:
    msg.data = msg.data[: len(msg.data) // 2]
    return msg


def _relabel(msg: Image, encoding: str) -> Image:
    msg.encoding = encoding
    return msg


def _with_k(info: CameraInfo, fx: float) -> CameraInfo:
    k = list(info.k)
    k[0] = fx
    info.k = k
    return info


# (label, kind counted, what to break). Stamps and images come from the frame given.
BAD_BUNDLES: list[tuple[str, str, Callable[[Bundle, Frame], None]]] = [
    ("unknown colour encoding", "bad_image", lambda b, f: _relabel(b.color, "yuv422")),
    ("depth encoding on the colour topic", "bad_image",
     lambda b, f: setattr(b, "color", depth_to_image(f.depth_m, "32FC1", b.stamp, "cam"))),
    ("truncated colour", "bad_image", lambda b, f: _truncate(b.color)),
    ("colour step larger than the data", "bad_image", lambda b, f: setattr(b.color, "step", b.color.step + 8)),
    ("truncated depth", "bad_image", lambda b, f: _truncate(b.depth)),
    ("16UC1 depth labelled 32FC1", "bad_image",
     lambda b, f: setattr(b, "depth", _relabel(depth_to_image(f.depth_m, "16UC1", b.stamp, "cam"), "32FC1"))),
    ("32FC1 depth labelled 16UC1", "bad_image", lambda b, f: _relabel(b.depth, "16UC1")),
    ("colour encoding on the depth topic", "bad_image", lambda b, f: setattr(b, "depth", b.color)),
    ("depth smaller than colour", "size_mismatch",
     lambda b, f: setattr(b, "depth", depth_to_image(f.depth_m[::2, ::2].copy(), "32FC1", b.stamp, "cam"))),
    ("colour smaller than camera_info", "size_mismatch",
     lambda b, f: setattr(b, "color", numpy_to_image(f.rgb[::2, ::2].copy(), "rgb8", b.stamp, "cam"))),
    ("depth all NaN", "empty_depth",
     lambda b, f: setattr(b, "depth", numpy_to_image(np.full_like(f.depth_m, np.nan), "32FC1", b.stamp, "cam"))),
    ("depth all +inf", "empty_depth",
     lambda b, f: setattr(b, "depth", numpy_to_image(np.full_like(f.depth_m, np.inf), "32FC1", b.stamp, "cam"))),
    ("depth all negative", "empty_depth",
     lambda b, f: setattr(b, "depth", numpy_to_image(-f.depth_m, "32FC1", b.stamp, "cam"))),
    ("16UC1 depth all zero", "empty_depth",
     lambda b, f: setattr(b, "depth", numpy_to_image(np.zeros(f.depth_m.shape, np.uint16), "16UC1", b.stamp, "cam"))),
    ("zero focal length", "camera_info", lambda b, f: _with_k(b.info, 0.0)),
    ("NaN focal length", "camera_info", lambda b, f: _with_k(b.info, float("nan"))),
    ("4 distortion coefficients", "camera_info", lambda b, f: setattr(b.info, "d", [0.01, 0.0, 0.0, 0.0])),
    ("NaN distortion coefficient", "camera_info", lambda b, f: setattr(b.info, "d", [float("nan"), 0.0, 0.0, 0.0, 0.0])),
    ("pose with a NaN position", "bad_pose", lambda b, f: setattr(b.pose.pose.position, "x", float("nan"))),
]


class _Feeder:
    """Publishes keyframe bundles on ``memgs/keyframe/*`` and spins until the node counted each."""

    def __init__(self, ctx, node, parts: tuple[str, ...]) -> None:  # noqa: ANN001
        self.node = node
        self.peer = rclpy.create_node("bundle_feeder", context=ctx)
        types = {"color": Image, "depth": Image, "info": CameraInfo, "pose": PoseStamped,
                 "keypoints": PointCloud2, "seeds": PointCloud2}
        topics = {"info": "camera_info"}
        self.pubs = {p: self.peer.create_publisher(types[p], f"memgs/keyframe/{topics.get(p, p)}", qos.keyframes())
                     for p in parts}
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(node)
        self.ex.add_node(self.peer)
        assert _spin_until(self.ex, lambda: all(p.get_subscription_count() for p in self.pubs.values()))

    def send(self, b: Bundle, done: Callable[[], bool]) -> None:
        for part, pub in self.pubs.items():
            pub.publish(getattr(b, part))
        assert _spin_until(self.ex, done), f"keyframe {b.stamp} was never handled"

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        self.peer.destroy_node()


def _feed_bad_bundles(feeder: _Feeder, frames: list[Frame], on_refused: Callable[[str], None]) -> None:
    """One bundle per entry of BAD_BUNDLES; each must add exactly one problem of its kind."""
    c = feeder.node.stats.values
    for i, (label, kind, breaker) in enumerate(BAD_BUNDLES):
        f = frames[1 + i % (len(frames) - 1)]
        b = _bundle(f, f.stamp_ns + 1000 * (i + 1))
        breaker(b, f)
        before, total = c[f"problem.{kind}"], _problems(c)
        feeder.send(b, lambda: _problems(c) > total)
        assert c[f"problem.{kind}"] == before + 1, f"{label}: counted as {dict(c)}"
        on_refused(label)


def test_keyframe_sampler_refuses_bad_bundles_by_kind_and_keeps_sampling(context, frames) -> None:  # noqa: ANN001
    from memgs_ros.nodes.keyframe_sampler.node import KeyframeSamplerNode

    node = KeyframeSamplerNode(context=context)
    feeder = _Feeder(context, node, ("color", "depth", "info", "pose", "keypoints"))
    seeds: list[PointCloud2] = []
    feeder.peer.create_subscription(PointCloud2, "memgs/keyframe/seeds", seeds.append, qos.reliable(50))
    c = node.stats.values
    try:
        feeder.send(_bundle(frames[0], frames[0].stamp_ns), lambda: c["keyframes"] == 1 and len(seeds) == 1)

        def refused(label: str) -> None:
            assert c["keyframes"] == 1, f"{label} was sampled"

        _feed_bad_bundles(feeder, frames, refused)
        b = _bundle(frames[0], frames[0].stamp_ns + 10**9)
        _without_field(b.keypoints, "depth")
        feeder.send(b, lambda: c["problem.bad_keypoints"] == 1)
        # Keypoints outside the image or with NaN positions are the tracker's bug, not a crash here.
        b = _bundle(frames[0], frames[0].stamp_ns + 2 * 10**9)
        kps = np.zeros(3, KEYPOINT_DTYPE)
        kps["u"], kps["v"], kps["depth"] = [np.nan, 1e9, -5.0], [3.0, np.inf, -5.0], [1.0, 1.0, np.nan]
        b.keypoints = structured_to_pointcloud2(kps, b.stamp, "cam")
        feeder.send(b, lambda: c["keyframes"] == 2 and len(seeds) == 2)
        assert seeds[-1].width == 0  # nothing usable among them; the keyframe itself was fine
        last = frames[-1]
        feeder.send(_bundle(last, last.stamp_ns + 10**9), lambda: c["keyframes"] == 3 and len(seeds) == 3)
        assert seeds[-1].width > 0
        assert c["problem.camera_info"] == 4 and c["problem.empty_depth"] == 4
    finally:
        feeder.close()


def test_mapper_refuses_bad_bundles_without_touching_the_map(context, frames) -> None:  # noqa: ANN001
    from memgs_ros.nodes.mapper.node import MapperNode

    node = MapperNode(context=context, parameter_overrides=[
        Parameter("pacing", value="lockstep"), Parameter("iterations_per_frame", value=0), Parameter("device", value="cpu"),
        Parameter("render_rate_hz", value=0.0)])
    feeder = _Feeder(context, node, ("color", "depth", "info", "pose", "seeds"))
    c = node.stats.values
    try:
        feeder.send(_bundle(frames[0], frames[0].stamp_ns), lambda: c["keyframes"] == 1)
        before = node.session.snapshot().result(30)
        n_kf = node.session.status.keyframes_trained
        assert len(before) > 0

        def unchanged(label: str) -> None:
            after = node.session.snapshot().result(30)
            assert node.session.status.keyframes_trained == n_kf and c["keyframes"] == 1, f"{label} went in"
            assert np.array_equal(after.ids, before.ids) and np.array_equal(after.xyz, before.xyz), label

        _feed_bad_bundles(feeder, frames, unchanged)
        b = _bundle(frames[0], frames[0].stamp_ns + 10**9)
        _without_field(b.seeds, "rgb")
        feeder.send(b, lambda: c["problem.bad_seeds"] == 1)
        unchanged("seeds without colours")
        # The same keyframe again (a replay of the keyframe topics): ignored, the map unchanged.
        feeder.send(_bundle(frames[0], frames[0].stamp_ns), lambda: c["duplicate_keyframe_parts"] == 5)
        unchanged("a keyframe stamp seen before")
        last = frames[-1]
        feeder.send(_bundle(last, last.stamp_ns + 10**9), lambda: c["keyframes"] == 2)
        assert _spin_until(feeder.ex, lambda: node.session.status.keyframes_trained == n_kf + 1)
        assert len(node.session.snapshot().result(30)) > len(before)
        # Refined poses: unknown stamps are ignored, a broken pose is counted, not fatal.
        from nav_msgs.msg import Path

        pub = feeder.peer.create_publisher(Path, "memgs/keyframe/refined_poses", qos.reliable(20))
        assert _spin_until(feeder.ex, lambda: pub.get_subscription_count() > 0)
        bad = matrix_to_pose_stamped(np.eye(4), last.stamp_ns + 10**9, "map")
        bad.pose.orientation.w = float("nan")
        pub.publish(Path(poses=[matrix_to_pose_stamped(np.eye(4), 12345, "map"), bad]))
        assert _spin_until(feeder.ex, lambda: c["problem.bad_pose"] == 2)
        assert c["keyframe_pose_updates"] == 0
    finally:
        node.close()
        feeder.close()


def test_the_sampler_reads_keyframe_depth_in_rep118_units_without_a_scale_of_its_own(
        context, frames, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """The tracker sends keyframe depth in REP-118's units (``rep118_depth``): TUM's 16-bit 1/5000 m
    as 32FC1 metres, a RealSense's millimetres as they are. The sampler, which declares no
    depth_scale, puts its seeds at the frame's depth either way (not at 5x or 1/5 of it), and
    prepares (undistorts, turns into metres) each keyframe's images once."""
    from sensor_msgs.msg import PointCloud2 as Cloud

    from memgs_ros.core.geometry.view import ViewPreparation
    from memgs_ros.nodes.keyframe_sampler.node import KeyframeSamplerNode
    from memgs_ros.ros.codecs import pointcloud2_to_structured
    from memgs_ros.ros.images import rep118_depth

    prepared: list[int] = []
    real = ViewPreparation.__call__
    monkeypatch.setattr(ViewPreparation, "__call__", lambda self, *a, **k: prepared.append(1) or real(self, *a, **k))

    feeder = _Feeder(context, KeyframeSamplerNode(context=context), ("color", "depth", "info", "pose", "keypoints"))
    seeds: list[Cloud] = []
    feeder.peer.create_subscription(Cloud, "memgs/keyframe/seeds", seeds.append, qos.keyframes())
    c = feeder.node.stats.values
    try:
        f = frames[1]
        T_cw = np.linalg.inv(f.T_wc_gt)
        for i, units in enumerate((5000.0, 1000.0)):
            b = _bundle(f, f.stamp_ns + i)
            b.depth = rep118_depth(depth_to_image(f.depth_m, "16UC1", b.stamp, "cam", units), units)
            assert b.depth.encoding == ("32FC1" if units == 5000.0 else "16UC1")
            feeder.send(b, lambda i=i: len(seeds) == i + 1)
            cloud = pointcloud2_to_structured(seeds[-1], required=("x", "y", "z"))
            p_w = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
            z = (p_w @ T_cw[:3, :3].T + T_cw[:3, 3])[:, 2]
            assert np.median(z) == pytest.approx(np.nanmedian(f.depth_m[f.depth_m > 0]), rel=0.1), units
        assert c["keyframes"] == 2 and _problems(c) == 0, dict(c)
        assert len(prepared) == 2
    finally:
        feeder.close()


def test_free_running_mapper_drops_and_counts_keyframes_it_cannot_insert(context, frames) -> None:  # noqa: ANN001
    """Keyframes arriving faster than the mapper inserts them: the bounded insert queue keeps the
    newest, drops the oldest whole and counts each; the executor keeps draining the topics."""
    import threading

    from memgs_ros.nodes.mapper.node import MapperNode

    node = MapperNode(context=context, parameter_overrides=[
        Parameter("insert_queue", value=1), Parameter("device", value="cpu"), Parameter("render_rate_hz", value=0.0),
        Parameter("mapping.min_keyframes", value=100),
        Parameter("mapping.live_min_keyframes", value=100)])  # no training: only insertion is exercised
    gate = threading.Event()
    started: list[int] = []

    def hold_inserts(m):  # noqa: ANN001, ANN202 - runs on the session's worker
        add = m.add_prepared_keyframe

        def slow_add(kf, *args, **kwargs):  # noqa: ANN001, ANN202
            started.append(kf.stamp_ns)
            assert gate.wait(30.0)
            return add(kf, *args, **kwargs)

        m.add_prepared_keyframe = slow_add

    node.session.call(hold_inserts).result(30)
    feeder = _Feeder(context, node, ("color", "depth", "info", "pose", "seeds"))
    c = node.stats.values
    try:
        stamps = [frames[i].stamp_ns for i in range(4)]
        feeder.send(_bundle(frames[0], stamps[0]), lambda: len(started) == 1)  # the insert thread holds it
        for i in (1, 2, 3):  # queue of 1: the 3rd drops the 2nd, the 4th drops the 3rd
            feeder.send(_bundle(frames[i], stamps[i]), lambda i=i: node.stats.values.get("insert_queue") == 1
                        and c["problem.keyframe_overload"] == i - 1)
        gate.set()
        assert _spin_until(feeder.ex, lambda: c["keyframes"] == 2)
        assert c["problem.keyframe_overload"] == 2
        assert node.session.status.keyframes_trained == 2
        table = node.session.state_dict().result(30).extra["keyframe_stamps"]
        assert sorted(int(k) for k in table) == [stamps[0], stamps[3]]  # the first and the newest
        # Refined poses are one more command in the session's queue.
        from nav_msgs.msg import Path

        pub = feeder.peer.create_publisher(Path, "memgs/keyframe/refined_poses", qos.reliable(20))
        assert _spin_until(feeder.ex, lambda: pub.get_subscription_count() > 0)
        T = frames[3].T_wc_gt.copy()
        T[:3, 3] += 0.03  # bundle adjustment: the training pose only, the Gaussians stay
        pub.publish(Path(poses=[matrix_to_pose_stamped(T, stamps[3], "map")]))
        assert _spin_until(feeder.ex, lambda: c["keyframe_pose_updates"] == 1)
        kfs = node.session.state_dict().result(30).keyframes
        np.testing.assert_allclose([k.T_wc for k in kfs if k.stamp_ns == stamps[3]][0], T, atol=1e-6)
        assert c["keyframes_corrected"] == 0
        # A loop correction of the same keyframe moves its Gaussians with it (its own topic).
        means = lambda m: m.gmap.means.detach().numpy().copy()  # noqa: E731 - runs on the session's worker
        before = node.session.call(means).result(30)
        loop = feeder.peer.create_publisher(Path, "memgs/keyframe/loop_corrected_poses", qos.reliable(20))
        assert _spin_until(feeder.ex, lambda: loop.get_subscription_count() > 0)
        T2 = T.copy()
        T2[:3, 3] += [0.1, 0.0, 0.0]
        loop.publish(Path(poses=[matrix_to_pose_stamped(T2, stamps[3], "map")]))
        assert _spin_until(feeder.ex, lambda: c["keyframes_corrected"] == 1)
        moved = np.linalg.norm(node.session.call(means).result(30) - before, axis=1)
        assert c["gaussians_corrected"] > 0 and int((np.abs(moved - 0.1) < 1e-4).sum()) == c["gaussians_corrected"]
        # A command nobody waits on that fails (here a correction the map refuses) reaches the stats.
        from memgs_ros.errors import DataError

        def refuse(m):  # noqa: ANN001, ANN202 - runs on the session's worker
            def correct(_ids):  # noqa: ANN001, ANN202
                raise DataError("keyframe 3: a correction that would move Gaussians off the map")
            m.correct_keyframes = correct

        node.session.call(refuse).result(30)
        loop.publish(Path(poses=[matrix_to_pose_stamped(T, stamps[3], "map")]))
        assert _spin_until(feeder.ex, lambda: c["problem.command_failed"] == 1)
        assert c["keyframes_corrected"] == 1
    finally:
        gate.set()
        node.close()
        feeder.close()


# ----------------------------------------------------------------------------- tracker stamps

def test_tracker_stamp_rules(context) -> None:  # noqa: ANN001
    """Duplicate and slightly older stamps are dropped; a jump back by more than
    ``time_jump_back_s`` (a bag replayed in a loop) restarts the stamp order and tracking goes
    on; a frame stamped far ahead of the node's clock is dropped."""
    from memgs_ros.nodes.tracker.node import TrackerNode

    frames = list(generate_frames(parse_spec("synthetic:w=128,h=96,n=4,seed=2")))  # enough texture to track
    node = TrackerNode(context=context, parameter_overrides=[
        Parameter("color_topic", value="color/image_raw"), Parameter("depth_topic", value="depth/image_raw"),
        Parameter("camera_info_topic", value="color/camera_info"), Parameter("sync", value="exact"),
        Parameter("input_reliability", value="reliable")])
    peer = rclpy.create_node("frame_feeder", context=context)
    pc = peer.create_publisher(Image, "color/image_raw", qos.reliable(50))
    pd = peer.create_publisher(Image, "depth/image_raw", qos.reliable(50))
    pi = peer.create_publisher(CameraInfo, "color/camera_info", qos.reliable(50))
    processed: list[Header] = []
    peer.create_subscription(Header, "memgs/tracker/processed", processed.append, qos.reliable(100))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(peer)
    c = node.stats.values
    tracked = lambda: sum(v for k, v in c.items() if k.startswith("state."))  # noqa: E731
    try:
        assert _spin_until(ex, lambda: pc.get_subscription_count() and pd.get_subscription_count()
                           and pi.get_subscription_count())
        assert node.wait_until_warm(120)  # a live frame before it is "warming"
        pi.publish(camera_to_camera_info(frames[0].camera, frames[0].stamp_ns, "cam"))
        assert _spin_until(ex, lambda: node.cams.camera is not None)

        def send(f: Frame, stamp: int) -> None:
            n = len(processed)
            pc.publish(numpy_to_image(f.rgb, "rgb8", stamp, "cam"))
            pd.publish(depth_to_image(f.depth_m, "32FC1", stamp, "cam"))
            assert _spin_until(ex, lambda: len(processed) > n), f"frame {stamp} was never handled"

        shift = 60 * 10**9  # first pass 60 s later than the loop's second pass
        for f in frames[:3]:
            send(f, f.stamp_ns + shift)
        assert tracked() == 3
        send(frames[2], frames[2].stamp_ns + shift)  # the same frame twice
        assert c["problem.stamp_duplicate"] == 1 and tracked() == 3
        send(frames[1], frames[1].stamp_ns + shift)  # 33 ms late: out of order
        assert c["problem.stamp_order"] == 1 and tracked() == 3
        now_ns = node.get_clock().now().nanoseconds
        send(frames[3], now_ns + 24 * 3600 * 10**9)  # a day ahead of the clock
        assert c["problem.stamp_future"] == 1 and tracked() == 3
        # The bag starts over: 60 s back. Accepted, counted once, and the order restarts from it.
        for f in frames[:3]:
            send(f, f.stamp_ns)
        assert c["problem.time_jump_back"] == 1 and tracked() == 6
        assert c["problem.stamp_order"] == 1 and c["problem.stamp_duplicate"] == 1
        assert c["poses_out"] >= 4
    finally:
        node.close()
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


# ----------------------------------------------------------------------------- merger

def test_merger_refuses_malformed_deltas_and_counts_unknown_removals(context, tmp_path) -> None:  # noqa: ANN001
    from memgs_ros.nodes.merger.node import MergerNode

    merger = MergerNode(context=context, parameter_overrides=[
        Parameter("map_path", value=str(tmp_path / "m.ply")), Parameter("save_period_s", value=0.0),
        Parameter("publish_period_s", value=0.0)])
    peer = rclpy.create_node("delta_feeder", context=context)
    pub = peer.create_publisher(PointCloud2, "memgs/map/delta", qos.reliable(50))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(merger)
    ex.add_node(peer)
    c = merger.stats.values
    rng = np.random.default_rng(0)
    g = GaussianMap(max_sh_degree=0)
    g.add_from_points(rng.uniform(-1, 1, (20, 3)), rng.uniform(0, 1, (20, 3)), keyframe_id=0, iteration=0)
    outbox = DeltaOutbox(sh_degree=0)

    def send(msg: PointCloud2, cond: Callable[[], bool]) -> None:
        pub.publish(msg)
        assert _spin_until(ex, cond)

    try:
        assert _spin_until(ex, lambda: pub.get_subscription_count() > 0)
        send(structured_to_pointcloud2(outbox.next_delta(g.to_records()), 0, "map"),
             lambda: len(merger.map.replica) == 20)
        ids = merger.map.replica.records.ids.copy()
        g.remove(np.arange(len(g)) < 5)
        rows = outbox.next_delta(g.to_records())  # seq 2: 5 removals
        good = structured_to_pointcloud2(rows, 0, "map")

        broken = structured_to_pointcloud2(rows, 0, "map")
        _without_field(broken, "opacity")
        send(broken, lambda: c["problem.bad_map_message"] == 1)
        short = structured_to_pointcloud2(rows, 0, "map")
        short.data = short.data[:-3]  # rows of the wrong size
        send(short, lambda: c["problem.bad_map_message"] == 2)
        wide = structured_to_pointcloud2(rows, 0, "map")
        wide.point_step -= 4  # a field no longer fits its row
        send(wide, lambda: c["problem.bad_map_message"] == 3)
        assert np.array_equal(merger.map.replica.records.ids, ids) and merger.map.replica.seq == 1

        send(good, lambda: merger.map.replica.seq == 2)
        assert len(merger.map.replica) == 15 and not merger.map.resyncing
        # seq 3 removes ids the replica never had (and that the sender's count agrees with).
        ghost = np.zeros(3, message_dtype(0))
        ghost["op"][0], ghost["op"][1:] = 2, 1
        ghost["id"][0] = (3 << 32) | 15
        ghost["id"][1:] = [10**6, 10**6 + 1]
        send(structured_to_pointcloud2(ghost, 0, "map"), lambda: merger.map.replica.seq == 3)
        assert c["problem.unknown_removal"] == 1 and len(merger.map.replica) == 15 and not merger.map.resyncing
        assert merger.stats.values["unknown_removals"] == 2
    finally:
        ex.shutdown()
        merger.destroy_node()
        peer.destroy_node()


# ----------------------------------------------------------------------------- depth mix-ups

def test_depth_encoding_mixups_are_named_and_real_padded_16uc1_still_decodes(frames) -> None:  # noqa: ANN001
    from memgs_ros.errors import MessageError
    from memgs_ros.io.image_decoding import decode_depth

    f = frames[0]
    as16 = _relabel(depth_to_image(f.depth_m, "16UC1", 0, "cam"), "32FC1")
    with pytest.raises(MessageError, match="exactly a 64x48 16UC1 image: is the encoding wrong"):
        decode_depth(as16)
    as32 = _relabel(depth_to_image(f.depth_m, "32FC1", 0, "cam"), "16UC1")
    with pytest.raises(MessageError, match="32FC1 data labelled 16UC1"):
        decode_depth(as32)
    # Genuine 16UC1 rows padded to the width of a float row, 0.5 m .. 15 m: never taken for floats.
    for mm in (500, 8000, 15000):
        units = np.full(f.depth_m.shape, mm, np.uint16)
        padded = np.zeros((units.shape[0], units.shape[1] * 2), np.uint16)
        padded[:, : units.shape[1]] = units
        msg = numpy_to_image(padded, "16UC1", 0, "cam")
        msg.width, msg.step = units.shape[1], units.shape[1] * 4
        np.testing.assert_allclose(decode_depth(msg), mm / 1000.0)


# ----------------------------------------------------------------------------- converters never crash

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_ENCODINGS = st.sampled_from(["rgb8", "bgr8", "rgba8", "mono8", "16UC1", "mono16", "32FC1", "yuv422", "", "64FC1"])


@settings(max_examples=200, deadline=None)
@given(enc=_ENCODINGS, h=st.integers(-2, 9), w=st.integers(-2, 9), step=st.integers(-4, 40),
       n=st.integers(0, 400), big=st.booleans(), scale=st.sampled_from([1000.0, 0.0, -1.0, float("nan")]))
def test_image_converters_return_or_raise_message_error(enc: str, h: int, w: int, step: int, n: int, big: bool,
                                                        scale: float) -> None:
    from memgs_ros.errors import MessageError
    from memgs_ros.io.image_decoding import decode_depth, decode_rgb

    msg = Image(encoding=enc, is_bigendian=int(big), data=bytes(range(256)) * (n // 256) + bytes(n % 256))
    # Negative sizes cannot be set on the message (uint32): they wrap as a sender's bug would.
    msg.height, msg.width, msg.step = h % 2**32, w % 2**32, step % 2**32
    for convert in (decode_rgb, lambda m: decode_depth(m, scale)):
        try:
            out = convert(msg)
        except MessageError:
            continue
        assert out.shape[:2] == (msg.height, msg.width)


@settings(max_examples=200, deadline=None)
@given(k=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=9, max_size=9),
       d=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), max_size=8),
       model=st.sampled_from(["plumb_bob", "rational_polynomial", "", "none", "equidistant"]),
       size=st.tuples(st.integers(0, 5000), st.integers(0, 5000)), binning=st.integers(0, 3))
def test_camera_info_converter_returns_a_valid_camera_or_raises(k, d, model, size, binning) -> None:  # noqa: ANN001
    from memgs_ros.errors import MessageError
    from memgs_ros.io.image_decoding import decode_camera_info

    msg = CameraInfo(width=size[0], height=size[1], distortion_model=model, d=d, k=k, binning_x=binning)
    try:
        cam = decode_camera_info(msg)
    except MessageError:
        return
    assert cam.fx > 0 and cam.fy > 0 and np.all(np.isfinite([cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]))
    assert cam.width > 0 and cam.height > 0


def test_mapper_checkpoints_written_while_keyframes_arrive_are_whole(context, frames, tmp_path) -> None:  # noqa: ANN001
    """Regression: the free-running mapper used to copy its keyframe-stamp table for a checkpoint
    outside the map's lock while its insert thread added keyframes, so a checkpoint could hold a
    keyframe without its stamp (resumed, that keyframe's replay went in twice) or the copy could
    raise 'dictionary changed size during iteration'. Every checkpoint written while keyframes
    arrive must name each of its keyframes' stamps."""
    import threading

    from memgs_ros.core.mapping import checkpoint
    from memgs_ros.nodes.mapper.node import MapperNode

    path = tmp_path / "ck.npz"
    node = MapperNode(context=context, parameter_overrides=[
        Parameter("device", value="cpu"), Parameter("render_rate_hz", value=0.0),
        Parameter("checkpoint_path", value=str(path)), Parameter("checkpoint_period_s", value=0.0),
        Parameter("mapping.min_keyframes", value=100),
        Parameter("mapping.live_min_keyframes", value=100)])  # no training: insertions back to back
    feeder = _Feeder(context, node, ("color", "depth", "info", "pose", "seeds"))
    c = node.stats.values
    stop = threading.Event()
    written: list[checkpoint.MapperCheckpoint] = []
    errors: list[BaseException] = []

    def save_while_inserting() -> None:
        while not stop.is_set():
            try:
                if node.save_checkpoint(force=True).result(30) is not None:
                    written.append(checkpoint.load(path))
            except BaseException as err:  # noqa: BLE001 - reported to the test thread
                errors.append(err)

    saver = threading.Thread(target=save_while_inserting)
    saver.start()
    try:
        for i in range(12):
            f = frames[i % len(frames)]
            feeder.send(_bundle(f, f.stamp_ns + i * 10**9), lambda i=i: c["keyframes"] == i + 1)
    finally:
        stop.set()
        saver.join(60)
        node.close()
        feeder.close()
    assert not errors and c["problem.checkpoint_failed"] == 0, (errors, dict(c))
    assert len(written) >= 3
    for ck in written:
        table = {int(s): int(k) for s, k in ck.extra["keyframe_stamps"].items()}
        assert all(table.get(kf.stamp_ns) == kf.kf_id for kf in ck.keyframes), (
            f"a checkpoint holds keyframes {[kf.stamp_ns for kf in ck.keyframes]} but stamps {sorted(table)}")


def test_every_node_declares_exactly_its_parameter_table(context) -> None:  # noqa: ANN001
    """The tables the CLI checks names against (CONFIGS) are what the nodes declare, and a
    parameter a node does not declare is refused at start, naming the closest real one."""
    from memgs_ros.errors import ConfigError
    from memgs_ros.nodes.bag_player import node as bag_player
    from memgs_ros.nodes.keyframe_sampler import node as keyframe_sampler
    from memgs_ros.nodes.mapper import node as mapper
    from memgs_ros.nodes.merger import node as merger
    from memgs_ros.nodes.merger.node import MergerNode
    from memgs_ros.nodes.tracker import node as tracker
    from memgs_ros.nodes.tracker.node import TrackerNode
    from memgs_ros.ros.config_params import check_declared, module_parameter_names

    for module, factory in ((merger, MergerNode), (tracker, TrackerNode), (mapper, mapper.MapperNode),
                            (keyframe_sampler, keyframe_sampler.KeyframeSamplerNode),
                            (bag_player, lambda **kw: bag_player.BagPlayer(frames=[], **kw))):
        node = factory(context=context)
        try:
            assert set(node._parameters) == module_parameter_names(module), module.__name__
            check_declared(node)  # nothing stray: no error
        finally:
            node.destroy_node()
    node = MergerNode(context=context, parameter_overrides=[Parameter("save_period", value=5.0)])
    try:
        with pytest.raises(ConfigError, match=r"merger has no parameter 'save_period' \(did you mean save_period_s"):
            check_declared(node)
    finally:
        node.destroy_node()
