"""Recorded outputs: the bag stream underneath, the --record checks, the recorder node in-process,
and a short run over real DDS whose mcap file rosbags reads back."""
from __future__ import annotations

import os
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from memgs_ros.cli import main
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.bag_stream import BackgroundBagStream, BagStream, ros2_typestore
from memgs_ros.io.bag_writer import MessageFactory, write_bag
from memgs_ros.io.synthetic import generate_frames, parse_spec
from memgs_ros.orchestration.run_files import check_record_path


def _read(path: Path) -> tuple[dict[str, str], list[tuple[str, int, bytes]]]:
    """({topic: msgtype}, [(topic, bag time ns, raw CDR)]) of a single-file bag, with rosbags and no
    metadata.yaml (what Foxglove and ``ros2 bag`` get)."""
    from rosbags.rosbag2 import Reader

    with Reader(path) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        return types, [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]


def _pose_cdr(stamp_s: int, x: float) -> bytes:
    mf = MessageFactory(ros2_typestore(), ros1=False)
    msg = mf.pose_stamped(mf.header(stamp_s * 10**9, "map"), np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * x)
    return mf.serialize(msg, "geometry_msgs/msg/PoseStamped")


# --------------------------------------------------------------------------- the bag stream


def test_bag_stream_writes_raw_cdr_that_rosbags_reads_back(tmp_path: Path) -> None:
    out = tmp_path / "rec.mcap"
    with BagStream(out) as bag:
        bag.add_topic("/memgs/pose", "geometry_msgs/msg/PoseStamped")
        for i in range(3):
            assert bag.write("/memgs/pose", 1_000 + i, _pose_cdr(i, float(i)))
        assert not out.exists()  # only the temporary file exists while recording
    assert bag.write("/memgs/pose", 9, _pose_cdr(9, 9.0)) is False  # closed: dropped, not an error
    types, msgs = _read(out)
    assert types == {"/memgs/pose": "geometry_msgs/msg/PoseStamped"}
    assert [t for _, t, _ in msgs] == [1000, 1001, 1002]
    ts = ros2_typestore()
    last = ts.deserialize_cdr(msgs[-1][2], "geometry_msgs/msg/PoseStamped")
    assert last.pose.position.x == 2.0 and last.header.stamp.sec == 2
    assert [p.name for p in tmp_path.iterdir()] == ["rec.mcap"]  # no temporary folder left


def test_bag_stream_replaces_only_when_complete_and_abort_keeps_the_old_file(tmp_path: Path) -> None:
    out = tmp_path / "rec.mcap"
    out.write_bytes(b"old")
    with pytest.raises(DataError, match="already exists"):
        BagStream(out)  # write_bag's rule: never overwrite unless asked
    bag = BagStream(out, overwrite=True)
    bag.add_topic("/a", "std_msgs/msg/String")
    assert out.read_bytes() == b"old"
    bag.abort()
    assert out.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["rec.mcap"]
    with BagStream(out, overwrite=True) as bag:
        bag.add_topic("/a", "std_msgs/msg/String")
    assert _read(out) == ({"/a": "std_msgs/msg/String"}, [])
    with pytest.raises(DataError, match="not a ROS 2 Jazzy type"), BagStream(tmp_path / "b.mcap") as bag:
        bag.add_topic("/x", "my_pkg/msg/Unknown")
    assert not (tmp_path / "b.mcap").exists()
    (tmp_path / "dir.mcap").mkdir()
    with pytest.raises(DataError, match="already exists"):
        BagStream(tmp_path / "dir.mcap", overwrite=True)


def test_background_stream_survives_ctrl_c_in_the_caller_and_reports_write_errors(tmp_path: Path) -> None:
    import _thread
    import signal
    import threading

    out = tmp_path / "bg.mcap"
    bag = BackgroundBagStream(out, max_queued=8)  # small: the caller waits on the writer too
    bag.add_topic("/memgs/pose", "geometry_msgs/msg/PoseStamped")
    sent = 0
    interrupted = threading.Event()

    def ctrl_c() -> None:  # what Ctrl-C does to the main thread, again until it lands in our loop
        while not interrupted.wait(0.2):  # (library code may swallow one that lands inside it)
            _thread.interrupt_main()

    # Python's own SIGINT handler, whatever an earlier test in this process left installed (a
    # handler that only sets a flag would swallow every simulated Ctrl-C).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    threading.Thread(target=ctrl_c, daemon=True).start()
    deadline = time.monotonic() + 60.0
    try:
        with pytest.raises(KeyboardInterrupt):
            while time.monotonic() < deadline:  # bounded: a lost interrupt fails the test, never hangs it
                if bag.write("/memgs/pose", 10 + sent, _pose_cdr(sent, float(sent))):
                    sent += 1
    finally:
        interrupted.set()
        if previous is not None:  # None: installed outside Python, left as it is
            signal.signal(signal.SIGINT, previous)
    assert bag.close() > 0 and not bag.is_open and bag.write("/memgs/pose", 0, b"") is False
    _, msgs = _read(out)  # whole: every record the caller handed over, none cut in half
    # (the interrupt may land after the last one was queued but before `sent` counted it)
    assert sent > 0 and len(msgs) in (sent, sent + 1), (sent, len(msgs))
    assert [t for _, t, _ in msgs] == list(range(10, 10 + len(msgs)))
    ts = ros2_typestore()
    last = ts.deserialize_cdr(msgs[-1][2], "geometry_msgs/msg/PoseStamped")
    assert last.pose.position.x == len(msgs) - 1

    bad = BackgroundBagStream(tmp_path / "bad.mcap")
    with pytest.raises(DataError, match="not a ROS 2 Jazzy type"):
        bad.add_topic("/x", "my_pkg/msg/Unknown")  # refused at once, not in the thread
    bad.write("/never/added", 1, b"\0")  # fails in the writer thread ...
    with pytest.raises(DataError, match="cannot write bag"):
        bad.close()  # ... and is reported here; nothing is left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bg.mcap"]


def test_write_bag_still_writes_frames_through_the_stream(tmp_path: Path) -> None:
    res = write_bag(generate_frames(parse_spec("synthetic:w=32,h=24,n=2,seed=1")), tmp_path / "s.mcap")
    types, msgs = _read(res.path)
    assert res.frames == 2 and Counter(t for t, _, _ in msgs)["/camera/rgb/image_color"] == 2
    assert types["/camera/depth/image"] == "sensor_msgs/msg/Image"


# --------------------------------------------------------------------------- --record checks


def test_record_path_checks(tmp_path: Path) -> None:
    assert check_record_path(tmp_path / "new" / "deeper" / "r.mcap") == (tmp_path / "new/deeper/r.mcap").resolve()
    assert (tmp_path / "new" / "deeper").is_dir()
    with pytest.raises(ConfigError, match=r"ending in \.mcap"):
        check_record_path(tmp_path / "r.bag")
    (tmp_path / "folder.mcap").mkdir()
    with pytest.raises(DataError, match="is an existing folder"):
        check_record_path(tmp_path / "folder.mcap")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(DataError, match="cannot create its folder"):
        check_record_path(tmp_path / "afile" / "r.mcap")


@pytest.mark.parametrize("command", ["run", "demo", "eval"])
@pytest.mark.parametrize("record, fragment", [
    ("rec.txt", "ending in .mcap"), ("folder.mcap", "is an existing folder"), ("afile/r.mcap", "cannot create")])
def test_bad_record_path_is_refused_before_anything_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, record: str, fragment: str) -> None:
    (tmp_path / "folder.mcap").mkdir()
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "out"
    source = ["--bag", "synthetic:w=32,h=24,n=3,seed=1"] if command == "run" else (
        ["synthetic:w=32,h=24,n=3,seed=1"] if command == "eval" else [])
    code = main([command, *source, "--out", str(out), "--record", str(tmp_path / record)])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], err
    assert err[0].startswith(f"memgs {command}: error: --record") and fragment in err[0], err[0]
    # nothing ran: no node logs, no bag written by demo
    assert not (out / "logs").exists() and not (out / "synthetic.mcap").exists()


def test_recorder_parameters_are_checked_like_every_node_s() -> None:
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from memgs_ros.cli.run import check_config

    params = check_config("synthetic", {"recorder.topics": ["memgs/pose"], "recorder.discovery_period_s": 1.0})
    assert params["recorder"]["topics"] == ["memgs/pose"]
    with pytest.raises(ConfigError, match="recorder has no parameter 'topic'"):
        check_config("synthetic", {"recorder.topic": ["memgs/pose"]})


# --------------------------------------------------------------------------- the node in-process


def test_recorder_node_adapts_to_publishers_and_writes_the_file_on_shutdown(
        tmp_path: Path, context: object) -> None:
    rclpy = pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from memgs_ros.nodes.recorder.node import RecorderNode
    from memgs_ros.ros import qos

    with pytest.raises(ConfigError, match="'path' is required"):
        RecorderNode(context=context)
    with pytest.raises(ConfigError, match="must end in .mcap"):
        RecorderNode(context=context, parameter_overrides=[Parameter("path", value=str(tmp_path / "r.db3"))])
    with pytest.raises(ConfigError, match="parameter 'topics'"):
        RecorderNode(context=context, parameter_overrides=[Parameter("path", value=str(tmp_path / "r.mcap")),
                                                           Parameter("topics", value=["no spaces allowed"])])
    assert not list(tmp_path.iterdir())  # refused before any file was opened

    peer = rclpy.create_node("peer", context=context)
    latched = peer.create_publisher(String, "memgs/tracking_state", qos.latched())
    latched.publish(String(data="before the recorder"))  # latched: must still reach the file
    best_effort = peer.create_publisher(PoseStamped, "cam/pose", qos.sensor())  # a RELIABLE reader hears none
    out = tmp_path / "r.mcap"
    rec = RecorderNode(context=context, parameter_overrides=[
        Parameter("path", value=str(out)),
        Parameter("topics", value=["memgs/tracking_state", "/cam/pose", "never/published"])])
    executor = SingleThreadedExecutor(context=context)
    for node in (rec, peer):
        executor.add_node(node)
    end = time.monotonic() + 20.0
    while len(rec.recorded) < 2 and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    assert rec.recorded == {"/memgs/tracking_state": "std_msgs/msg/String", "/cam/pose": "geometry_msgs/msg/PoseStamped"}
    assert rec.pending == ["/never/published"]
    # Best effort: poses sent before the recorder's reader is matched are lost, so keep sending
    # (a loaded machine can take seconds to match) until five are in the file, and the latched
    # state (delivered once its reader matches) is too.
    end = time.monotonic() + 30.0
    while time.monotonic() < end and (rec.bag.counts.get("/cam/pose", 0) < 5
                                      or rec.bag.counts.get("/memgs/tracking_state", 0) < 1):
        best_effort.publish(PoseStamped())
        executor.spin_once(timeout_sec=0.05)
    rec.close()
    executor.shutdown()
    rec.destroy_node()
    peer.destroy_node()
    types, msgs = _read(out)
    counts = Counter(t for t, _, _ in msgs)
    assert types == rec.recorded and counts["/memgs/tracking_state"] == 1 and counts["/cam/pose"] >= 5
    ts = ros2_typestore()
    state = next(raw for t, _, raw in msgs if t == "/memgs/tracking_state")
    assert ts.deserialize_cdr(state, "std_msgs/msg/String").data == "before the recorder"


# --------------------------------------------------------------------------- end to end


SPEC = "synthetic:w=320,h=240,n=15,seed=3"
FAST = {"mapper.iterations_per_frame": 3, "mapper.final_iterations": 50,
        "mapper.mapping.merge_start_iter": 60, "mapper.mapping.merge_interval": 60}


@pytest.mark.ros
@pytest.mark.slow
def test_run_records_every_output_topic(tmp_path: Path, ros_domain_id: int) -> None:
    pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")
    from memgs_ros.core.map_io.map_delta import decode, unpack_rgb
    from memgs_ros.core.map_io.ply import load_ply
    from memgs_ros.orchestration.pipeline import RunOptions, run_pipeline

    bag = write_bag(generate_frames(parse_spec(SPEC)), tmp_path / "synthetic.mcap").path
    ns = f"/memgs_test_{os.getpid()}_{os.urandom(3).hex()}"
    record = tmp_path / "rec" / "run.mcap"
    s = run_pipeline(RunOptions(source=str(bag), config="synthetic", out_dir=tmp_path / "out", namespace=ns,
                                domain_id=ros_domain_id, overrides=FAST, timeout_s=300,
                                record=check_record_path(record)), progress=False)
    assert s.frames == 15 and s.poses == 15

    types, msgs = _read(record)
    counts = Counter(t for t, _, _ in msgs)
    t = {name: f"{ns}/memgs/{name}" for name in (
        "pose", "odom", "path", "tracking_state", "keyframe/pose", "map/delta", "mapper/snapshot",
        "map/gaussians", "render/color", "render/depth", "render/camera_info", "tracker/stats",
        "mapper/stats", "merger/stats", "keyframe_sampler/stats", "player/stats")}
    expected_types = {
        "pose": "geometry_msgs/msg/PoseStamped", "odom": "nav_msgs/msg/Odometry", "path": "nav_msgs/msg/Path",
        "tracking_state": "std_msgs/msg/String", "keyframe/pose": "geometry_msgs/msg/PoseStamped",
        "map/delta": "sensor_msgs/msg/PointCloud2", "mapper/snapshot": "sensor_msgs/msg/PointCloud2",
        "map/gaussians": "sensor_msgs/msg/PointCloud2", "render/color": "sensor_msgs/msg/Image",
        "render/depth": "sensor_msgs/msg/Image", "render/camera_info": "sensor_msgs/msg/CameraInfo",
        **{f"{n}/stats": "diagnostic_msgs/msg/DiagnosticArray"
           for n in ("tracker", "mapper", "merger", "keyframe_sampler", "player")}}
    for name, msgtype in expected_types.items():
        assert types.get(t[name]) == msgtype, (name, types.get(t[name]))
        assert counts[t[name]] >= 1, (name, counts)
    # every frame tracked: one pose, one tracking state, and odometry from the second (the first
    # starts the map: its pose is the origin, fitted to nothing); every keyframe's pose
    assert counts[t["pose"]] == counts[t["tracking_state"]] == s.frames == counts[t["odom"]] + 1
    assert counts[t["keyframe/pose"]] == s.keyframes
    assert counts[t["map/delta"]] == s.delta_messages
    assert counts[t["render/color"]] == counts[t["render/camera_info"]]
    # TF in the run's namespace (<ns>/tf, as multi-robot launches remap it): the body per tracked frame
    assert types.get(f"{ns}/tf") == types.get(f"{ns}/tf_static") == "tf2_msgs/msg/TFMessage", types
    assert counts[f"{ns}/tf"] == s.frames and counts[f"{ns}/tf_static"] >= 1
    # the run's own namespace only
    assert all(name.startswith(f"{ns}/memgs/") or name in (f"{ns}/tf", f"{ns}/tf_static") for name in types)

    ts = ros2_typestore()  # rosbags alone reads it, as Foxglove would
    raw_map = [raw for n, _, raw in msgs if n == t["map/gaussians"]][-1]
    last_map = ts.deserialize_cdr(raw_map, "sensor_msgs/msg/PointCloud2")
    assert last_map.width - 1 == s.gaussians == len(load_ply(s.ply_path))  # row 0 is the META row
    assert "rgb" in [f.name for f in last_map.fields]
    # and rclpy: the recorded bytes are the merger's message, which decodes as the saved map
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from memgs_ros.ros.codecs import pointcloud2_to_structured

    rows = pointcloud2_to_structured(deserialize_message(raw_map, PointCloud2))
    decoded = decode(rows)
    assert len(decoded.upserts) == s.gaussians
    expected = np.rint(np.clip(0.5 + 0.28209479177387814 * decoded.upserts.f_dc.astype(np.float64), 0, 1) * 255)
    assert np.array_equal(unpack_rgb(rows["rgb"][1:]), expected.astype(np.uint8))
    ply = load_ply(s.ply_path)
    assert np.array_equal(np.sort(ply.xyz[:, 0]), np.sort(decoded.upserts.xyz[:, 0]))
    image = ts.deserialize_cdr([raw for n, _, raw in msgs if n == t["render/color"]][-1], "sensor_msgs/msg/Image")
    assert image.encoding == "rgb8" and image.width * image.height * 3 == len(image.data)
    assert not list(record.parent.glob(".*"))  # no temporary file left beside the recording
