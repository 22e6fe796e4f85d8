"""Message codecs: images, camera info, stamps, poses and PointCloud2 against hand-built messages."""
from __future__ import annotations

import array

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("rclpy")

from geometry_msgs.msg import Pose  # noqa: E402
from nav_msgs.msg import Path  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField  # noqa: E402

from memgs_ros.core.geometry.camera import TUM_FR1, TUM_FR3, PinholeCamera  # noqa: E402
from memgs_ros.core.geometry.poses import pose_from_tq, rotmat_to_quat_xyzw  # noqa: E402
from memgs_ros.errors import MessageError  # noqa: E402
from memgs_ros.io.image_decoding import decode_camera_info, decode_depth, decode_rgb, image_to_numpy  # noqa: E402
from memgs_ros.ros import codecs, images  # noqa: E402

ENC_DTYPES = {"rgb8": ("u1", 3), "bgr8": ("u1", 3), "rgba8": ("u1", 4), "bgra8": ("u1", 4), "mono8": ("u1", 1),
              "16UC1": ("u2", 1), "32FC1": ("f4", 1)}


def _random_image(enc: str, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    kind, c = ENC_DTYPES[enc]
    shape = (h, w) if c == 1 else (h, w, c)
    if kind == "f4":
        return rng.normal(size=shape).astype(np.float32)
    return rng.integers(0, np.iinfo(kind).max, size=shape, endpoint=True).astype(kind)


def _hand_image(arr: np.ndarray, enc: str, pad: int, big: bool) -> Image:
    """Build an Image byte by byte the way a foreign driver might: padded rows, any byte order."""
    h, w = arr.shape[:2]
    wire = arr.astype(arr.dtype.newbyteorder(">" if big else "<"))
    rows = wire.reshape(h, -1).view(np.uint8)
    padded = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    msg = Image(height=h, width=w, encoding=enc, is_bigendian=int(big), step=rows.shape[1] + pad)
    msg.data = padded.tobytes()
    return msg


# ----------------------------------------------------------------------------- images


@pytest.mark.parametrize("enc", list(ENC_DTYPES))
def test_image_round_trip_every_encoding(enc: str) -> None:
    arr = _random_image(enc, 5, 7, np.random.default_rng(1))
    msg = images.numpy_to_image(arr, enc, 1_500_000_123, "cam")
    assert msg.step == 7 * arr.dtype.itemsize * ENC_DTYPES[enc][1]
    assert msg.is_bigendian == 0 and isinstance(msg.data, array.array)
    assert codecs.stamp_to_ns(msg.header.stamp) == 1_500_000_123 and msg.header.frame_id == "cam"
    out = image_to_numpy(msg)
    assert out.dtype == arr.dtype and out.shape == arr.shape
    np.testing.assert_array_equal(out, arr)


@pytest.mark.parametrize("enc", list(ENC_DTYPES))
@pytest.mark.parametrize("big", [False, True])
def test_image_decode_padded_rows_and_byte_order(enc: str, big: bool) -> None:
    arr = _random_image(enc, 4, 3, np.random.default_rng(2))
    out = image_to_numpy(_hand_image(arr, enc, pad=5, big=big))
    assert out.dtype == arr.dtype.newbyteorder("=")
    np.testing.assert_array_equal(out, arr)


@settings(max_examples=40, deadline=None)
@given(
    enc=st.sampled_from(list(ENC_DTYPES)),
    h=st.integers(1, 9),
    w=st.integers(1, 9),
    pad=st.integers(0, 7),
    big=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_image_decode_property(enc: str, h: int, w: int, pad: int, big: bool, seed: int) -> None:
    arr = _random_image(enc, h, w, np.random.default_rng(seed))
    np.testing.assert_array_equal(image_to_numpy(_hand_image(arr, enc, pad, big)), arr)


def test_image_accepts_bytes_and_list_data() -> None:
    arr = _random_image("rgb8", 2, 3, np.random.default_rng(3))
    msg = images.numpy_to_image(arr, "rgb8", 0, "c")
    for data in (bytes(msg.data), list(msg.data)):
        msg2 = Image(height=2, width=3, encoding="rgb8", step=9)
        msg2.data = data
        np.testing.assert_array_equal(image_to_numpy(msg2), arr)


def test_decode_rgb_converts_channel_orders() -> None:
    rgb = _random_image("rgb8", 4, 5, np.random.default_rng(4))
    rgba = np.concatenate([rgb, np.full((4, 5, 1), 7, np.uint8)], axis=2)
    cases = {
        "rgb8": rgb,
        "bgr8": rgb[:, :, ::-1],
        "rgba8": rgba,
        "bgra8": np.concatenate([rgb[:, :, ::-1], rgba[:, :, 3:]], axis=2),
    }
    for enc, arr in cases.items():
        out = decode_rgb(images.numpy_to_image(np.ascontiguousarray(arr), enc, 0, "c"))
        assert out.dtype == np.uint8 and out.shape == (4, 5, 3), enc
        np.testing.assert_array_equal(out, rgb, err_msg=enc)
    gray = rgb[:, :, 0].copy()
    out = decode_rgb(images.numpy_to_image(gray, "mono8", 0, "c"))
    np.testing.assert_array_equal(out, np.stack([gray] * 3, axis=2))


@pytest.mark.parametrize("enc,order", [("bgr8", [2, 1, 0]), ("rgba8", [0, 1, 2]), ("bgra8", [2, 1, 0])])
def test_rgb_from_padded_image(enc: str, order: list[int]) -> None:
    arr = _random_image(enc, 3, 5, np.random.default_rng(6))
    np.testing.assert_array_equal(decode_rgb(_hand_image(arr, enc, pad=3, big=False)), arr[:, :, order])


def test_depth_16uc1_scaled_and_zero_is_nan() -> None:
    mm = np.array([[0, 1000, 1500], [65535, 250, 0]], np.uint16)
    d = decode_depth(images.numpy_to_image(mm, "16UC1", 0, "c"), depth_scale=1000.0)
    assert d.dtype == np.float32
    np.testing.assert_allclose(d[0, 1:], [1.0, 1.5])
    np.testing.assert_allclose(d[1, :2], [65.535, 0.25], rtol=1e-6)
    assert np.isnan(d[0, 0]) and np.isnan(d[1, 2])
    d5000 = decode_depth(images.numpy_to_image(mm, "16UC1", 0, "c"), depth_scale=5000.0)
    np.testing.assert_allclose(d5000[0, 1], 0.2)


def test_depth_32fc1_invalid_values_become_nan_without_touching_the_message() -> None:
    m = np.array([[1.25, np.nan, np.inf], [-1.0, 0.0, 3.0]], np.float32)
    msg = images.numpy_to_image(m, "32FC1", 0, "c")
    d = decode_depth(msg)
    np.testing.assert_array_equal(d[[0, 1], [0, 2]], [1.25, 3.0])
    assert np.isnan(d[0, 1:]).all() and np.isnan(d[1, :2]).all()
    assert image_to_numpy(msg)[1, 0] == -1.0  # the message buffer is unchanged


@pytest.mark.parametrize("enc,scale", [("32FC1", 1.0), ("16UC1", 1000.0), ("16UC1", 5000.0)])
def test_depth_round_trip(enc: str, scale: float) -> None:
    rng = np.random.default_rng(5)
    d = rng.uniform(0.3, 6.0, size=(6, 8)).astype(np.float32)
    d[0, 0], d[1, 1], d[2, 2] = np.nan, 0.0, -2.0
    out = decode_depth(images.depth_to_image(d, enc, 0, "c", depth_scale=scale), depth_scale=scale)
    valid = np.isfinite(d) & (d > 0)
    np.testing.assert_array_equal(np.isnan(out), ~valid)
    np.testing.assert_allclose(out[valid], d[valid], atol=0.5 / scale + 1e-6)


def test_depth_to_16uc1_marks_out_of_range_invalid() -> None:
    img = images.depth_to_image(np.array([[70.0, 1.0]], np.float32), "16UC1", 0, "c", depth_scale=1000.0)
    np.testing.assert_array_equal(image_to_numpy(img), [[0, 1000]])


def _image(enc: str = "rgb8", h: int = 2, w: int = 3, step: int = 9, n: int = 18) -> Image:
    msg = Image(height=h, width=w, encoding=enc, step=step)
    msg.data = bytes(n)
    return msg


@pytest.mark.parametrize(
    "msg,fragment",
    [
        (_image(enc="yuv422"), "unsupported image encoding 'yuv422'"),
        (_image(step=8, n=16), "step 8 is less than width*bytes_per_pixel = 9"),
        (_image(n=17), "17 bytes, expected step*height = 9*2 = 18"),
        (_image(h=0, n=0), "no pixels"),
        (_image(enc="32FC1", step=12, n=23), "23 bytes, expected step*height = 12*2 = 24"),
    ],
)
def test_image_malformed_raises_message_error(msg: Image, fragment: str) -> None:
    with pytest.raises(MessageError, match=fragment.replace("*", r"\*")):
        image_to_numpy(msg)


def test_wrong_kind_of_image_and_wrong_arrays_are_refused() -> None:
    with pytest.raises(MessageError, match="'32FC1' is not a colour encoding"):
        decode_rgb(_image(enc="32FC1", step=12, n=24))
    with pytest.raises(MessageError, match="'rgb8' is not a depth encoding"):
        decode_depth(_image())
    with pytest.raises(MessageError, match="depth_scale"):
        decode_depth(_image(enc="16UC1", step=6, n=12), depth_scale=0.0)
    with pytest.raises(MessageError, match=r"rgb8 needs dtype uint8, got float32"):
        images.numpy_to_image(np.zeros((2, 2, 3), np.float32), "rgb8", 0, "c")
    with pytest.raises(MessageError, match=r"32FC1 needs an array \[H, W\], got shape \(2, 2, 3\)"):
        images.numpy_to_image(np.zeros((2, 2, 3), np.float32), "32FC1", 0, "c")
    with pytest.raises(MessageError, match="unsupported image encoding 'rgb16'"):
        images.numpy_to_image(np.zeros((2, 2, 3), np.uint16), "rgb16", 0, "c")
    with pytest.raises(MessageError, match="depth encoding must be 32FC1 or 16UC1"):
        images.depth_to_image(np.zeros((2, 2), np.float32), "mono8", 0, "c")


def test_numpy_to_image_byte_swaps_big_endian_input() -> None:
    arr = np.arange(6, dtype=">u2").reshape(2, 3) * 300
    msg = images.numpy_to_image(arr, "16UC1", 0, "c")
    assert msg.is_bigendian == 0
    np.testing.assert_array_equal(image_to_numpy(msg), arr.astype(np.uint16))


# ----------------------------------------------------------------------------- stamps, camera info


@pytest.mark.parametrize("ns", [0, 1, 999_999_999, 1_000_000_000, 1_305_031_229_528_784_000, (2**31 - 1) * 10**9])
def test_stamp_round_trip(ns: int) -> None:
    stamp = codecs.ns_to_stamp(ns)
    assert 0 <= stamp.nanosec < 10**9
    assert codecs.stamp_to_ns(stamp) == ns


@pytest.mark.parametrize("ns", [-1, 2**31 * 10**9])
def test_stamp_out_of_range(ns: int) -> None:
    with pytest.raises(MessageError, match=f"stamp {ns} ns does not fit"):
        codecs.ns_to_stamp(ns)


@pytest.mark.parametrize("cam", [TUM_FR1, TUM_FR3, PinholeCamera(64, 48, 50.0, 51.0, 31.5, 23.5)])
def test_camera_info_round_trip(cam: PinholeCamera) -> None:
    msg = images.camera_to_camera_info(cam, 42, "cam")
    assert msg.distortion_model == "plumb_bob" and len(msg.d) == 5
    assert list(msg.p) == [cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0]
    assert decode_camera_info(msg) == cam


def test_camera_info_rational_polynomial_round_trips_in_full() -> None:
    cam = PinholeCamera(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.2, 0.001, 0.002, 0.05, 0.01, -0.02, 0.003))
    msg = images.camera_to_camera_info(cam, 0, "c")
    assert msg.distortion_model == "rational_polynomial" and list(msg.d) == list(cam.dist)
    assert decode_camera_info(msg) == cam
    # k4..k6 all zero is the plumb_bob camera: both spellings of one calibration compare equal
    msg.d = [*TUM_FR1.dist, 0.0, 0.0, 0.0]
    assert decode_camera_info(msg).dist == TUM_FR1.dist


def test_camera_info_without_distortion_model() -> None:
    msg = images.camera_to_camera_info(TUM_FR3, 0, "c")
    msg.distortion_model, msg.d = "", []
    assert decode_camera_info(msg) == TUM_FR3


def _info(**changes: object) -> CameraInfo:
    msg = images.camera_to_camera_info(TUM_FR1, 0, "c")
    for k, v in changes.items():
        setattr(msg, k, v)
    return msg


@pytest.mark.parametrize(
    "msg,fragment",
    [
        (_info(distortion_model="equidistant", d=[0.0] * 4), "'equidistant' with 4 coefficients is not supported"),
        (_info(distortion_model="rational_polynomial", d=[0.0] * 5), "rational_polynomial distortion needs 8"),
        (_info(d=[0.1, 0.2, 0.0, 0.0]), "plumb_bob distortion needs 5 coefficients in D, got 4"),
        (_info(k=[0.0, 0, 320, 0, 500, 240, 0, 0, 1]), "invalid focal lengths fx=0.0"),
        (_info(k=[float("nan"), 0, 320, 0, 500, 240, 0, 0, 1]), "invalid focal lengths fx=nan"),
        (_info(width=0), "not a valid camera: camera size must be positive"),
        (_info(binning_x=2), "binning 2x0"),
    ],
)
def test_camera_info_malformed(msg: CameraInfo, fragment: str) -> None:
    with pytest.raises(MessageError, match=fragment):
        decode_camera_info(msg)


# ----------------------------------------------------------------------------- poses


def _random_pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    return pose_from_tq(rng.normal(size=3), q / np.linalg.norm(q))


def test_pose_round_trips() -> None:
    T = _random_pose(7)
    ps = codecs.matrix_to_pose_stamped(T, 5_000_000_001, "world")
    assert ps.header.frame_id == "world" and codecs.stamp_to_ns(ps.header.stamp) == 5_000_000_001
    np.testing.assert_allclose(codecs.pose_to_matrix(ps.pose), T, atol=1e-12)
    odom = codecs.matrix_to_odometry(T, 3, "odom", "camera")
    assert odom.child_frame_id == "camera" and odom.header.frame_id == "odom"
    np.testing.assert_allclose(codecs.pose_to_matrix(odom.pose.pose), T, atol=1e-12)
    shared = codecs.pose_to_odometry(ps, "camera")  # the node's way: one conversion for both
    assert shared.header == ps.header and shared.pose.pose == ps.pose and shared.child_frame_id == "camera"
    assert list(shared.pose.covariance) == [0.0] * 36 and shared.twist.twist.linear.x == 0.0
    # A publisher's Odometry filled again for the next pose (the tracker's per-frame messages).
    ps2 = codecs.matrix_to_pose_stamped(_random_pose(8), 6, "world")
    again = codecs.pose_to_odometry(ps2, "camera2", out=shared)
    assert again is shared and again.header == ps2.header and again.pose.pose == ps2.pose
    assert again.child_frame_id == "camera2" and codecs.stamp_to_ns(ps.header.stamp) == 5_000_000_001


def test_pose_messages_are_built_as_the_quaternion_reference_gives_them() -> None:
    """The encoder writes the entries it checked; the quaternion is ``rotmat_to_quat_xyzw``'s,
    bit for bit, whichever of Shepperd's four cases a rotation takes."""
    for seed in range(40):
        T = _random_pose(seed)
        pose = codecs.matrix_to_pose(T)
        want = rotmat_to_quat_xyzw(T[:3, :3])
        got = [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
        assert got == want.tolist() and [pose.position.x, pose.position.y, pose.position.z] == T[:3, 3].tolist()
    bad = np.eye(4)
    bad[2, 3] = np.nan
    with pytest.raises(MessageError, match="finite 4x4"):
        codecs.matrix_to_pose_stamped(bad, 1, "world")
    with pytest.raises(MessageError, match="does not fit"):
        codecs.matrix_to_pose_stamped(np.eye(4), -1, "world")


def test_pose_to_matrix_normalises_and_refuses_zero_quaternion() -> None:
    pose = Pose()
    pose.orientation.w = 2.0
    np.testing.assert_allclose(codecs.pose_to_matrix(pose), np.eye(4))
    pose.orientation.w = 0.0
    with pytest.raises(MessageError, match="zero quaternion"):
        codecs.pose_to_matrix(pose)
    with pytest.raises(MessageError, match=r"finite 4x4 matrix, got shape \(3, 4\)"):
        codecs.matrix_to_pose(np.eye(4)[:3])


def test_append_to_path_trims_and_stamps() -> None:
    path = Path()
    for i in range(5):
        codecs.append_to_path(path, codecs.matrix_to_pose_stamped(np.eye(4), i, "world"), max_len=3)
    assert [codecs.stamp_to_ns(p.header.stamp) for p in path.poses] == [2, 3, 4]
    assert codecs.stamp_to_ns(path.header.stamp) == 4 and path.header.frame_id == "world"


# ----------------------------------------------------------------------------- PointCloud2

CLOUD_DTYPES = [
    np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]),
    np.dtype([("x", "<f8"), ("rgb", "u1", (3,)), ("n", "<u2"), ("k", "<i4"), ("a", "i1"), ("b", "<i2")]),
    np.dtype([("id", "<u8"), ("op", "u1"), ("pos", "<f4", (3,)), ("seq", "<i8")]),
    np.dtype({"names": ["x", "w"], "formats": ["<f4", "<u4"], "offsets": [0, 12], "itemsize": 20}),  # padding
    np.dtype([("x", ">f4"), ("id", ">u8"), ("v", ">u2")]),  # big-endian input
]


def _random_cloud(dtype: np.dtype, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    arr = np.zeros(n, dtype)
    for name in dtype.names:
        base = dtype.fields[name][0].base
        shape = (n,) + dtype.fields[name][0].shape
        if base.kind == "f":
            arr[name] = rng.normal(size=shape)
        else:
            info = np.iinfo(base)
            arr[name] = rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=base.newbyteorder("="))
    return arr


@pytest.mark.parametrize("dtype", CLOUD_DTYPES, ids=lambda d: ",".join(d.names))
@pytest.mark.parametrize("n", [0, 1, 17])
def test_pointcloud2_round_trip(dtype: np.dtype, n: int) -> None:
    arr = _random_cloud(dtype, n, seed=n)
    msg = codecs.structured_to_pointcloud2(arr, 77, "map")
    assert msg.point_step == dtype.itemsize and msg.row_step == dtype.itemsize * n
    assert (msg.height, msg.width) == (1, n) and not msg.is_bigendian
    assert codecs.stamp_to_ns(msg.header.stamp) == 77
    out = codecs.pointcloud2_to_structured(msg)
    assert out.dtype.names == dtype.names and out.shape == (n,)
    for name in dtype.names:
        assert out.dtype.fields[name][0].base == dtype.fields[name][0].base.newbyteorder("="), name
        np.testing.assert_array_equal(out[name], arr[name], err_msg=name)


def test_pointcloud2_uint64_travels_as_lo_hi_pair() -> None:
    arr = np.array([(2**64 - 1, -(2**62)), (2**33 + 5, 7)], dtype=[("id", "<u8"), ("seq", "<i8")])
    msg = codecs.structured_to_pointcloud2(arr, 0, "map")
    fields = {f.name: (f.offset, f.datatype) for f in msg.fields}
    assert fields == {
        "id_lo": (0, PointField.UINT32), "id_hi": (4, PointField.UINT32),
        "seq_lo": (8, PointField.UINT32), "seq_hi": (12, PointField.INT32),
    }
    raw = np.frombuffer(msg.data, dtype="<u4").reshape(2, 4)
    assert raw[1, 0] == 5 and raw[1, 1] == 2  # low word first: any reader can rebuild the id
    out = codecs.pointcloud2_to_structured(msg, required=("id", "seq"))
    np.testing.assert_array_equal(out["id"], arr["id"])
    np.testing.assert_array_equal(out["seq"], arr["seq"])
    with pytest.raises(MessageError, match="clashes with existing field 'id_lo'"):
        codecs.structured_to_pointcloud2(np.zeros(1, [("id", "<u8"), ("id_lo", "<u4")]), 0, "m")


def test_pointcloud2_big_endian_lo_hi_pair_is_joined() -> None:
    """Big-endian writers put the high word first; the pair still comes back as one uint64."""
    raw = np.zeros(3, dtype=[("id", ">u8"), ("x", ">f4")])
    raw["id"], raw["x"] = [2**64 - 2, 5, 2**40 + 3], [1.0, 2.0, 3.0]
    fields = [PointField(name="id_hi", offset=0, datatype=PointField.UINT32, count=1),
              PointField(name="id_lo", offset=4, datatype=PointField.UINT32, count=1),
              PointField(name="x", offset=8, datatype=PointField.FLOAT32, count=1)]
    msg = PointCloud2(height=1, width=3, is_bigendian=True, point_step=12, row_step=36, fields=fields)
    msg.data = raw.tobytes()
    out = codecs.pointcloud2_to_structured(msg, required=("id", "x"))
    assert out.dtype.names == ("id", "x") and out.dtype["id"] == np.dtype(np.uint64)
    np.testing.assert_array_equal(out["id"], raw["id"])
    np.testing.assert_array_equal(out["x"], raw["x"])


def _hand_cloud(arr: np.ndarray, big: bool, row_pad: int, height: int) -> PointCloud2:
    """A foreign-made cloud: fields in reverse order, chosen byte order, padded rows."""
    dtype = arr.dtype
    wire = arr.astype(dtype.newbyteorder(">" if big else "<"))
    w = len(arr) // height
    rows = wire.view(np.uint8).reshape(height, w * dtype.itemsize)
    data = np.concatenate([rows, np.full((height, row_pad), 0xEE, np.uint8)], axis=1)
    codes = {np.dtype(k).newbyteorder("="): v for k, v in
             [("f4", 7), ("f8", 8), ("u1", 2), ("u2", 4), ("u4", 6), ("i4", 5), ("i2", 3), ("i1", 1)]}
    fields = []
    for name in reversed(dtype.names):
        ftype, off = dtype.fields[name][:2]
        count = int(np.prod(ftype.shape)) if ftype.shape else 1
        fields.append(PointField(name=name, offset=off, datatype=codes[ftype.base.newbyteorder("=")], count=count))
    msg = PointCloud2(height=height, width=w, fields=fields, is_bigendian=big, point_step=dtype.itemsize,
                      row_step=w * dtype.itemsize + row_pad)
    msg.data = data.tobytes()
    return msg


@settings(max_examples=40, deadline=None)
@given(
    names=st.lists(st.sampled_from(["a", "b", "c", "d", "e"]), min_size=1, max_size=4, unique=True),
    kinds=st.lists(st.sampled_from(["<f4", "<f8", "u1", "<u2", "<u4", "<i4", "<i2", "i1"]), min_size=4, max_size=4),
    counts=st.lists(st.integers(1, 3), min_size=4, max_size=4),
    pad=st.integers(0, 9),
    row_pad=st.integers(0, 6),
    height=st.sampled_from([1, 2, 3]),
    width=st.integers(0, 5),
    big=st.booleans(),
)
def test_pointcloud2_decode_property(names, kinds, counts, pad, row_pad, height, width, big) -> None:
    formats = [(k, (c,)) if c > 1 else k for k, c in zip(kinds, counts)][: len(names)]
    packed = np.dtype(list(zip(names, formats)))
    dtype = np.dtype({"names": names, "formats": formats,
                      "offsets": [packed.fields[n][1] for n in names], "itemsize": packed.itemsize + pad})
    arr = _random_cloud(dtype, height * width, seed=pad)
    out = codecs.pointcloud2_to_structured(_hand_cloud(arr, big, row_pad, height))
    assert out.shape == (height * width,)
    for name in names:
        np.testing.assert_array_equal(out[name], arr[name])


def test_pointcloud2_decode_is_zero_copy_for_native_clouds() -> None:
    arr = _random_cloud(CLOUD_DTYPES[0], 10, 0)
    msg = codecs.structured_to_pointcloud2(arr, 0, "m")
    out = codecs.pointcloud2_to_structured(msg)
    assert np.shares_memory(out, np.frombuffer(msg.data, np.uint8))


def _cloud(**changes: object) -> PointCloud2:
    msg = codecs.structured_to_pointcloud2(np.zeros(4, [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]), 0, "m")
    for k, v in changes.items():
        setattr(msg, k, v)
    return msg


@pytest.mark.parametrize(
    "msg,fragment",
    [
        (_cloud(data=bytes(47)), r"data has 47 bytes, expected row_step\*height = 48\*1 = 48"),
        (_cloud(row_step=40), r"row_step 40 is less than width\*point_step = 48"),
        (_cloud(point_step=8, row_step=32, data=bytes(32)), "field 'z' .offset 8, 4 bytes. does not fit point_step 8"),
        (_cloud(fields=[PointField(name="x", offset=0, datatype=9, count=1)]), "unknown datatype 9"),
        (_cloud(fields=[PointField(name="x", offset=0, datatype=7, count=0)]), "count 0"),
        (_cloud(fields=[]), "no fields"),
        (_cloud(fields=[PointField(name="x", offset=0, datatype=7, count=1)] * 2), "field 'x' twice"),
    ],
)
def test_pointcloud2_malformed(msg: PointCloud2, fragment: str) -> None:
    with pytest.raises(MessageError, match=fragment):
        codecs.pointcloud2_to_structured(msg)


def test_pointcloud2_required_fields_and_bad_inputs() -> None:
    with pytest.raises(MessageError, match=r"lacks required field\(s\) \['rgb'\]"):
        codecs.pointcloud2_to_structured(_cloud(), required=("x", "rgb"))
    with pytest.raises(MessageError, match="needs a structured array"):
        codecs.structured_to_pointcloud2(np.zeros((3, 3), np.float32), 0, "m")
    with pytest.raises(MessageError, match="field 'h' has dtype float16"):
        codecs.structured_to_pointcloud2(np.zeros(3, [("h", "f2")]), 0, "m")


def test_pointcloud2_organised_cloud_keeps_rows() -> None:
    arr = _random_cloud(CLOUD_DTYPES[0], 6, 3).reshape(2, 3)
    msg = codecs.structured_to_pointcloud2(arr, 0, "m")
    assert (msg.height, msg.width, msg.row_step) == (2, 3, 36)
    np.testing.assert_array_equal(codecs.pointcloud2_to_structured(msg), arr.reshape(-1))


def test_keyframe_depth_goes_on_in_rep118_units() -> None:
    """Millimetres and metres pass as they are; 16-bit depth of another scale (TUM: 5000 a metre)
    becomes 32FC1 metres with the value each unit stood for (0 -> NaN), stamp and frame kept."""
    units = np.array([[5000, 0], [12345, 65535]], np.uint16)
    tum = images.numpy_to_image(units, "16UC1", 7, "cam")
    out = images.rep118_depth(tum, 5000.0)
    assert out.encoding == "32FC1" and out.header.frame_id == "cam" and codecs.stamp_to_ns(out.header.stamp) == 7
    got = decode_depth(out)
    np.testing.assert_allclose(got[~np.isnan(got)], units[units > 0] / np.float32(5000.0), rtol=1e-7)
    assert np.isnan(got[0, 1])
    mm = images.numpy_to_image(units, "16UC1", 7, "cam")
    assert images.rep118_depth(mm, 1000.0) is mm
    metres = images.depth_to_image(np.ones((2, 2), np.float32), "32FC1", 7, "cam")
    assert images.rep118_depth(metres, 5000.0) is metres
