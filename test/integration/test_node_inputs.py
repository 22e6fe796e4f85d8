"""Nodes in-process (private rclpy context): bad input is counted and logged, never fatal."""
from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from memgs_ros.io.image_decoding import image_to_numpy  # noqa: E402
from memgs_ros.io.synthetic import generate_frames, parse_spec  # noqa: E402
from memgs_ros.nodes.tracker.node import TrackerNode  # noqa: E402
from memgs_ros.ros import qos  # noqa: E402
from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image  # noqa: E402

pytestmark = pytest.mark.ros


def _spin_until(executor: SingleThreadedExecutor, cond, timeout_s: float = 20.0) -> bool:  # noqa: ANN001
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
        if cond():
            return True
    return False


def test_tracker_survives_bad_frames_and_tracks_good_ones(context) -> None:  # noqa: ANN001
    params = [Parameter("color_topic", value="color/image_raw"), Parameter("depth_topic", value="depth/image_raw"),
              Parameter("camera_info_topic", value="color/camera_info"), Parameter("sync", value="exact")]
    node = TrackerNode(context=context, parameter_overrides=params)
    pub_node = rclpy.create_node("feeder", context=context)
    pc = pub_node.create_publisher(Image, "color/image_raw", qos.reliable(50))
    pd = pub_node.create_publisher(Image, "depth/image_raw", qos.reliable(50))
    pi = pub_node.create_publisher(CameraInfo, "color/camera_info", qos.reliable(50))
    processed: list[Header] = []
    pub_node.create_subscription(Header, "memgs/tracker/processed", processed.append, qos.reliable(100))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(pub_node)
    try:
        assert _spin_until(ex, lambda: pc.get_subscription_count() and pd.get_subscription_count()
                           and pi.get_subscription_count())
        assert node.wait_until_warm(120)  # a live frame before it is "warming"
        frames = list(generate_frames(parse_spec("synthetic:w=128,h=96,n=6,seed=2")))
        f0 = frames[0]
        bad_info = camera_to_camera_info(f0.camera, f0.stamp_ns, "cam")
        bad_info.k = [0.0] * 9  # zero focal length
        pi.publish(bad_info)
        sent = 0

        def send(color: Image, depth: Image) -> None:
            nonlocal sent
            pc.publish(color)
            pd.publish(depth)
            sent += 1
            assert _spin_until(ex, lambda: len(processed) >= sent), f"frame {sent} was never handled"

        # Before any valid camera_info the first frame waits; then it is tracked.
        pc.publish(numpy_to_image(f0.rgb, "rgb8", f0.stamp_ns, "cam"))
        pd.publish(depth_to_image(f0.depth_m, "32FC1", f0.stamp_ns, "cam"))
        assert _spin_until(ex, lambda: node.cams.waiting, 10.0) and not processed
        pi.publish(camera_to_camera_info(f0.camera, f0.stamp_ns, "cam"))
        assert _spin_until(ex, lambda: node.stats.values["poses_out"] == 1 and len(processed) == 1)
        sent = 1
        f1, f2, f3 = frames[1:4]
        # Wrong encoding on the colour image.
        weird = numpy_to_image(f1.rgb, "rgb8", f1.stamp_ns, "cam")
        weird.encoding = "yuv422"
        send(weird, depth_to_image(f1.depth_m, "32FC1", f1.stamp_ns, "cam"))
        # Depth of another size than colour.
        send(numpy_to_image(f2.rgb, "rgb8", f2.stamp_ns, "cam"),
             depth_to_image(np.ones((48, 64), np.float32), "32FC1", f2.stamp_ns, "cam"))
        # Truncated data (step says more than there is).
        cut = numpy_to_image(f3.rgb, "rgb8", f3.stamp_ns, "cam")
        cut.data = cut.data[: len(cut.data) // 2]
        send(cut, depth_to_image(f3.depth_m, "32FC1", f3.stamp_ns, "cam"))
        # All-NaN depth: refused by nobody, but reported.
        f4 = frames[4]
        send(numpy_to_image(f4.rgb, "rgb8", f4.stamp_ns, "cam"),
             depth_to_image(np.full_like(f4.depth_m, np.nan), "32FC1", f4.stamp_ns, "cam"))
        # A stamp going backwards.
        send(numpy_to_image(f1.rgb, "rgb8", f1.stamp_ns - 10**6, "cam"),
             depth_to_image(f1.depth_m, "32FC1", f1.stamp_ns - 10**6, "cam"))
        # And a good frame still tracks afterwards.
        f5 = frames[5]
        send(numpy_to_image(f5.rgb, "rgb8", f5.stamp_ns, "cam"), depth_to_image(f5.depth_m, "32FC1", f5.stamp_ns, "cam"))
        c = node.stats.values
        assert c["problem.camera_info"] == 1
        assert c["problem.bad_image"] == 3
        assert c["problem.empty_depth"] == 1
        assert c["problem.stamp_order"] == 1
        assert c["poses_out"] >= 2
    finally:
        node.close()
        ex.shutdown()
        node.destroy_node()
        pub_node.destroy_node()


def test_tracker_counts_undelivered_frames_and_drops_stale_ones(context) -> None:  # noqa: ANN001
    """A gap in the colour publisher's sequence numbers is counted as skipped.busy; a frame that
    waited longer than max_frame_age_s beyond the least wait seen is dropped as stale (and
    acknowledged as processed). A constant clock offset between camera and tracker is not
    staleness. With max_frame_age_s 0 (lockstep replays) no frame is dropped."""
    params = [Parameter("max_frame_age_s", value=0.1), Parameter("sync", value="exact")]
    node = TrackerNode(context=context, parameter_overrides=params)
    handled: list[int] = []
    node._handle = lambda color, depth: handled.append(color.header.stamp.sec)  # noqa: SLF001 - intake only
    node.rgbd = False  # colour alone reaches _handle: no pairing in the way
    try:
        assert node.wait_until_warm(120)  # a live frame before it is "warming"
        offset = -5_000_000_000  # the camera's clock 5 s behind the tracker's

        def info(seq: int, waited_s: float) -> dict:
            return {"source_timestamp": time.time_ns() + offset - int(waited_s * 1e9),
                    "publication_sequence_number": seq}

        def color(sec: int) -> Image:
            msg = Image()
            msg.header.stamp.sec = sec
            return msg

        node.on_color(color(1), info(1, 0.0))
        node.on_color(color(2), info(2, 0.05))  # 50 ms later than the least wait: fresh
        node.on_color(color(3), info(5, 0.0))  # sequence 3 and 4 never arrived
        node.on_color(color(4), info(6, 0.5))  # waited 0.5 s: stale
        assert handled == [1, 2, 3]
        assert node.stats.values["skipped.busy"] == 2
        assert node.stats.values["skipped.stale"] == 1
    finally:
        node.destroy_node()
    reliable = TrackerNode(context=context, parameter_overrides=[Parameter("max_frame_age_s", value=0.0),
                                                                 Parameter("input_reliability", value="reliable")])
    seen: list[int] = []
    reliable._handle = lambda color, depth: seen.append(color.header.stamp.sec)  # noqa: SLF001
    reliable.rgbd = False
    try:
        reliable.on_color(color(1), info(1, 0.0))
        reliable.on_color(color(2), info(2, 5.0))
        assert seen == [1, 2] and reliable.stats.values["skipped.stale"] == 0
    finally:
        reliable.destroy_node()


def test_live_frames_before_the_kernels_are_in_are_counted_as_warming(context, monkeypatch) -> None:  # noqa: ANN001
    """A live camera does not wait for a fresh install's compile: its frames that come before the
    kernels are dropped, counted (skipped.warming) and answered on memgs/tracker/processed; the
    first frame after them is tracked. A lockstep replay's frame waits instead (not counted)."""
    import threading

    import memgs_ros.nodes.tracker.node as tracker_module

    gate = threading.Event()
    monkeypatch.setattr(tracker_module, "warm_up", lambda: gate.wait(60))  # a compile that takes its time
    node = TrackerNode(context=context, parameter_overrides=[Parameter("max_frame_age_s", value=0.1)])
    handled: list[int] = []
    answered: list[int] = []
    node._handle = lambda color, depth: handled.append(color.header.stamp.sec)  # noqa: SLF001 - intake only
    node.out.processed = lambda stamp, keyframe=False: answered.append(stamp)
    node.rgbd = False
    try:
        for sec in (1, 2):
            msg = Image()
            msg.header.stamp.sec = sec
            node.on_color(msg, {"source_timestamp": time.time_ns(), "publication_sequence_number": sec})
        assert handled == [] and node.stats.values["skipped.warming"] == 2 and len(answered) == 2
        gate.set()
        assert node.wait_until_warm(30)
        msg = Image()
        msg.header.stamp.sec = 3
        node.on_color(msg, {"source_timestamp": time.time_ns(), "publication_sequence_number": 3})
        assert handled == [3] and node.stats.values["skipped.warming"] == 2
    finally:
        gate.set()
        node.destroy_node()


def test_tracker_loads_its_kernels_before_the_first_frame(context) -> None:  # noqa: ANN001
    """The kernels load beside the executor from start-up (a live replay starts once the gauge
    says so); before, the first frame paid ~0.4 s for them and the next dozen frames were lost."""
    node = TrackerNode(context=context)
    try:
        deadline = time.monotonic() + 120.0  # a fresh install compiles them
        while time.monotonic() < deadline:
            node.stats.apply_posted()
            if node.stats.values.get("kernels_warm") == 1:
                break
            time.sleep(0.05)
        assert node.stats.values.get("kernels_warm") == 1
        assert "problem.warm_up" not in node.stats.values
        assert node.tracker is None  # built on the first frame, from warm kernels
    finally:
        node.destroy_node()


def test_tracker_forwards_keyframe_colour_as_received_and_depth_in_rep118_units(context) -> None:  # noqa: ANN001
    """A keyframe's colour leaves as it came in (the camera's message); its depth in REP-118's units:
    TUM's 16UC1 at 5000 a metre as 32FC1 metres, unit for unit (millimetres would pass as they
    are: test_codecs), so no node after the tracker needs the camera's scale; a depth paired from a
    nearby stamp takes the colour's stamp, which names the keyframe's bundle."""
    params = [Parameter("color_topic", value="color/image_raw"), Parameter("depth_topic", value="depth/image_raw"),
              Parameter("camera_info_topic", value="color/camera_info"), Parameter("depth_scale", value=5000.0),
              Parameter("max_sync_dt_s", value=0.02)]
    node = TrackerNode(context=context, parameter_overrides=params)
    peer = rclpy.create_node("kf_peer", context=context)
    pc = peer.create_publisher(Image, "color/image_raw", qos.reliable(50))
    pd = peer.create_publisher(Image, "depth/image_raw", qos.reliable(50))
    pi = peer.create_publisher(CameraInfo, "color/camera_info", qos.reliable(50))
    got: dict[str, list[Image]] = {"color": [], "depth": []}
    for part in got:
        peer.create_subscription(Image, f"memgs/keyframe/{part}", got[part].append, qos.keyframes())
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(peer)
    try:
        assert _spin_until(ex, lambda: pc.get_subscription_count() and pd.get_subscription_count()
                           and pi.get_subscription_count(), 60.0)
        assert node.wait_until_warm(120)
        f = next(iter(generate_frames(parse_spec("synthetic:w=128,h=96,n=1,seed=2"))))
        pi.publish(camera_to_camera_info(f.camera, f.stamp_ns, "cam"))
        color = numpy_to_image(f.rgb, "bgr8", f.stamp_ns, "cam")  # a camera's channel order, kept
        depth = depth_to_image(f.depth_m, "16UC1", f.stamp_ns - 5_000_000, "cam", 5000.0)  # 5 ms earlier
        pc.publish(color)
        pd.publish(depth)
        assert _spin_until(ex, lambda: got["color"] and got["depth"], 30.0), "the first frame made no keyframe"
        kc, kd = got["color"][0], got["depth"][0]
        assert (kc.encoding, bytes(kc.data)) == ("bgr8", bytes(color.data))
        units = image_to_numpy(depth).astype(np.float32)
        metres = image_to_numpy(kd)
        assert kd.encoding == "32FC1" and metres.shape == units.shape
        np.testing.assert_allclose(metres[units > 0], units[units > 0] / np.float32(5000.0), rtol=1e-7)
        assert np.isnan(metres[units == 0]).all()
        assert kd.header.stamp == kc.header.stamp == color.header.stamp
    finally:
        node.destroy_node()
        peer.destroy_node()


def test_tracker_takes_compressed_colour_and_depth(context) -> None:  # noqa: ANN001
    """image_transport=compressed: JPEG colour on <color_topic>/compressed and compressedDepth PNG on
    <depth_topic>/compressedDepth (as image_transport publishes them) track like the raw images; a
    frame that does not decode is counted, not fatal."""
    from sensor_msgs.msg import CompressedImage

    from memgs_ros.core.geometry.view import metres_to_units
    from memgs_ros.io.bag_writer import compress_depth_units, compress_rgb
    from memgs_ros.ros.codecs import make_header

    params = [Parameter("color_topic", value="color/image_raw"), Parameter("depth_topic", value="depth/image_raw"),
              Parameter("camera_info_topic", value="color/camera_info"), Parameter("sync", value="exact"),
              Parameter("image_transport", value="compressed"), Parameter("max_frame_age_s", value=0.0)]
    node = TrackerNode(context=context, parameter_overrides=params)
    pub_node = rclpy.create_node("feeder", context=context)
    pc = pub_node.create_publisher(CompressedImage, "color/image_raw/compressed", qos.reliable(50))
    pd = pub_node.create_publisher(CompressedImage, "depth/image_raw/compressedDepth", qos.reliable(50))
    pi = pub_node.create_publisher(CameraInfo, "color/camera_info", qos.reliable(50))
    processed: list[Header] = []
    pub_node.create_subscription(Header, "memgs/tracker/processed", processed.append, qos.reliable(100))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(pub_node)

    def compressed(stamp_ns: int, fmt: str, data: np.ndarray) -> CompressedImage:
        msg = CompressedImage()
        msg.header, msg.format, msg.data = make_header(stamp_ns, "cam"), fmt, data.tobytes()
        return msg

    try:
        assert _spin_until(ex, lambda: pc.get_subscription_count() and pd.get_subscription_count()
                           and pi.get_subscription_count())
        assert node.wait_until_warm(120)
        # the first 6 of 60 frames: the wobble path spans the sequence, so 6 of 6 would jump
        frames = list(itertools.islice(generate_frames(parse_spec("synthetic:w=320,h=240,n=60,seed=2")), 6))
        pi.publish(camera_to_camera_info(frames[0].camera, frames[0].stamp_ns, "cam"))
        for k, f in enumerate(frames):
            fmt, data = compress_rgb(f.rgb)
            if k == 3:
                data = data[:16]  # cut short on the link
            pc.publish(compressed(f.stamp_ns, fmt, data))
            pd.publish(compressed(f.stamp_ns, *compress_depth_units(metres_to_units(f.depth_m, 1000.0))))
            assert _spin_until(ex, lambda k=k: len(processed) > k), f"frame {k} was never handled"
        c = node.stats.values
        assert c["frames_in"] == 6 and c["problem.bad_image"] == 1 and c["poses_out"] == 5, dict(c)
        assert c["state.OK"] == 5 and not c["state.LOST"]
    finally:
        node.close()
        ex.shutdown()
        node.destroy_node()
        pub_node.destroy_node()


def test_colour_without_depth_is_warned_with_its_likely_cause(context) -> None:  # noqa: ANN001
    """A RealSense started without align_depth: colour arrives, the depth topic stays silent. The
    tracker says so within unpaired_warn_s (and counts the colour frames it could not pair)."""
    params = [Parameter("color_topic", value="color/image_raw"), Parameter("depth_topic", value="depth/image_raw"),
              Parameter("camera_info_topic", value="color/camera_info"), Parameter("unpaired_warn_s", value=0.5)]
    node = TrackerNode(context=context, parameter_overrides=params)
    pub_node = rclpy.create_node("feeder", context=context)
    pc = pub_node.create_publisher(Image, "color/image_raw", qos.reliable(50))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(pub_node)
    try:
        assert _spin_until(ex, lambda: pc.get_subscription_count()) and node.wait_until_warm(120)
        f = next(iter(generate_frames(parse_spec("synthetic:w=64,h=48,n=1,seed=2"))))
        t0, k = time.monotonic(), 0
        while not node.stats.values["problem.unpaired_color"] and time.monotonic() - t0 < 10:
            pc.publish(numpy_to_image(f.rgb, "rgb8", f.stamp_ns + k * 33_333_333, "cam"))
            k += 1
            _spin_until(ex, lambda: False, 0.05)
        waited = time.monotonic() - t0
        assert node.stats.values["problem.unpaired_color"] == 1 and 0.5 <= waited < 2.0, waited
        assert node.stats.values["skipped.unpaired"] >= k - 6  # all but the pairer's queue of 5
        assert node.stats.values["poses_out"] == 0
    finally:
        node.close()
        ex.shutdown()
        node.destroy_node()
        pub_node.destroy_node()
