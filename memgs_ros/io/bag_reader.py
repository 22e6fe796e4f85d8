"""Read RGB-D frames and ground truth from bags: TUM's ROS 1 bags (bz2), ROS 2 MCAP and sqlite3.

Opening a bag first settles its topics: TUM's names when the bag has them, the ones given
(``BagTopics.parse``: ``memgs run --topics``), or else found by type and encoding
(``discover_topics``: a realsense-ros bag's colour, its aligned depth and camera_info; raw or
image_transport's ``compressed`` / ``compressedDepth``), said in the log, an ambiguous bag refused
with the candidates. Then one pass over its small messages and image headers finds the
camera (first CameraInfo on the colour info topic, unless a camera is given), pairs colour
and depth images by nearest header stamp (one-to-one within ``max_dt_s``) and collects
ground truth, either from a PoseStamped topic or by composing ``/tf`` (and ``/tf_static``)
edges from the world frame down to the camera optical frame. Iterating makes a second
pass that decodes only the paired images, so memory stays at a few frames.

Bad input never stops a read: a message that does not deserialise, an unsupported
encoding, a size mismatch or an unexpected type is counted in ``skipped`` (kind -> count),
logged once per kind, and skipped; topics nobody asked for (``/cortex_marker_array``,
``/imu``) are counted without being read. A bag that cannot be opened or read at all
(missing, truncated, corrupt) raises DataError naming the file.
"""
from __future__ import annotations

import logging
import os
from collections import defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar, cast

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import interpolate_poses, pose_from_tq
from memgs_ros.errors import ConfigError, DataError, MemgsError, MessageError
from memgs_ros.io.bag_writer import (
    DEPTH_INFO_TOPIC,
    DEPTH_TOPIC,
    POSE_TOPIC,
    RGB_INFO_TOPIC,
    RGB_TOPIC,
    TF_TOPIC,
    ros2_typestore,
)
from memgs_ros.io.image_decoding import (
    COLOR_ENCODINGS,
    DEFAULT_DEPTH_SCALE,
    DEPTH_ENCODINGS,
    check_image,
    compressed_is_depth,
    decode_camera_info,
    decode_color_message,
    decode_compressed_rgb,
    decode_depth_message,
    is_compressed,
)
from memgs_ros.io.skips import SkipLog
from memgs_ros.io.tum import associate

logger = logging.getLogger(__name__)

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
# Tried in this order when no camera frame is configured (frames compared without leading '/').
DEFAULT_CAMERA_FRAMES = ("openni_rgb_optical_frame", "camera_rgb_optical_frame")


@dataclass(frozen=True)
class BagTopics:
    """Topic and frame names. Defaults are TUM's (and what ``bag_writer`` writes).

    camera_frame: tf frame of the colour optical frame; None = the first of
    DEFAULT_CAMERA_FRAMES in the tf tree, else the colour images' header frame_id.
    world_frame: None = the root of the tf tree above the camera frame.
    Frame names match with or without ROS 1's leading slash.
    """

    rgb: str = RGB_TOPIC
    depth: str = DEPTH_TOPIC
    rgb_info: str = RGB_INFO_TOPIC
    depth_info: str = DEPTH_INFO_TOPIC
    tf: str = TF_TOPIC
    tf_static: str = "/tf_static"
    pose: str = POSE_TOPIC
    camera_frame: str | None = None
    world_frame: str | None = None

    # --topics keys -> fields
    KEYS: ClassVar[Mapping[str, str]] = MappingProxyType(
        {"color": "rgb", "depth": "depth", "camera_info": "rgb_info", "pose": "pose"})

    @classmethod
    def parse(cls, text: str) -> BagTopics:
        """``color=/a,depth=/b,camera_info=/c`` (any of them; ``pose=`` the ground truth) -> BagTopics;
        ConfigError naming the bad item. An empty text gives the defaults (found in the bag when absent)."""
        given: dict[str, str] = {}
        for item in (i.strip() for i in text.split(",")):
            if not item:
                continue
            key, eq, topic = (x.strip() for x in item.partition("="))
            if not eq or key not in cls.KEYS or not topic:
                raise ConfigError(f"--topics item {item!r}: expected KEY=/topic with KEY one of "
                                  f"{', '.join(cls.KEYS)}")
            given[cls.KEYS[key]] = topic if topic.startswith("/") else "/" + topic
        return cls(**given, explicit=tuple(given))  # type: ignore[arg-type]

    explicit: tuple[str, ...] = ()  # fields the user named: used as given, checked against the bag


def _transport_base(topic: str) -> str:
    """The raw topic an image_transport topic carries (``X/compressed``, ``X/compressedDepth`` -> X)."""
    for suffix in ("/compressed", "/compressedDepth"):
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic


def _peek(reader: Any, conn: Any) -> Any | None:
    """The first message of a connection, deserialised; None when it has none or it does not decode."""
    try:
        for c, _, raw in reader.messages(connections=[conn]):
            return reader.deserialize(raw, c.msgtype)
    except Exception:  # noqa: BLE001 - a topic that cannot be peeked is no candidate
        return None
    return None


def _image_kind(msg: Any) -> str | None:
    """'color', 'mono' or 'depth' for an Image or CompressedImage; None for anything else."""
    if is_compressed(msg):
        return "depth" if compressed_is_depth(msg) else "color"
    enc = str(getattr(msg, "encoding", ""))
    if enc in DEPTH_ENCODINGS:
        return "depth"
    if enc in ("mono8", "8UC1"):
        return "mono"
    return "color" if enc in COLOR_ENCODINGS else None


def discover_topics(reader: Any, topics: BagTopics, with_depth: bool, where: str) -> tuple[BagTopics, str]:
    """The bag's colour, depth and camera_info topics: TUM's (``topics``' defaults) when the bag has
    them, the user's as given (DataError when absent), else found by type and encoding. Returns the
    topics and a line saying what was chosen (empty when nothing was guessed)."""
    conns = {c.topic: c for c in reader.connections}
    for field in topics.explicit:
        if getattr(topics, field) not in conns:
            images = sorted(t for t, c in conns.items() if c.msgtype in IMAGE_TYPES + (INFO_TYPE,))
            raise DataError(f"{where}: no topic {getattr(topics, field)} in the bag (its image and camera_info "
                            f"topics: {', '.join(images) or 'none'})")
    need_rgb = "rgb" not in topics.explicit and topics.rgb not in conns
    need_depth = with_depth and "depth" not in topics.explicit and topics.depth not in conns
    need_info = "rgb_info" not in topics.explicit and topics.rgb_info not in conns
    if not (need_rgb or need_depth or need_info):
        return topics, ""
    # kind -> stream (raw topic) -> (topic to read, its encoding or format)
    found: dict[str, dict[str, tuple[str, str]]] = {"color": {}, "mono": {}, "depth": {}}
    for topic, c in sorted(conns.items()):
        if c.msgtype not in IMAGE_TYPES or (msg := _peek(reader, c)) is None or (kind := _image_kind(msg)) is None:
            continue
        base = _transport_base(topic)
        what = str(msg.format) if is_compressed(msg) else str(msg.encoding)
        if base not in found[kind] or topic == base:  # a stream's raw topic before its transports
            found[kind][base] = (topic, what)
    chosen: dict[str, tuple[str, str]] = {}
    if need_rgb:
        pool = found["color"] or found["mono"]
        if not pool:
            raise DataError(f"{where}: no colour image topic (sensor_msgs/Image rgb8, bgr8 or a CompressedImage); "
                            f"give one with --topics color=/topic")
        if len(pool) > 1:
            raise DataError(f"{where}: {len(pool)} colour image topics ({', '.join(t for t, _ in pool.values())}); "
                            f"choose one with --topics color=/topic")
        chosen["rgb"] = next(iter(pool.values()))
    if need_depth:
        pool = found["depth"]
        aligned = {b: v for b, v in pool.items() if "aligned_depth_to_color" in b}
        pool = aligned or pool
        if not pool:
            raise DataError(f"{where}: no depth image topic (16UC1 / 32FC1 Image or compressedDepth) to pair with "
                            f"colour; a RealSense records depth registered to colour with align_depth.enable:=true "
                            f"(or map colour only: memgs eval --mode mono)")
        if len(pool) > 1:
            raise DataError(f"{where}: {len(pool)} depth image topics ({', '.join(t for t, _ in pool.values())}) "
                            f"and none aligned to colour; choose one with --topics depth=/topic")
        chosen["depth"] = next(iter(pool.values()))
    fields = {k: v[0] for k, v in chosen.items()}
    if need_info:  # the colour stream's own camera_info, or the bag's only one
        sibling = _transport_base(fields.get("rgb", topics.rgb)).rsplit("/", 1)[0] + "/camera_info"
        infos = [t for t, c in conns.items() if c.msgtype == INFO_TYPE]
        if sibling in conns:
            fields["rgb_info"] = sibling
        elif len(infos) == 1:
            fields["rgb_info"] = infos[0]
    out = replace(topics, **cast("dict[str, Any]", fields))  # topic names: str fields only
    if not chosen:
        return out, (f"{where}: camera_info {out.rgb_info}" if out.rgb_info != topics.rgb_info else "")
    line = "; ".join(f"{name} {chosen[key][0]} ({chosen[key][1]})"
                     for name, key in (("colour", "rgb"), ("depth", "depth")) if key in chosen)
    return out, f"{where}: topics found by type: {line}; camera_info {out.rgb_info}"


def _frame_name(name: str) -> str:
    return name.lstrip("/")


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _transform_to_T(tr: Any) -> np.ndarray:
    t, q = tr.translation, tr.rotation
    return pose_from_tq(np.array([t.x, t.y, t.z]), np.array([q.x, q.y, q.z, q.w]))


class _Edge:
    """One tf edge parent -> child: stamped samples of T_parent_child."""

    def __init__(self) -> None:
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []
        self.static = False

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        st = np.asarray(self.stamps, dtype=np.int64)
        P = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        order = np.argsort(st, kind="stable")
        st, P = st[order], P[order]
        keep = np.concatenate([[True], np.diff(st) > 0]) if len(st) else np.zeros(0, bool)
        return st[keep], P[keep]

    def is_constant(self) -> bool:
        P = np.asarray(self.poses)
        return self.static or bool(np.allclose(P, P[:1], atol=1e-9))


class _Scan:
    """What pass 1 collects (filled by BagSource._note, read once by BagSource._scan)."""

    def __init__(self) -> None:
        self.rgb_stamps: list[tuple[int, int]] = []  # (index on topic, stamp)
        self.depth_stamps: list[tuple[int, int]] = []
        self.info: PinholeCamera | None = None
        self.rgb_frame_id: str | None = None
        self.rgb_size: tuple[int, int] | None = None
        self.edges: dict[tuple[str, str], _Edge] = {}
        self.pose_st: list[int] = []
        self.pose_T: list[np.ndarray] = []


class BagSource:
    """A bag as a frame source: ``.camera``, ``.name``, ``len()``, iteration, ``ground_truth()``.

    path: ROS 1 ``.bag`` file, ROS 2 bag directory, or a bare ``.mcap`` / ``.db3`` file.
    depth_scale: 16UC1 / mono16 depth units per metre (RealSense 1000, TUM PNG-style 5000).
    Images decode as :mod:`memgs_ros.io.image_decoding` says: RGB uint8, depth metres with NaN invalid.
    with_depth: False pairs nothing and yields every colour image with depth None. A bad message
    or frame is skipped and counted in ``skipped`` by kind (``strict``: DataError instead).
    """

    def __init__(self, path: str | os.PathLike[str], topics: BagTopics = BagTopics(),
                 camera: PinholeCamera | None = None,
                 max_dt_s: float = 0.02, depth_scale: float = DEFAULT_DEPTH_SCALE, with_depth: bool = True,
                 gt_max_gap_s: float = 0.1, max_frames: int | None = None, strict: bool = False) -> None:
        self.path = Path(path)
        self.name = self.path.name
        self.topics = topics
        self.topic_choice = ""  # what discover_topics chose, when it had to
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise ConfigError(f"depth_scale must be a positive number of units per metre, got {depth_scale}")
        self.depth_scale = float(depth_scale)
        self.with_depth = with_depth
        self._skips = SkipLog(str(self.path), strict)
        self.skipped = self._skips.counts  # bad frames and messages skipped, by kind
        if not self.path.exists():
            raise DataError(f"{self.path}: bag not found")
        self._scan(camera, max_dt_s, gt_max_gap_s, max_frames)

    # ------------------------------------------------------------------ helpers

    def _skip(self, kind: str, detail: str = "", n: int = 1, level: int = logging.WARNING) -> None:
        self._skips.skip(kind, detail, n, level)

    def _open(self) -> Any:
        from rosbags.highlevel import AnyReader

        return AnyReader([self.path], default_typestore=ros2_typestore())

    def _fail(self, err: Exception) -> DataError:
        return DataError(f"{self.path}: cannot read bag ({type(err).__name__}: {err})")

    # -------------------------------------------------------------------- pass 1

    def _scan(self, camera: PinholeCamera | None, max_dt_s: float, gt_max_gap_s: float,
              max_frames: int | None) -> None:
        try:
            with self._open() as reader:
                self.topics, self.topic_choice = discover_topics(reader, self.topics, self.with_depth, str(self.path))
        except MemgsError:
            raise
        except Exception as err:  # noqa: BLE001 - rosbags/mcap/sqlite raise many kinds; the bag is unusable
            raise self._fail(err) from err
        if self.topic_choice:
            logger.info("%s", self.topic_choice)
        scan = self._read_headers(want_camera=camera is None)
        self.camera = self._checked_camera(camera if camera is not None else scan.info, scan.rgb_size)
        self._plan = self._pair_frames(scan, max_dt_s, max_frames)
        if scan.pose_st and self.topics.camera_frame is None:
            self._gt_stamps, self._gt_poses = _sorted_unique(np.array(scan.pose_st, np.int64), np.array(scan.pose_T))
            self.gt_source = self.topics.pose
        else:
            self._gt_stamps, self._gt_poses, self.gt_source = self._gt_from_tf(scan.edges, scan.rgb_frame_id)
        q = np.array([p[2] for p in self._plan], dtype=np.int64)
        self._frame_gt, self._frame_gt_valid = interpolate_poses(
            self._gt_stamps, self._gt_poses, q, round(gt_max_gap_s * 1e9))

    def _read_headers(self, want_camera: bool) -> _Scan:
        """Pass 1 over the wanted connections; a message that does not decode or fit is skipped."""
        scan = _Scan()
        try:
            with self._open() as reader:
                counters: dict[str, int] = defaultdict(int)
                for c, bag_ns, raw in reader.messages(connections=self._wanted_connections(reader)):
                    topic = c.topic
                    index = counters[topic]
                    counters[topic] += 1
                    try:
                        msg = reader.deserialize(raw, c.msgtype)
                    except Exception as err:  # noqa: BLE001 - any decoder failure is one bad message
                        self._skip(f"malformed message on {topic}", f"{type(err).__name__}: {err}")
                        continue
                    try:
                        self._note(scan, topic, msg, index, int(bag_ns), want_camera)
                    except (MessageError, AttributeError, ValueError, DataError) as err:
                        self._skip(f"bad message on {topic}", str(err))
        except MemgsError:
            raise
        except Exception as err:  # noqa: BLE001 - rosbags/mcap/sqlite raise many kinds; the bag is unusable
            raise self._fail(err) from err
        return scan

    def _wanted_connections(self, reader: Any) -> list[Any]:
        """The connections pass 1 reads; the others are counted as skipped, by topic or by type."""
        t = self.topics
        wanted_types = {t.rgb: IMAGE_TYPES, t.depth: IMAGE_TYPES, t.rgb_info: (INFO_TYPE,),
                        t.tf: TF_TYPES, t.tf_static: TF_TYPES, t.pose: (POSE_TYPE,)}
        if not self.with_depth:
            del wanted_types[t.depth]
        conns = []
        for c in reader.connections:
            if c.topic == t.depth_info:
                continue  # depth is registered to colour: its camera_info adds nothing
            if c.topic not in wanted_types:
                # unused topics are normal (TUM: /imu, /cortex_marker_array): counted, not read
                self._skip(f"topic {c.topic}", f"not used ({c.msgtype})", int(c.msgcount), logging.INFO)
            elif c.msgtype not in wanted_types[c.topic]:
                self._skip(f"type {c.msgtype} on {c.topic}", f"expected {wanted_types[c.topic][0]}",
                           int(c.msgcount))
            else:
                conns.append(c)
        return conns

    def _note(self, scan: _Scan, topic: str, msg: Any, index: int, bag_ns: int, want_camera: bool) -> None:
        """Records what pass 1 needs of one message (raises on a message that does not fit)."""
        t = self.topics
        if topic == t.rgb or topic == t.depth:
            is_rgb = topic == t.rgb
            if not is_compressed(msg):
                check_image(msg, COLOR_ENCODINGS if is_rgb else DEPTH_ENCODINGS)
            elif compressed_is_depth(msg) == is_rgb:
                raise MessageError(f"compressed image of format '{msg.format}' on the "
                                   f"{'colour' if is_rgb else 'depth'} topic")
            stamp = _stamp_ns(msg.header) or bag_ns
            if is_rgb:
                scan.rgb_stamps.append((index, stamp))
                if scan.rgb_frame_id is None:
                    scan.rgb_frame_id = _frame_name(str(msg.header.frame_id))
                    if is_compressed(msg):  # the size is inside the JPEG / PNG: decode the first
                        h, w = decode_compressed_rgb(msg).shape[:2]
                        scan.rgb_size = (w, h)
                    else:
                        scan.rgb_size = (int(msg.width), int(msg.height))
            else:
                scan.depth_stamps.append((index, stamp))
        elif topic == t.rgb_info:
            if scan.info is None and want_camera:
                scan.info = decode_camera_info(msg)
        elif topic == t.pose:
            scan.pose_st.append(_stamp_ns(msg.header) or bag_ns)
            p, q = msg.pose.position, msg.pose.orientation
            scan.pose_T.append(pose_from_tq(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])))
        elif topic in (t.tf, t.tf_static):
            for ts in msg.transforms:
                key = (_frame_name(str(ts.header.frame_id)), _frame_name(str(ts.child_frame_id)))
                e = scan.edges.setdefault(key, _Edge())
                e.static |= topic == t.tf_static
                e.stamps.append(_stamp_ns(ts.header) or bag_ns)
                e.poses.append(_transform_to_T(ts.transform))

    def _checked_camera(self, camera: PinholeCamera | None, rgb_size: tuple[int, int] | None) -> PinholeCamera:
        if camera is None:
            raise DataError(f"{self.path}: no CameraInfo on {self.topics.rgb_info}; pass a camera explicitly")
        if rgb_size is not None and rgb_size != (camera.width, camera.height):
            raise DataError(f"{self.path}: colour images are {rgb_size[0]}x{rgb_size[1]} but the camera is "
                            f"{camera.width}x{camera.height}")
        return camera

    def _pair_frames(self, scan: _Scan, max_dt_s: float, max_frames: int | None) -> list[tuple[int, int | None, int]]:
        """(rgb index, depth index, stamp) per frame in stamp order: colour paired with the nearest depth."""
        rgb_stamps, depth_stamps = scan.rgb_stamps, scan.depth_stamps
        rs = np.array([s for _, s in rgb_stamps], dtype=np.int64)
        plan: list[tuple[int, int | None, int]] = []
        if self.with_depth:
            ds = np.array([s for _, s in depth_stamps], dtype=np.int64)
            for i, j in associate(rs, ds, round(max_dt_s * 1e9)):
                plan.append((rgb_stamps[i][0], depth_stamps[j][0], int(rs[i])))
        else:
            plan = [(k, None, s) for k, s in rgb_stamps]
        plan.sort(key=lambda p: p[2])
        if max_frames is not None:
            plan = plan[:max_frames]
        if not plan:
            t = self.topics
            raise DataError(f"{self.path}: no frames (colour on {t.rgb}"
                            f"{f' paired with depth on {t.depth}' if self.with_depth else ''})")
        return plan

    def _gt_from_tf(self, edges: dict[tuple[str, str], _Edge], rgb_frame_id: str | None
                    ) -> tuple[np.ndarray, np.ndarray, str]:
        """Compose tf edges world -> ... -> camera optical frame into (stamps [M], T_wc [M, 4, 4], description)."""
        empty = (np.zeros(0, np.int64), np.zeros((0, 4, 4)), "none")
        if not edges:
            return empty
        parent_of = {child: parent for parent, child in edges}
        t = self.topics
        if t.camera_frame is not None:
            cam = _frame_name(t.camera_frame)
        else:
            cands = [f for f in DEFAULT_CAMERA_FRAMES if f in parent_of] + ([rgb_frame_id] if rgb_frame_id else [])
            cam = next((f for f in cands if f in parent_of), "")
        if cam not in parent_of:
            logger.info("%s: camera frame %r not in the tf tree; no ground truth from tf", self.path, cam)
            return empty
        world = _frame_name(t.world_frame) if t.world_frame is not None else None
        chain: list[_Edge] = []  # from camera up
        node, seen = cam, {cam}
        while node in parent_of and node != world:
            parent = parent_of[node]
            chain.append(edges[(parent, node)])
            if parent in seen:
                raise DataError(f"{self.path}: tf cycle at {parent!r}")
            seen.add(parent)
            node = parent
        if world is not None and node != world:
            logger.info("%s: world frame %r is not above %r in tf; no ground truth", self.path, world, cam)
            return empty
        chain.reverse()  # world first
        dynamic = [e for e in chain if not e.is_constant()]
        stamps = dynamic[0].arrays()[0] if dynamic else chain[0].arrays()[0][:1]
        T = np.tile(np.eye(4), (len(stamps), 1, 1))
        valid = np.ones(len(stamps), dtype=bool)
        for e in chain:
            if e.is_constant():
                T = T @ e.poses[0]
            else:
                st, P = e.arrays()
                Pi, ok = interpolate_poses(st, P, stamps)
                T = T @ Pi
                valid &= ok
        return stamps[valid], T[valid], f"tf {node} -> {cam}"

    # -------------------------------------------------------------------- pass 2

    @property
    def gt_coverage(self) -> float:
        return float(np.mean(self._frame_gt_valid)) if len(self._frame_gt_valid) else 0.0

    def __len__(self) -> int:
        return len(self._plan)

    def frame_stamps(self) -> np.ndarray:
        """[N] int64 the stamps of the frames the scan paired, in order."""
        return np.array([p[2] for p in self._plan], dtype=np.int64)

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole ground-truth trajectory in the bag: (stamps_ns [M], T_wc [M, 4, 4]); empty when absent."""
        return self._gt_stamps.copy(), self._gt_poses.copy()

    def __iter__(self) -> Iterator[Frame]:
        t = self.topics
        want_rgb = {p[0]: k for k, p in enumerate(self._plan)}
        want_depth = {p[1]: k for k, p in enumerate(self._plan) if p[1] is not None}
        rgb: dict[int, np.ndarray] = {}
        depth: dict[int, np.ndarray] = {}
        failed: set[int] = set()
        next_k = 0
        topics = {t.rgb, t.depth} if self.with_depth else {t.rgb}
        try:
            with self._open() as reader:
                conns = [c for c in reader.connections if c.topic in topics and c.msgtype in IMAGE_TYPES]
                counters: dict[str, int] = defaultdict(int)
                for c, _, raw in reader.messages(connections=conns):
                    index = counters[c.topic]
                    counters[c.topic] += 1
                    is_rgb = c.topic == t.rgb
                    k = (want_rgb if is_rgb else want_depth).get(index)
                    if k is None:
                        continue
                    try:
                        msg = reader.deserialize(raw, c.msgtype)
                        img = decode_color_message(msg) if is_rgb else decode_depth_message(msg, self.depth_scale)
                        expected = (self.camera.height, self.camera.width)
                        if img.shape[:2] != expected:
                            raise MessageError(f"image is {img.shape[1]}x{img.shape[0]}, "
                                               f"camera is {expected[1]}x{expected[0]}")
                    except Exception as err:  # noqa: BLE001 - pass 1 validated it; a failure here is one bad frame
                        self._skip(f"undecodable image on {c.topic}", str(err))
                        failed.add(k)
                    else:
                        (rgb if is_rgb else depth)[k] = img
                    while next_k < len(self._plan):
                        need_depth = self._plan[next_k][1] is not None
                        if next_k in failed:
                            rgb.pop(next_k, None)
                            depth.pop(next_k, None)
                            next_k += 1
                            continue
                        if next_k not in rgb or (need_depth and next_k not in depth):
                            break
                        yield self._frame(next_k, rgb.pop(next_k), depth.pop(next_k, None))
                        next_k += 1
            # a planned image that never came back (bag changed under us): emit what is complete
            for k in range(next_k, len(self._plan)):
                if k in rgb and (self._plan[k][1] is None or k in depth):
                    yield self._frame(k, rgb.pop(k), depth.pop(k, None))
                elif k not in failed:
                    self._skip("incomplete frame", f"stamp {self._plan[k][2]}")
        except MemgsError:
            raise
        except Exception as err:  # noqa: BLE001 - the bag became unreadable mid-way
            raise self._fail(err) from err

    def _frame(self, k: int, rgb: np.ndarray, depth: np.ndarray | None) -> Frame:
        gt = self._frame_gt[k].copy() if self._frame_gt_valid[k] else None
        return Frame(self._plan[k][2], rgb, depth, self.camera, gt)


def _sorted_unique(stamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order].reshape(-1, 4, 4)
    keep = np.concatenate([[True], np.diff(stamps) > 0]) if len(stamps) else np.zeros(0, bool)
    return stamps[keep], poses[keep]


__all__ = ["BagSource", "BagTopics", "discover_topics"]
