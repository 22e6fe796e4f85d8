"""Bags: ROS 2 MCAP/sqlite3 round trips, TUM's ROS 1 layout, bad messages, corrupt files, decoding."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.errors import DataError, MessageError
from memgs_ros.io.bag_reader import BagSource, BagTopics
from memgs_ros.io.bag_writer import (
    DEPTH_TOPIC,
    RGB_INFO_TOPIC,
    RGB_TOPIC,
    MessageFactory,
    chain_T_kinect_optical,
    ros1_typestore,
    ros2_typestore,
    write_bag,
    write_ros1_tum_bag,
)
from memgs_ros.io.image_decoding import decode_camera_info, decode_depth, decode_rgb
from memgs_ros.io.sources import SyntheticSource, open_source
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames, write_tum_folder

SPEC = SyntheticSpec(width=64, height=48, n_frames=6, seed=4, hole_fraction=0.05)


@pytest.fixture(scope="module")
def frames():
    return list(generate_frames(SPEC))


def assert_same_frames(expected, got, depth_atol=0.0):
    assert len(got) == len(expected)
    for a, b in zip(expected, got):
        assert a.stamp_ns == b.stamp_ns
        np.testing.assert_array_equal(a.rgb, b.rgb)
        # bags decode invalid depth as NaN, whether the source wrote 0 or NaN
        valid = np.isfinite(a.depth_m) & (a.depth_m > 0)
        np.testing.assert_array_equal(np.isnan(b.depth_m), ~valid)
        np.testing.assert_allclose(b.depth_m[valid], a.depth_m[valid], atol=depth_atol)
        np.testing.assert_allclose(b.T_wc_gt, a.T_wc_gt, atol=1e-8)
        assert b.camera == a.camera


@pytest.mark.parametrize("name", ["seq.mcap", "seq.db3", "seq_dir_mcap", "seq_dir_sqlite3"])
def test_ros2_bag_round_trip(tmp_path, frames, name):
    storage = "sqlite3" if name.endswith(("db3", "sqlite3")) else "mcap"
    out = tmp_path / name
    res = write_bag(frames, out, storage=storage)
    assert res.frames == 6 and res.bytes > 64 * 48 * 3 * 6
    assert out.is_file() == name.endswith((".mcap", ".db3"))
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # temp files gone
    src = open_source(out)
    assert isinstance(src, BagSource) and len(src) == 6 and src.gt_coverage == 1.0
    assert_same_frames(frames, list(src))
    assert dict(src.skipped) == {}
    stamps, poses = src.ground_truth()
    np.testing.assert_array_equal(stamps, [f.stamp_ns for f in frames])
    # ground truth from /tf alone (pose topic ignored once a camera frame is named) agrees
    tf_only = BagSource(out, topics=BagTopics(camera_frame="camera_rgb_optical_frame"))
    assert tf_only.gt_source.startswith("tf world")
    np.testing.assert_allclose(tf_only.ground_truth()[1], poses, atol=1e-9)
    with pytest.raises(DataError, match="already exists"):
        write_bag(frames, out, storage=storage)


def test_tum_folder_to_bag_to_frames(tmp_path, frames):
    """The convert path: TUM folder -> ROS 2 bag -> reader gives the folder's frames and poses."""
    folder = tmp_path / "tum"
    write_tum_folder(frames, folder)
    res = write_bag(open_source(folder), tmp_path / "conv.mcap")
    assert res.frames == 6
    assert_same_frames(frames, list(open_source(tmp_path / "conv.mcap")), depth_atol=0.5 / 5000 + 1e-6)


def test_convert_writes_a_tum_layout_ros1_bag(tmp_path, frames, capsys):
    """``memgs convert FOLDER X.bag``: TUM's ROS 1 layout, read back frame for frame."""
    from memgs_ros.cli import main

    folder = tmp_path / "tum"
    write_tum_folder(frames, folder, depth_factor=5000.0)
    out = tmp_path / "tum.bag"
    assert main(["convert", str(folder), str(out), "--no-progress"]) == 0
    assert out.read_bytes()[:13] == b"#ROSBAG V2.0\n"
    src = open_source(out)
    assert src.gt_source == "tf world -> openni_rgb_optical_frame"
    assert_same_frames(frames, list(src), depth_atol=1e-4)
    assert main(["convert", str(folder), str(tmp_path / "b.bag"), "--storage", "mcap", "--no-progress"]) == 2
    assert "--storage is for ROS 2 bags" in capsys.readouterr().err


def test_ros1_tum_layout_gives_composed_ground_truth(tmp_path, frames, caplog):
    # the static chain is not the identity, so an uncomposed /world -> /kinect would be wrong
    assert np.abs(chain_T_kinect_optical() - np.eye(4)).max() > 0.5
    out = tmp_path / "rgbd_dataset_freiburg1_synth.bag"
    write_ros1_tum_bag(frames, out)
    assert out.read_bytes()[:13] == b"#ROSBAG V2.0\n"
    assert b"bz2" in out.read_bytes()[:8192] or b"compression=bz2" in out.read_bytes()
    with caplog.at_level(logging.INFO, logger="memgs_ros.io.bag_reader"):
        src = open_source(out)
        got = list(src)
    assert src.gt_source == "tf world -> openni_rgb_optical_frame"
    assert_same_frames(frames, got)
    stamps, poses = src.ground_truth()
    assert len(stamps) == 6
    np.testing.assert_allclose(poses, np.array([f.T_wc_gt for f in frames]), atol=1e-9)
    # naming the frame with ROS 1's slash works too, and a frame that is not in the tree gives no gt
    assert BagSource(out, topics=BagTopics(camera_frame="/openni_rgb_optical_frame")).gt_coverage == 1.0
    none = BagSource(out, topics=BagTopics(camera_frame="/nowhere"))
    assert none.gt_coverage == 0.0 and all(f.T_wc_gt is None for f in none)


def _write_custom_ros2(path: Path, frames, extra) -> None:
    """A ROS 2 bag with the frames plus ``extra(writer, ts, mf, conns)`` messages."""
    ts = ros2_typestore()
    mf = MessageFactory(ts, ros1=False)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {
            "rgb": w.add_connection(RGB_TOPIC, "sensor_msgs/msg/Image", typestore=ts),
            "depth": w.add_connection(DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=ts),
            "info": w.add_connection(RGB_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", typestore=ts),
        }
        for k, f in enumerate(frames):
            s = f.stamp_ns
            w.write(conns["info"], s, mf.serialize(mf.camera_info(mf.header(s, "cam"), f.camera), "sensor_msgs/msg/CameraInfo"))
            w.write(conns["rgb"], s, mf.serialize(mf.image(mf.header(s, "cam"), f.rgb, "rgb8"), "sensor_msgs/msg/Image"))
            if k != 2:  # depth of frame 2 missing; the others jittered by up to 7 ms
                sd = s + (7_000_000 if k % 2 else -5_000_000)
                w.write(conns["depth"], sd,
                        mf.serialize(mf.image(mf.header(sd, "cam"), f.depth_m, "32FC1"), "sensor_msgs/msg/Image"))
        extra(w, ts, mf, conns)


def test_bad_and_unknown_messages_are_counted_and_skipped(tmp_path, frames, caplog):
    s0 = frames[0].stamp_ns

    def extra(w, ts, mf, conns):
        # garbage bytes on the colour topic: does not deserialise
        w.write(conns["rgb"], s0 + 1, b"\x00\x01\x00\x00\xff")
        # deserialises, but the buffer is too short for its size
        short = mf.image(mf.header(s0 + 2, "cam"), frames[0].rgb, "rgb8")
        short.data = short.data[:100]
        w.write(conns["rgb"], s0 + 2, mf.serialize(short, "sensor_msgs/msg/Image"))
        # an encoding nobody decodes
        yuv = mf.image(mf.header(s0 + 3, "cam"), frames[0].rgb, "rgb8")
        yuv.encoding = "yuv422"
        w.write(conns["rgb"], s0 + 3, mf.serialize(yuv, "sensor_msgs/msg/Image"))
        # unknown topics (one of TUM's) and a known topic carrying the wrong type
        s_type = "std_msgs/msg/String"
        c = w.add_connection("/cortex_marker_array", s_type, typestore=ts)
        for k in range(3):
            w.write(c, s0 + k, ts.serialize_cdr(ts.types[s_type](data="x"), s_type))
        c = w.add_connection("/groundtruth/pose", s_type, typestore=ts)
        w.write(c, s0, ts.serialize_cdr(ts.types[s_type](data="not a pose"), s_type))

    out = tmp_path / "bad"
    _write_custom_ros2(out, frames, extra)
    with caplog.at_level(logging.WARNING, logger="memgs_ros.io.bag_reader"):
        src = BagSource(out)
        got = list(src)
    # jittered depth pairs within 20 ms; frame 2 has no depth and is dropped
    assert [f.stamp_ns for f in got] == [f.stamp_ns for k, f in enumerate(frames) if k != 2]
    assert all(f.T_wc_gt is None for f in got)
    np.testing.assert_array_equal(got[0].rgb, frames[0].rgb)
    sk = dict(src.skipped)
    assert sk["malformed message on /camera/rgb/image_color"] == 1
    assert sk["bad message on /camera/rgb/image_color"] == 2
    assert sk["topic /cortex_marker_array"] == 3
    assert sk["type std_msgs/msg/String on /groundtruth/pose"] == 1
    # logged once per kind, naming the bag
    bad_logs = [r for r in caplog.records if "bad message on /camera/rgb/image_color" in r.getMessage()]
    assert len(bad_logs) == 1 and "bad" in bad_logs[0].getMessage()
    # tighter pairing drops the 7 ms pairs
    assert len(BagSource(out, max_dt_s=0.006)) == 2  # frames 0 and 4 (-5 ms)


@pytest.mark.parametrize("name", ["t.mcap", "t.db3", "t.bag"])
def test_truncated_bag_is_a_data_error_naming_the_file(tmp_path, frames, name):
    full = tmp_path / ("full_" + name)
    if name.endswith(".bag"):
        write_ros1_tum_bag(frames, full)
    else:
        write_bag(frames, full)
    data = full.read_bytes()
    cut = tmp_path / name
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=rf"{name}: cannot read bag"):
        list(open_source(cut))
    junk = tmp_path / ("junk_" + name)
    junk.write_bytes(b"this is not a bag at all" * 10)
    with pytest.raises(DataError, match=rf"junk_{name}"):
        list(open_source(junk))


def test_missing_inputs(tmp_path):
    with pytest.raises(DataError, match="no such file or directory"):
        open_source(tmp_path / "nope.mcap")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="neither a TUM folder"):
        open_source(tmp_path / "empty")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(DataError, match="unknown input"):
        open_source(tmp_path / "x.txt")


def _image(mf, data, encoding, step=None, bigendian=False):
    msg = mf.image(mf.header(0, "c"), data, encoding)
    if bigendian:
        msg.data = np.ascontiguousarray(data.astype(data.dtype.newbyteorder(">"))).view(np.uint8).reshape(-1)
        msg.is_bigendian = 1
    if step is not None:
        h = data.shape[0]
        rows = np.asarray(msg.data).reshape(h, -1)
        padded = np.zeros((h, step), np.uint8)
        padded[:, : rows.shape[1]] = rows
        msg.data, msg.step = padded.reshape(-1), step
    return msg


def test_decode_encodings_padding_and_endianness():
    mf = MessageFactory(ros2_typestore(), ros1=False)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    np.testing.assert_array_equal(decode_rgb(_image(mf, rgb, "rgb8")), rgb)
    np.testing.assert_array_equal(decode_rgb(_image(mf, rgb[..., ::-1].copy(), "bgr8", step=24)), rgb)
    gray = rgb[..., 0].copy()
    np.testing.assert_array_equal(decode_rgb(_image(mf, gray, "mono8", step=8)), np.repeat(gray[..., None], 3, 2))
    mm = rng.integers(1, 5000, (5, 7)).astype(np.uint16)
    mm[0, 0] = 0
    for be in (False, True):
        d = decode_depth(_image(mf, mm, "16UC1", step=16, bigendian=be), depth_scale=1000.0)
        assert d.dtype == np.float32 and np.isnan(d[0, 0]) and np.isfinite(d).sum() == mm.size - 1
        np.testing.assert_allclose(d[mm > 0], mm[mm > 0] / 1000.0, rtol=1e-6)
        metres = (mm * 0.001).astype(np.float32)
        metres[1, 1] = np.nan
        d = decode_depth(_image(mf, metres, "32FC1", step=32, bigendian=be))
        assert np.isnan(d[1, 1]) and np.isnan(d[0, 0])
        np.testing.assert_array_equal(d[2:], metres[2:])
    with pytest.raises(MessageError, match="'yuv422' is not a colour encoding"):
        decode_rgb(_image(mf, rgb, "yuv422"))
    short = _image(mf, rgb, "rgb8")
    short.step = 10
    with pytest.raises(MessageError, match="step 10 is less than width"):
        decode_rgb(short)


def test_camera_info_both_ros_versions():
    cam = PinholeCamera(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.2, 0.001, 0.002, 0.05))
    rational = PinholeCamera(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.2, 0.001, 0.002, 0.05, 0.01, 0.02, -0.03))
    for ts, ros1 in ((ros2_typestore(), False), (ros1_typestore(), True)):
        mf = MessageFactory(ts, ros1=ros1)
        assert decode_camera_info(mf.camera_info(mf.header(0, "c"), cam)) == cam
        msg = mf.camera_info(mf.header(0, "c"), rational)
        assert msg.distortion_model == "rational_polynomial"
        assert decode_camera_info(msg) == rational


def test_synthetic_source_and_ground_truth():
    src = open_source("synthetic:w=32,h=24,n=3,seed=5", max_frames=2)
    assert isinstance(src, SyntheticSource) and len(src) == 2 and src.camera.width == 32
    fr = list(src)
    stamps, poses = src.ground_truth()
    assert [f.stamp_ns for f in fr] == stamps.tolist()
    np.testing.assert_array_equal(poses[1], fr[1].T_wc_gt)
