"""Write frames to ROS 2 bags (MCAP or sqlite3), in TUM's or realsense-ros's layout
(``write_realsense_bag``, raw or compressed), and to ROS 1 bags in the official TUM layout.

ROS 2 layout (TUM topic names, Jazzy types):

| topic | type | content |
| --- | --- | --- |
| ``/camera/rgb/image_color`` | sensor_msgs/Image | rgb8 |
| ``/camera/depth/image`` | sensor_msgs/Image | 32FC1 metres, NaN = invalid |
| ``/camera/rgb/camera_info`` | sensor_msgs/CameraInfo | plumb_bob (or rational_polynomial) + distortion |
| ``/camera/depth/camera_info`` | sensor_msgs/CameraInfo | plumb_bob (or rational_polynomial) + distortion |
| ``/tf`` | tf2_msgs/TFMessage | ``world`` -> camera optical frame (ground truth) |
| ``/groundtruth/pose`` | geometry_msgs/PoseStamped | camera in ``world`` (ground truth) |

Every message's bag time is its header stamp. Output is atomic: written under a temporary
name beside ``out_path`` and renamed into place. An ``out_path`` ending in ``.mcap`` or
``.db3`` is a single storage file (rosbags and ``ros2 bag`` read those without
``metadata.yaml``); anything else is a bag directory.

:class:`~memgs_ros.io.bag_stream.BagStream` (serialised messages one at a time, atomic) is the
writer underneath the ROS 2 variant; the recorder node streams a run's outputs through it too.

The ROS 1 variant reproduces TUM's own bags: ``tf/tfMessage`` with ``/world -> /kinect``
(the mocap body) plus the static ``/kinect -> /openni_camera -> /openni_rgb_frame ->
/openni_rgb_optical_frame`` chain republished with every frame, frame ids with leading
slashes, bz2-compressed chunks.
"""
from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import invert_pose, pose_from_tq, pose_to_tq
from memgs_ros.core.geometry.view import metres_to_units
from memgs_ros.errors import DataError
from memgs_ros.io.bag_stream import BagStream, _size, _tmp_sibling, ros2_typestore

RGB_TOPIC = "/camera/rgb/image_color"
DEPTH_TOPIC = "/camera/depth/image"
RGB_INFO_TOPIC = "/camera/rgb/camera_info"
DEPTH_INFO_TOPIC = "/camera/depth/camera_info"
TF_TOPIC = "/tf"
POSE_TOPIC = "/groundtruth/pose"
WORLD_FRAME = "world"
CAMERA_FRAME = "camera_rgb_optical_frame"

# ROS 1 TUM frames and the static chain below the mocap body (kinect). The rotations are
# what make composition worth testing: the optical frame is z forward, x right, y down.
ROS1_WORLD = "/world"
ROS1_KINECT = "/kinect"
ROS1_CHAIN: tuple[tuple[str, str, tuple[float, float, float], tuple[float, float, float, float]], ...] = (
    ("/kinect", "/openni_camera", (0.0, -0.02, 0.05), (0.0, 0.0, 0.0, 1.0)),
    ("/openni_camera", "/openni_rgb_frame", (0.0, -0.0125, 0.0), (0.0, 0.0, 0.0, 1.0)),
    ("/openni_rgb_frame", "/openni_rgb_optical_frame", (0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5)),
)
ROS1_OPTICAL = "/openni_rgb_optical_frame"
ROS1_DEPTH_OPTICAL = "/openni_depth_optical_frame"

TF_MESSAGE_ROS1 = "tf/msg/tfMessage"
_TF_MESSAGE_ROS1_DEF = "geometry_msgs/TransformStamped[] transforms\n"


def ros1_typestore() -> Any:
    """ROS 1 Noetic store with ``tf/msg/tfMessage`` registered (it is not in rosbags' store)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    if TF_MESSAGE_ROS1 not in ts.types:
        ts.register(get_types_from_msg(_TF_MESSAGE_ROS1_DEF, TF_MESSAGE_ROS1))
    return ts


def chain_T_kinect_optical() -> np.ndarray:
    """Composed static chain /kinect -> /openni_rgb_optical_frame, [4, 4]."""
    T = np.eye(4)
    for _, _, t, q in ROS1_CHAIN:
        T = T @ pose_from_tq(np.array(t), np.array(q))
    return T


@dataclass(frozen=True)
class MessageFactory:
    """Builds rosbags message objects for one type store (ROS 1 and ROS 2 differ in field names)."""

    ts: Any
    ros1: bool

    def _t(self, name: str) -> Any:
        return self.ts.types[name]

    def header(self, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        stamp = self._t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)
        if self.ros1:
            return self._t("std_msgs/msg/Header")(seq=seq, stamp=stamp, frame_id=frame_id)
        return self._t("std_msgs/msg/Header")(stamp=stamp, frame_id=frame_id)

    def image(self, header: Any, data: np.ndarray, encoding: str) -> Any:
        """data: [H, W, 3] uint8 (rgb8/bgr8), [H, W] uint8/uint16/float32; little endian, no padding."""
        h, w = data.shape[:2]
        raw = np.ascontiguousarray(data)
        step = raw.strides[0]
        buf = raw.view(np.uint8).reshape(-1)
        return self._t("sensor_msgs/msg/Image")(header=header, height=h, width=w, encoding=encoding,
                                                is_bigendian=0, step=step, data=buf)

    def compressed_image(self, header: Any, fmt: str, data: np.ndarray) -> Any:
        return self._t(COMPRESSED_TYPE)(header=header, format=fmt, data=np.ascontiguousarray(data, np.uint8))

    def camera_info(self, header: Any, camera: PinholeCamera) -> Any:
        K = camera.K.reshape(-1)
        R = np.eye(3).reshape(-1)
        P = np.zeros(12)
        P[[0, 2, 5, 6, 10]] = (camera.fx, camera.cx, camera.fy, camera.cy, 1.0)
        roi = self._t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        D = camera.dist_coeffs.astype(np.float64)
        fields = {"D": D, "K": K, "R": R, "P": P} if self.ros1 else {"d": D, "k": K, "r": R, "p": P}
        return self._t("sensor_msgs/msg/CameraInfo")(
            header=header, height=camera.height, width=camera.width, distortion_model=camera.distortion_model,
            binning_x=0, binning_y=0, roi=roi, **fields)

    def transform_stamped(self, header: Any, child: str, T: np.ndarray) -> Any:
        t, q = pose_to_tq(T)
        tr = self._t("geometry_msgs/msg/Transform")(
            translation=self._t("geometry_msgs/msg/Vector3")(x=t[0], y=t[1], z=t[2]),
            rotation=self._t("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3]))
        return self._t("geometry_msgs/msg/TransformStamped")(header=header, child_frame_id=child, transform=tr)

    def tf_message(self, transforms: list[Any]) -> Any:
        return self._t(TF_MESSAGE_ROS1 if self.ros1 else "tf2_msgs/msg/TFMessage")(transforms=transforms)

    def pose_stamped(self, header: Any, T: np.ndarray) -> Any:
        t, q = pose_to_tq(T)
        pose = self._t("geometry_msgs/msg/Pose")(
            position=self._t("geometry_msgs/msg/Point")(x=t[0], y=t[1], z=t[2]),
            orientation=self._t("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3]))
        return self._t("geometry_msgs/msg/PoseStamped")(header=header, pose=pose)

    def serialize(self, msg: Any, msgtype: str) -> bytes:
        if self.ros1:
            return bytes(self.ts.serialize_ros1(msg, msgtype))
        return bytes(self.ts.serialize_cdr(msg, msgtype))


def depth_to_32fc1(depth_m: np.ndarray) -> np.ndarray:
    """[H, W] float32 metres with 0 or NaN invalid -> [H, W] float32 with NaN invalid (TUM bag convention)."""
    d = depth_m.astype(np.float32, copy=True)
    d[~(np.isfinite(d) & (d > 0))] = np.nan
    return d


@dataclass(frozen=True)
class BagWriteResult:
    """What a writer produced."""

    path: Path
    frames: int
    bytes: int


def _topic_writer(bag: BagStream, mf: MessageFactory) -> Callable[[str, str, int, Any], None]:
    """``put(topic, msgtype, stamp_ns, msg)`` into a ROS 2 bag: the topic added at its first message."""
    topics: set[str] = set()

    def put(topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        if topic not in topics:
            bag.add_topic(topic, msgtype)
            topics.add(topic)
        bag.write(topic, stamp_ns, mf.serialize(msg, msgtype))

    return put


def write_bag(frames: Iterable[Frame], out_path: str | os.PathLike[str], storage: str | None = None,
              camera_frame_id: str = CAMERA_FRAME, world_frame_id: str = WORLD_FRAME,
              on_frame: Callable[[Frame], None] | None = None) -> BagWriteResult:
    """Write frames to a ROS 2 bag (module docstring for the layout).

    storage: "mcap" or "sqlite3"; None = from the suffix of ``out_path`` (.db3 -> sqlite3),
    else mcap. ``on_frame`` is called after each frame is written (progress bars).
    Returns the path, frame count and size in bytes.
    """
    def write(put: Callable[..., None], mf: MessageFactory, f: Frame, s: int) -> None:
        put(RGB_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", s, mf.camera_info(mf.header(s, camera_frame_id), f.camera))
        put(RGB_TOPIC, "sensor_msgs/msg/Image", s, mf.image(mf.header(s, camera_frame_id), f.rgb, "rgb8"))
        if (depth_m := f.depth_metres()) is not None:
            put(DEPTH_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", s,
                mf.camera_info(mf.header(s, camera_frame_id), f.camera))
            put(DEPTH_TOPIC, "sensor_msgs/msg/Image", s,
                mf.image(mf.header(s, camera_frame_id), depth_to_32fc1(depth_m), "32FC1"))
        if f.T_wc_gt is not None:
            tf = mf.transform_stamped(mf.header(s, world_frame_id), camera_frame_id, f.T_wc_gt)
            put(TF_TOPIC, "tf2_msgs/msg/TFMessage", s, mf.tf_message([tf]))
            put(POSE_TOPIC, "geometry_msgs/msg/PoseStamped", s,
                mf.pose_stamped(mf.header(s, world_frame_id), f.T_wc_gt))

    return _write_frames(Path(out_path), storage, frames, write, on_frame)


def _write_frames(out: Path, storage: str | None, frames: Iterable[Frame],
                  write: Callable[[Callable[..., None], MessageFactory, Frame, int], None],
                  on_frame: Callable[[Frame], None] | None) -> BagWriteResult:
    """A ROS 2 bag of ``frames``, each written by ``write(put, factory, frame, stamp_ns)``;
    ``on_frame`` after each; DataError when there were none."""
    n = 0
    with BagStream(out, storage) as bag:
        mf = MessageFactory(bag.typestore, ros1=False)
        put = _topic_writer(bag, mf)
        for f in frames:
            write(put, mf, f, int(f.stamp_ns))
            n += 1
            if on_frame is not None:
                on_frame(f)
        if n == 0:
            raise DataError(f"{out}: no frames to write")
    return BagWriteResult(out, n, _size(out))


# realsense-ros 4.x's layout (``ros2 launch realsense2_camera rs_launch.py align_depth.enable:=true``,
# camera_namespace and camera_name both "camera"), as ``ros2 bag record`` stores it.
RS_PREFIX = "/camera/camera"
RS_COLOR_TOPIC = f"{RS_PREFIX}/color/image_raw"
RS_COLOR_INFO_TOPIC = f"{RS_PREFIX}/color/camera_info"
RS_ALIGNED_DEPTH_TOPIC = f"{RS_PREFIX}/aligned_depth_to_color/image_raw"
RS_ALIGNED_DEPTH_INFO_TOPIC = f"{RS_PREFIX}/aligned_depth_to_color/camera_info"
RS_DEPTH_TOPIC = f"{RS_PREFIX}/depth/image_rect_raw"  # the depth camera's own view, not registered to colour
RS_DEPTH_INFO_TOPIC = f"{RS_PREFIX}/depth/camera_info"
RS_COLOR_FRAME = "camera_color_optical_frame"
RS_DEPTH_FRAME = "camera_depth_optical_frame"
RS_DEPTH_SCALE = 1000.0  # 16UC1 millimetres
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"


def compress_rgb(rgb: np.ndarray, quality: int = 95) -> tuple[str, np.ndarray]:
    """[H, W, 3] uint8 RGB -> (format, JPEG bytes [N] uint8) as image_transport's ``compressed`` writes rgb8."""
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise DataError("JPEG encoding failed")
    return "rgb8; jpeg compressed bgr8", buf.reshape(-1)


def compress_depth_units(depth_units: np.ndarray) -> tuple[str, np.ndarray]:
    """[H, W] uint16 depth units -> (format, bytes) as image_transport's ``compressedDepth`` writes 16UC1:
    a 12-byte header (int32 format 1 = PNG, of 0 inverse depth, 1 PNG, 2 RVL; float32 depthParam[2],
    unused for 16UC1), then the PNG."""
    import cv2

    ok, png = cv2.imencode(".png", np.ascontiguousarray(depth_units, dtype=np.uint16))
    if not ok:
        raise DataError("PNG encoding failed")
    header = np.array([1], "<i4").tobytes() + np.zeros(2, "<f4").tobytes()
    return "16UC1; compressedDepth png", np.concatenate([np.frombuffer(header, np.uint8), png.reshape(-1)])


def write_realsense_bag(frames: Iterable[Frame], out_path: str | os.PathLike[str], compressed: bool = False,
                        storage: str | None = None, world_frame_id: str = WORLD_FRAME, jpeg_quality: int = 95,
                        on_frame: Callable[[Frame], None] | None = None) -> BagWriteResult:
    """Write frames as a ROS 2 bag in realsense-ros 4.x's layout (``RS_*`` topics): colour rgb8 and
    depth aligned to it (16UC1 millimetres) with their camera_info, and the depth camera's own
    stream beside them (here the same pixels; a reader must prefer the aligned one). ``compressed``:
    colour as image_transport's ``compressed`` (JPEG, ``jpeg_quality``) and depth as its
    ``compressedDepth`` (PNG) on ``<topic>/compressed`` and ``<topic>/compressedDepth``, as a bag
    recorded over a radio link holds them. Ground truth, where frames carry it, goes on
    ``/groundtruth/pose`` (PoseStamped, a motion-capture recording beside the camera's).
    """
    def write(put: Callable[..., None], mf: MessageFactory, f: Frame, s: int) -> None:
        def image(topic: str, header: Any, data: np.ndarray, encoding: str) -> None:
            if not compressed:
                put(topic, "sensor_msgs/msg/Image", s, mf.image(header, data, encoding))
                return
            fmt, buf = compress_rgb(data, jpeg_quality) if encoding == "rgb8" else compress_depth_units(data)
            suffix = "compressed" if encoding == "rgb8" else "compressedDepth"
            put(f"{topic}/{suffix}", COMPRESSED_TYPE, s, mf.compressed_image(header, fmt, buf))

        put(RS_COLOR_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", s,
            mf.camera_info(mf.header(s, RS_COLOR_FRAME), f.camera))
        image(RS_COLOR_TOPIC, mf.header(s, RS_COLOR_FRAME), f.rgb, "rgb8")
        if (depth_m := f.depth_metres()) is not None:
            units = metres_to_units(depth_m, RS_DEPTH_SCALE)
            for topic, info, frame in ((RS_ALIGNED_DEPTH_TOPIC, RS_ALIGNED_DEPTH_INFO_TOPIC, RS_COLOR_FRAME),
                                       (RS_DEPTH_TOPIC, RS_DEPTH_INFO_TOPIC, RS_DEPTH_FRAME)):
                put(info, "sensor_msgs/msg/CameraInfo", s, mf.camera_info(mf.header(s, frame), f.camera))
                image(topic, mf.header(s, frame), units, "16UC1")
        if f.T_wc_gt is not None:
            put(POSE_TOPIC, "geometry_msgs/msg/PoseStamped", s,
                mf.pose_stamped(mf.header(s, world_frame_id), f.T_wc_gt))

    return _write_frames(Path(out_path), storage, frames, write, on_frame)


def write_ros1_tum_bag(frames: Iterable[Frame], out_path: str | os.PathLike[str], compress: bool = True,
                       on_frame: Callable[[Frame], None] | None = None) -> BagWriteResult:
    """Write frames as a ROS 1 bag in TUM's layout (see the module docstring).

    Ground truth goes out as /world -> /kinect = T_wc_gt composed with the inverse of the
    static chain, so composing the chain back gives T_wc_gt for /openni_rgb_optical_frame.
    Chunks are bz2-compressed unless ``compress`` is False.
    """
    from rosbags.rosbag1 import Writer

    out = Path(out_path)
    if out.exists():
        raise DataError(f"{out}: already exists; refusing to overwrite")
    ts = ros1_typestore()
    mf = MessageFactory(ts, ros1=True)
    T_optical_kinect = invert_pose(chain_T_kinect_optical())
    tmp_root = _tmp_sibling(out)
    tmp_bag = tmp_root / out.name
    n = 0
    try:
        writer = Writer(tmp_bag)
        if compress:
            writer.set_compression(Writer.CompressionFormat.BZ2)
        with writer:
            conns: dict[str, Any] = {}

            def put(topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                writer.write(conns[topic], stamp_ns, mf.serialize(msg, msgtype))

            for seq, f in enumerate(frames):
                s = int(f.stamp_ns)
                if f.T_wc_gt is not None:
                    T_world_kinect = f.T_wc_gt @ T_optical_kinect
                    tfs = [mf.transform_stamped(mf.header(s, ROS1_WORLD, seq), ROS1_KINECT, T_world_kinect)]
                    tfs += [mf.transform_stamped(mf.header(s, parent, seq), child,
                                                 pose_from_tq(np.array(t), np.array(q)))
                            for parent, child, t, q in ROS1_CHAIN]
                    put(TF_TOPIC, TF_MESSAGE_ROS1, s, mf.tf_message(tfs))
                put(RGB_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", s,
                    mf.camera_info(mf.header(s, ROS1_OPTICAL, seq), f.camera))
                put(RGB_TOPIC, "sensor_msgs/msg/Image", s, mf.image(mf.header(s, ROS1_OPTICAL, seq), f.rgb, "rgb8"))
                if (depth_m := f.depth_metres()) is not None:
                    put(DEPTH_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", s,
                        mf.camera_info(mf.header(s, ROS1_DEPTH_OPTICAL, seq), f.camera))
                    put(DEPTH_TOPIC, "sensor_msgs/msg/Image", s,
                        mf.image(mf.header(s, ROS1_DEPTH_OPTICAL, seq), depth_to_32fc1(depth_m), "32FC1"))
                n += 1
                if on_frame is not None:
                    on_frame(f)
        if n == 0:
            raise DataError(f"{out}: no frames to write")
        os.replace(tmp_bag, out)
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    return BagWriteResult(out, n, _size(out))


__all__ = [
    "CAMERA_FRAME",
    "DEPTH_INFO_TOPIC",
    "DEPTH_TOPIC",
    "POSE_TOPIC",
    "RGB_INFO_TOPIC",
    "RGB_TOPIC",
    "ROS1_OPTICAL",
    "ROS1_WORLD",
    "TF_TOPIC",
    "WORLD_FRAME",
    "BagStream",
    "BagWriteResult",
    "MessageFactory",
    "chain_T_kinect_optical",
    "depth_to_32fc1",
    "ros1_typestore",
    "ros2_typestore",
    "write_bag",
    "write_ros1_tum_bag",
]
