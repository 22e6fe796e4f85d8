"""A robot's own bags: realsense-ros 4.x's layout (raw, and compressed as image_transport writes it)
is read with no topic names given, an ambiguous bag is refused with its candidates, ``--topics``
names them, and the graph maps a compressed realsense bag end to end over DDS."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.errors import ConfigError, DataError, MessageError
from memgs_ros.io.bag_reader import BagSource, BagTopics
from memgs_ros.io.bag_stream import BagStream
from memgs_ros.io.bag_writer import (
    COMPRESSED_TYPE,
    RS_ALIGNED_DEPTH_TOPIC,
    RS_COLOR_INFO_TOPIC,
    RS_COLOR_TOPIC,
    RS_DEPTH_TOPIC,
    MessageFactory,
    compress_depth_units,
    write_realsense_bag,
)
from memgs_ros.io.image_decoding import decode_compressed_depth, decode_compressed_rgb
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

SPEC = SyntheticSpec(width=160, height=120, n_frames=8, seed=5, hole_fraction=0.05)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(generate_frames(SPEC))


@pytest.fixture(scope="module")
def bags(frames: list[Frame], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("rs")
    return {kind: write_realsense_bag(frames, root / kind, compressed=kind == "compressed").path
            for kind in ("raw", "compressed")}


def _valid(d: np.ndarray) -> np.ndarray:
    return np.isfinite(d) & (d > 0)


@pytest.mark.parametrize("kind", ["raw", "compressed"])
def test_a_realsense_bag_is_read_without_topic_names(bags: dict[str, Path], frames: list[Frame], kind: str) -> None:
    src = BagSource(bags[kind])
    # Colour and the depth aligned to it (not the depth camera's own stream beside it), found by type.
    assert src.topics.rgb.startswith(RS_COLOR_TOPIC) and src.topics.depth.startswith(RS_ALIGNED_DEPTH_TOPIC)
    assert src.topics.rgb_info == RS_COLOR_INFO_TOPIC
    assert "aligned_depth_to_color" in src.topic_choice and ("compressedDepth" in src.topic_choice) == (
        kind == "compressed")
    got = list(src)
    assert len(got) == len(frames) and src.camera == frames[0].camera
    for a, b in zip(frames, got):
        assert a.stamp_ns == b.stamp_ns and np.allclose(a.T_wc_gt, b.T_wc_gt)
        err = np.abs(a.rgb.astype(int) - b.rgb)
        assert err.max() == 0 if kind == "raw" else err.mean() < 4.0  # JPEG at quality 95
        ok = _valid(a.depth_m)
        assert np.array_equal(_valid(b.depth_m), ok & (np.rint(a.depth_m * 1000) > 0))
        assert np.abs(a.depth_m[ok] - b.depth_m[ok]).max() <= 0.0005 + 1e-6  # millimetres, both ways
    assert not any("not used (sensor_msgs/msg/Image" in k for k in src.skipped if RS_COLOR_TOPIC in k)


def test_the_compressed_bag_is_smaller_than_half(bags: dict[str, Path]) -> None:
    size = {k: sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) for k, p in bags.items()}
    assert size["compressed"] < 0.5 * size["raw"], size


def test_topics_given_by_name(bags: dict[str, Path]) -> None:
    topics = BagTopics.parse(f"color={RS_COLOR_TOPIC},depth={RS_DEPTH_TOPIC}")  # the unaligned stream, on purpose
    src = BagSource(bags["raw"], topics=topics)
    assert src.topics.depth == RS_DEPTH_TOPIC and src.topics.rgb_info == RS_COLOR_INFO_TOPIC and len(src) == 8
    with pytest.raises(DataError, match=r"no topic /camera/nope .*image_raw"):
        BagSource(bags["raw"], topics=BagTopics.parse("color=/camera/nope"))
    for bad in ("colour=/a", "color", "color="):
        with pytest.raises(ConfigError, match="--topics item"):
            BagTopics.parse(bad)
    assert BagTopics.parse("") == BagTopics()


def _bag(path: Path, frames: list[Frame], streams: list[tuple[str, str]]) -> Path:
    """A bag with the given (topic, 'rgb8' | '16UC1') image streams and colour camera_info."""
    with BagStream(path) as bag:
        mf = MessageFactory(bag.typestore, ros1=False)
        bag.add_topic(RS_COLOR_INFO_TOPIC, "sensor_msgs/msg/CameraInfo")
        for topic, _ in streams:
            bag.add_topic(topic, "sensor_msgs/msg/Image")
        for f in frames:
            h = mf.header(f.stamp_ns, "camera_color_optical_frame")
            bag.write(RS_COLOR_INFO_TOPIC, f.stamp_ns,
                      mf.serialize(mf.camera_info(h, f.camera), "sensor_msgs/msg/CameraInfo"))
            for topic, enc in streams:
                data = f.rgb if enc == "rgb8" else np.nan_to_num(f.depth_m * 1000).astype(np.uint16)
                bag.write(topic, f.stamp_ns, mf.serialize(mf.image(h, data, enc), "sensor_msgs/msg/Image"))
    return path


def test_an_ambiguous_bag_is_refused_with_its_candidates(frames: list[Frame], tmp_path: Path) -> None:
    two = _bag(tmp_path / "two", frames, [("/left/color/image_raw", "rgb8"), ("/right/color/image_raw", "rgb8"),
                                          (RS_ALIGNED_DEPTH_TOPIC, "16UC1")])
    with pytest.raises(DataError, match=r"2 colour image topics \(/left/color/image_raw, /right/color/image_raw\)"):
        BagSource(two)
    assert len(BagSource(two, topics=BagTopics.parse("color=/left/color/image_raw"))) == 8


def test_colour_without_depth_says_what_to_turn_on(frames: list[Frame], tmp_path: Path) -> None:
    bag = _bag(tmp_path / "nodepth", frames, [(RS_COLOR_TOPIC, "rgb8")])
    with pytest.raises(DataError, match="align_depth.enable"):
        BagSource(bag)
    assert len(BagSource(bag, with_depth=False)) == 8  # monocular maps it


def test_compressed_depth_is_image_transports_format(frames: list[Frame]) -> None:
    units = np.nan_to_num(frames[0].depth_m * 1000).astype(np.uint16)
    fmt, data = compress_depth_units(units)
    assert fmt == "16UC1; compressedDepth png" and bytes(data[:4]) == b"\1\0\0\0" and bytes(data[12:16]) == b"\x89PNG"

    class Msg:  # a CompressedImage as rclpy or rosbags hands it over
        def __init__(self, fmt: str, data: np.ndarray) -> None:
            self.format, self.data = fmt, data

    d = decode_compressed_depth(Msg(fmt, data), 1000.0)
    assert np.array_equal(np.nan_to_num(d * 1000).round().astype(np.uint16), units)
    # 32FC1 as quantised inverse depth (depthParam a, b): depth = a / (value - b); image_transport's
    # defaults (depth_quantization 100, depth_max 10 m): a = 100 * 101, b = 1 - a / 10
    a, b = 100.0 * 101.0, 1.0 - 100.0 * 101.0 / 10.0
    import cv2

    with np.errstate(divide="ignore"):
        inv = np.where(units > 0, np.rint(a / (units / 1000.0) + b), 0).astype(np.uint16)
    header = np.frombuffer(np.array([0], "<i4").tobytes() + np.array([a, b], "<f4").tobytes(), np.uint8)
    png = cv2.imencode(".png", inv)[1].reshape(-1)
    d32 = decode_compressed_depth(Msg("32FC1; compressedDepth png", np.concatenate([header, png])))
    ok = units > 0
    assert np.abs(d32[ok] - units[ok] / 1000.0).max() < 0.002 and np.isnan(d32[~ok]).all()
    for bad, why in ((Msg(fmt, data[:10]), "no header"), (Msg(fmt, data[:40]), "does not decode"),
                     (Msg("16UC1; compressedDepth rvl", data), "RVL"), (Msg("rgb8; jpeg compressed bgr8", data),
                                                                      "not compressedDepth")):
        with pytest.raises(MessageError, match=why):
            decode_compressed_depth(bad)
    with pytest.raises(MessageError, match="holds depth"):
        decode_compressed_rgb(Msg(fmt, data))
    assert COMPRESSED_TYPE == "sensor_msgs/msg/CompressedImage"


@pytest.mark.ros
@pytest.mark.slow
def test_memgs_run_maps_a_compressed_realsense_bag(tmp_path: Path, ros_domain_id: int) -> None:
    """`memgs run --bag` with no topic flags, over real DDS: the compressed realsense bag maps as
    the same frames in TUM's layout would (the runner's own ATE against the bag's ground truth)."""
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from memgs_ros.core.metrics.trajectory import ate
    from memgs_ros.io.tum import read_trajectory
    from memgs_ros.orchestration.pipeline import RunOptions, run_pipeline

    spec = SyntheticSpec(width=320, height=240, n_frames=30, seed=3)
    frames = list(generate_frames(spec))
    bag = write_realsense_bag(frames, tmp_path / "rs_compressed", compressed=True).path
    fast = {"mapper.iterations_per_frame": 3, "mapper.final_iterations": 100,
            "mapper.mapping.merge_start_iter": 60, "mapper.mapping.merge_interval": 60}
    s = run_pipeline(RunOptions(source=str(bag), config="synthetic", out_dir=tmp_path / "out",
                                namespace=f"/memgs_test_{os.getpid()}_{os.urandom(3).hex()}", domain_id=ros_domain_id,
                                overrides=fast, timeout_s=600), progress=False)
    assert s.frames == 30 and s.poses == 30 and s.gaussians > 1000
    est_stamps, est_poses = read_trajectory(Path(s.trajectory_path))
    err = ate(est_stamps, est_poses, np.array([f.stamp_ns for f in frames]), np.stack([f.T_wc_gt for f in frames]))
    assert err.n_matched == 30 and err.rmse_m < 0.02, err.rmse_m
