"""The one image decoder: rclpy and rosbags messages decode alike; malformed ones raise MessageError only."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("rclpy")

from rclpy.serialization import deserialize_message  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from memgs_ros.core.geometry.camera import PinholeCamera  # noqa: E402
from memgs_ros.errors import MessageError  # noqa: E402
from memgs_ros.io.bag_reader import BagSource  # noqa: E402
from memgs_ros.io.bag_writer import (  # noqa: E402
    DEPTH_TOPIC,
    RGB_INFO_TOPIC,
    RGB_TOPIC,
    MessageFactory,
    ros1_typestore,
    ros2_typestore,
)
from memgs_ros.io.image_decoding import (  # noqa: E402
    COLOR_ENCODINGS,
    DEPTH_ENCODINGS,
    IMAGE_ENCODINGS,
    decode_camera_info,
    decode_depth,
    decode_rgb,
    image_to_numpy,
)

ROS2 = MessageFactory(ros2_typestore(), ros1=False)
ROS1 = MessageFactory(ros1_typestore(), ros1=True)
PAD_BYTE = 0xFF  # as the high half of a float32 this is NaN, so padding never looks like float metres


def _wire_bytes(arr: np.ndarray, big: bool, pad: int) -> tuple[np.ndarray, int]:
    """[H, W(, C)] array -> (rows as one uint8 buffer with ``pad`` bytes per row, step)."""
    h = arr.shape[0]
    wire = arr.astype(arr.dtype.newbyteorder(">" if big else "<"))
    rows = np.ascontiguousarray(wire).reshape(h, -1).view(np.uint8)
    padded = np.concatenate([rows, np.full((h, pad), PAD_BYTE, np.uint8)], axis=1)
    return padded.reshape(-1), rows.shape[1] + pad


def rclpy_image(arr: np.ndarray, enc: str, big: bool = False, pad: int = 0) -> Image:
    data, step = _wire_bytes(arr, big, pad)
    return Image(height=arr.shape[0], width=arr.shape[1], encoding=enc, is_bigendian=int(big), step=step,
                 data=data.tobytes())


def rosbags_image(mf: MessageFactory) -> Callable[..., Any]:
    def make(arr: np.ndarray, enc: str, big: bool = False, pad: int = 0) -> Any:
        data, step = _wire_bytes(arr, big, pad)
        return mf._t("sensor_msgs/msg/Image")(header=mf.header(0, "c"), height=arr.shape[0], width=arr.shape[1],
                                              encoding=enc, is_bigendian=int(big), step=step, data=data)
    return make


FLAVOURS = {"rclpy": rclpy_image, "rosbags-ros2": rosbags_image(ROS2), "rosbags-ros1": rosbags_image(ROS1)}


def _pixels(enc: str, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    dtype, c = IMAGE_ENCODINGS[enc]
    shape = (h, w) if c == 1 else (h, w, c)
    if dtype == np.float32:  # metres with every kind of invalid value mixed in
        a = rng.uniform(-1.0, 20.0, size=shape).astype(np.float32)
        a[rng.random(shape) < 0.2] = rng.choice(np.array([0.0, np.nan, np.inf, -np.inf], np.float32))
        return a
    # 16-bit depth below 15 m in mm: real depth that the float-mislabel guard must never refuse
    hi = 15000 if dtype == np.uint16 else 255
    return rng.integers(0, hi, size=shape, endpoint=True).astype(dtype)


def _expected_rgb(arr: np.ndarray, enc: str) -> np.ndarray:
    return {"rgb8": lambda: arr, "bgr8": lambda: arr[..., ::-1], "rgba8": lambda: arr[..., :3],
            "bgra8": lambda: arr[..., 2::-1]}.get(enc, lambda: np.repeat(arr[..., None], 3, axis=2))()


def _expected_depth(arr: np.ndarray, scale: float) -> np.ndarray:
    d = arr.astype(np.float32) / np.float32(scale) if arr.dtype == np.uint16 else arr.astype(np.float32)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(d) & (d > 0), d, np.float32(np.nan)).astype(np.float32)


# ----------------------------------------------------------------------------- round trips


@settings(max_examples=60, deadline=None)
@given(enc=st.sampled_from(COLOR_ENCODINGS + DEPTH_ENCODINGS), h=st.integers(1, 8), w=st.integers(1, 8),
       pad=st.integers(0, 9), big=st.booleans(), scale=st.sampled_from([1000.0, 5000.0, 1.0]),
       seed=st.integers(0, 2**16))
def test_every_encoding_round_trips_in_every_flavour(enc: str, h: int, w: int, pad: int, big: bool, scale: float,
                                                      seed: int) -> None:
    arr = _pixels(enc, h, w, np.random.default_rng(seed))
    for flavour, make in FLAVOURS.items():
        msg = make(arr, enc, big, pad)
        np.testing.assert_array_equal(image_to_numpy(msg), arr, err_msg=flavour)
        if enc in COLOR_ENCODINGS:
            out, want = decode_rgb(msg), _expected_rgb(arr, enc)
            assert out.dtype == np.uint8 and out.shape == (h, w, 3), flavour
        else:
            out, want = decode_depth(msg, scale), _expected_depth(arr, scale)
            assert out.dtype == np.float32 and out.shape == (h, w), flavour
        np.testing.assert_array_equal(out, want, err_msg=flavour)  # NaN == NaN here: invalid stays invalid
        assert not np.shares_memory(out, np.asarray(msg.data)), flavour


@settings(max_examples=40, deadline=None)
@given(f=st.tuples(st.floats(1.0, 2000.0), st.floats(1.0, 2000.0)), c=st.tuples(st.floats(-50, 700), st.floats(-50, 500)),
       dist=st.lists(st.floats(-1.0, 1.0), min_size=8, max_size=8), rational=st.booleans(),
       size=st.tuples(st.integers(1, 4000), st.integers(1, 4000)))
def test_camera_info_round_trips_in_every_flavour(f: tuple[float, float], c: tuple[float, float], dist: list[float],
                                                   rational: bool, size: tuple[int, int]) -> None:
    d = tuple(dist) if rational and any(dist[5:]) else tuple(dist[:5])
    cam = PinholeCamera(size[0], size[1], f[0], f[1], c[0], c[1], d)
    from memgs_ros.ros.images import camera_to_camera_info

    for msg in (camera_to_camera_info(cam, 0, "c"), ROS2.camera_info(ROS2.header(0, "c"), cam),
                ROS1.camera_info(ROS1.header(0, "c"), cam)):
        assert decode_camera_info(msg) == cam


def test_bag_and_wire_give_identical_arrays(tmp_path: Path) -> None:
    """The same serialised messages, read by BagSource and deserialised by rclpy as a node gets them."""
    rng = np.random.default_rng(3)
    cam = PinholeCamera(9, 5, 10.0, 10.0, 4.0, 2.0, (0.01, -0.02, 0.0, 0.0, 0.0, 0.001, 0.0, 0.0))
    make = FLAVOURS["rosbags-ros2"]
    colour = [make(_pixels("bgr8", 5, 9, rng), "bgr8", False, 3), make(_pixels("rgba8", 5, 9, rng), "rgba8", True, 0)]
    mm = _pixels("16UC1", 5, 9, rng)
    mm[0, :4] = 0  # no measurement
    depth = [make(mm, "16UC1", True, 6), make(_pixels("32FC1", 5, 9, rng), "32FC1", False, 4)]
    raw: dict[str, list[bytes]] = {"rgb": [], "depth": []}
    ts = ros2_typestore()
    out = tmp_path / "same.mcap"
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {"rgb": w.add_connection(RGB_TOPIC, "sensor_msgs/msg/Image", typestore=ts),
                 "depth": w.add_connection(DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=ts),
                 "info": w.add_connection(RGB_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", typestore=ts)}
        for k, (c, d) in enumerate(zip(colour, depth)):
            stamp = 1_000_000_000 * (k + 1)
            c.header = d.header = ROS2.header(stamp, "cam")
            w.write(conns["info"], stamp, ROS2.serialize(ROS2.camera_info(c.header, cam), "sensor_msgs/msg/CameraInfo"))
            for key, msg in (("rgb", c), ("depth", d)):
                raw[key].append(ROS2.serialize(msg, "sensor_msgs/msg/Image"))
                w.write(conns[key], stamp, raw[key][-1])
    src = BagSource(out, depth_scale=5000.0)
    frames = list(src)
    assert len(frames) == 2 and dict(src.skipped) == {} and src.camera == cam
    for k, frame in enumerate(frames):
        wire_rgb = decode_rgb(deserialize_message(raw["rgb"][k], Image))
        wire_depth = decode_depth(deserialize_message(raw["depth"][k], Image), 5000.0)
        np.testing.assert_array_equal(frame.rgb, wire_rgb)
        np.testing.assert_array_equal(frame.depth_m, wire_depth)
        assert np.isnan(frame.depth_m).any() and np.isfinite(frame.depth_m).any()


# ----------------------------------------------------------------------------- malformed messages


def _with(msg: Any, **changes: Any) -> Any:
    for key, value in changes.items():
        setattr(msg, key, value)
    return msg


_RGB = np.zeros((2, 3, 3), np.uint8)
_MALFORMED: list[tuple[str, dict[str, Any], str]] = [
    ("rgb8", {"step": 8}, r"step 8 is less than width\*bytes_per_pixel = 9"),
    ("rgb8", {"data": bytes(17)}, r"17 bytes, expected step\*height = 9\*2 = 18"),
    ("rgb8", {"data": bytes(19)}, r"19 bytes, expected step\*height = 9\*2 = 18"),  # a longer buffer too
    ("rgb8", {"height": 0}, "no pixels"),
    ("rgb8", {"width": 0}, "no pixels"),
    ("rgb8", {"encoding": "yuv422"}, "'yuv422' is not a colour encoding"),
    ("rgb8", {"encoding": "8UC3"}, "'8UC3' is not a colour encoding.*no channel order"),
    ("rgb8", {"encoding": "32FC1"}, "'32FC1' is not a colour encoding"),
]


@pytest.mark.parametrize("flavour", list(FLAVOURS))
@pytest.mark.parametrize("enc,changes,fragment", _MALFORMED)
def test_malformed_images_raise_message_error(flavour: str, enc: str, changes: dict[str, Any], fragment: str) -> None:
    msg = FLAVOURS[flavour](_RGB, enc)
    if "data" in changes and flavour != "rclpy":
        changes = {**changes, "data": np.frombuffer(changes["data"], np.uint8)}
    with pytest.raises(MessageError, match=fragment):
        decode_rgb(_with(msg, **changes))


def test_depth_refusals_name_the_problem() -> None:
    mm = np.ones((2, 3), np.uint16)
    with pytest.raises(MessageError, match="'rgb8' is not a depth encoding"):
        decode_depth(rclpy_image(_RGB, "rgb8"))
    with pytest.raises(MessageError, match="depth_scale must be a positive number"):
        decode_depth(rclpy_image(mm, "16UC1"), float("nan"))
    with pytest.raises(MessageError, match=r"12 bytes, expected step\*height = 12\*2 = 24 \(the data is exactly "
                                           r"a 3x2 16UC1 image"):
        decode_depth(_with(rclpy_image(mm, "16UC1"), encoding="32FC1", step=12))
    with pytest.raises(MessageError, match="has no field encoding"):
        decode_depth(object())
    with pytest.raises(MessageError, match="image data must be uint8 bytes"):
        decode_depth(_with(FLAVOURS["rosbags-ros2"](mm, "16UC1"), data=np.zeros(12, np.float32)))
    with pytest.raises(MessageError, match="field height is not an integer"):
        decode_depth(_with(FLAVOURS["rosbags-ros2"](mm, "16UC1"), height="two"))


@settings(max_examples=150, deadline=None)
@given(enc=st.sampled_from([*IMAGE_ENCODINGS, "8UC3", "yuv422", ""]), h=st.integers(0, 6), w=st.integers(0, 6),
       step=st.integers(0, 30), n=st.integers(0, 200), big=st.booleans(), rosbags=st.booleans())
def test_any_image_header_decodes_consistently_or_raises_message_error(enc: str, h: int, w: int, step: int, n: int,
                                                                       big: bool, rosbags: bool) -> None:
    data = np.arange(n, dtype=np.uint8)
    if rosbags:
        msg: Any = ROS2._t("sensor_msgs/msg/Image")(header=ROS2.header(0, "c"), height=h, width=w, encoding=enc,
                                                    is_bigendian=int(big), step=step, data=data)
    else:
        msg = Image(height=h, width=w, encoding=enc, is_bigendian=int(big), step=step, data=data.tobytes())
    for decode in (image_to_numpy, decode_rgb, decode_depth):
        try:
            out = decode(msg)
        except MessageError:
            continue
        assert out.shape[:2] == (h, w) and n == step * h and enc in IMAGE_ENCODINGS


def _info(flavour: str, **changes: Any) -> Any:
    cam = PinholeCamera(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.2, 0.001, 0.002, 0.05))
    if flavour == "rclpy":
        from memgs_ros.ros.images import camera_to_camera_info

        msg = camera_to_camera_info(cam, 0, "c")
    else:
        mf = ROS1 if flavour == "rosbags-ros1" else ROS2
        msg = mf.camera_info(mf.header(0, "c"), cam)
    for key, value in changes.items():
        if flavour == "rosbags-ros1" and key in ("k", "d"):
            key = key.upper()
        if flavour != "rclpy" and key in ("k", "d", "K", "D"):
            value = np.asarray(value, np.float64)
        setattr(msg, key, value)
    return msg


_K = [50.0, 0.0, 31.5, 0.0, 51.0, 23.5, 0.0, 0.0, 1.0]


@pytest.mark.parametrize("flavour", list(FLAVOURS))
@pytest.mark.parametrize("changes,fragment", [
    ({"k": [float("nan"), *_K[1:]]}, "invalid focal lengths fx=nan"),
    ({"k": [*_K[:4], float("inf"), *_K[5:]]}, "invalid focal lengths fx=50.0 fy=inf"),
    ({"k": [-1.0, *_K[1:]]}, "invalid focal lengths fx=-1.0"),
    ({"k": [*_K[:2], float("nan"), *_K[3:]]}, "non-finite principal point cx=nan"),
    ({"k": _K[:6]}, "K needs 9 values, got 6"),
    ({"d": [0.1, float("nan"), 0.0, 0.0, 0.0]}, "non-finite distortion coefficients"),
    ({"d": [0.1] * 4}, "plumb_bob distortion needs 5 coefficients in D, got 4"),
    ({"distortion_model": "rational_polynomial"}, "rational_polynomial distortion needs 8 coefficients in D, got 5"),
    ({"distortion_model": "equidistant", "d": [0.1] * 4}, "'equidistant' with 4 coefficients is not supported"),
    ({"width": 0}, "not a valid camera: camera size must be positive"),
    ({"height": 0}, "not a valid camera: camera size must be positive"),
    ({"binning_x": 2}, "binning 2x0"),
])
def test_malformed_camera_info_raises_message_error(flavour: str, changes: dict[str, Any], fragment: str) -> None:
    with pytest.raises(MessageError, match=fragment):
        decode_camera_info(_info(flavour, **changes))


def test_camera_info_missing_fields_and_empty_distortion() -> None:
    class Bare:  # a CameraInfo-like object without K
        distortion_model = ""
        d: list[float] = []

    with pytest.raises(MessageError, match="Bare has no field k / K"):
        decode_camera_info(Bare())
    # empty D is no distortion, whatever the model says
    for model in ("", "none", "plumb_bob", "rational_polynomial"):
        msg = CameraInfo(k=_K, width=64, height=48, distortion_model=model)
        assert decode_camera_info(msg) == PinholeCamera(64, 48, 50.0, 51.0, 31.5, 23.5)


def test_metres_to_depth_units_rounds_to_nearest_and_marks_the_unrepresentable_invalid() -> None:
    from memgs_ros.io.image_decoding import metres_to_depth_units

    d = np.array([[0.0, -1.0, np.nan, np.inf, 0.2, 0.25, 0.75, 1.25, 617.0, 32767.5, 32767.75, 40000.0]], np.float32)
    units = metres_to_depth_units(d, 2.0)
    assert units.dtype == np.uint16 and units.shape == d.shape
    # Invalid stays 0; ties round to even (0.5 -> 0, 1.5 -> 2); beyond 65535 units is invalid, not clamped.
    assert units[0].tolist() == [0, 0, 0, 0, 0, 0, 2, 2, 1234, 65535, 0, 0]
