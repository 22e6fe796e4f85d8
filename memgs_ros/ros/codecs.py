"""Conversions between ROS 2 messages and numpy / core types.

sensor_msgs_py is not on PyPI, so PointCloud2 packing lives here (image messages:
:mod:`memgs_ros.ros.images`). Every conversion that can fail raises :class:`MessageError`
naming the field or size that is wrong. :func:`pointcloud2_to_structured` returns a view on the message buffer where the
layout allows it (no copy); treat it as read-only.

uint64 / int64 in PointCloud2: ``sensor_msgs/PointField`` has no 64-bit integer type, so
a 64-bit field ``name`` travels as two 4-byte fields at adjacent offsets: ``name_lo``
(UINT32, low word) and ``name_hi`` (UINT32 for uint64, INT32 for int64, high word).
:func:`structured_to_pointcloud2` splits such fields and :func:`pointcloud2_to_structured`
joins the pair back into one 64-bit field, so round trips are transparent and any other
reader still sees two plain integer fields.
"""
from __future__ import annotations

import array
import math
import sys
from collections.abc import Sequence
from itertools import chain
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, PoseStamped
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from memgs_ros.core.geometry.poses import pose_from_tq, quat_xyzw_of, rotmat_to_rotvec
from memgs_ros.errors import MessageError

__all__ = [
    "append_to_path",
    "bytes_array",
    "make_header",
    "matrix_to_odometry",
    "matrix_to_pose",
    "matrix_to_pose_stamped",
    "ns_to_stamp",
    "pointcloud2_to_structured",
    "pose_fields_to_matrix",
    "pose_to_matrix",
    "pose_to_odometry",
    "set_pose_fields",
    "set_stamp",
    "set_tracked_odometry",
    "stamp_to_ns",
    "structured_to_pointcloud2",
]

_NS_PER_S = 1_000_000_000
_INT32_MAX = 2**31 - 1


def bytes_array(arr: np.ndarray) -> array.array:
    """The raw bytes of a C-contiguous array as the array('B') rclpy stores uint8[] in.

    Assigning array('B') to a message field skips rclpy's per-element type check, so this
    is one memcpy; bytes or lists go through a Python loop over every byte.
    """
    out = array.array("B")
    out.frombytes(np.ascontiguousarray(arr).reshape(-1).view(np.uint8).data)
    return out


def _buffer(data: object) -> np.ndarray:
    """uint8 view of a message's data field (array('B'), bytes, bytearray or list)."""
    if isinstance(data, (array.array, bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8)


# --------------------------------------------------------------------------- stamps


def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time to integer nanoseconds."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


# Message fields are set in place on the sub-messages a new message makes anyway: a generated
# message's constructor builds every default sub-message even when one is passed in, so passing
# them built (a Header with its Time, a Pose with its Point and Quaternion) built each twice.


def set_stamp(stamp: Time, stamp_ns: int) -> None:
    """Write integer nanoseconds (>= 0, fits the int32 seconds of Time) into ``stamp`` in place."""
    ns = int(stamp_ns)
    sec, nanosec = divmod(ns, _NS_PER_S)
    if ns < 0 or sec > _INT32_MAX:
        raise MessageError(f"stamp {ns} ns does not fit builtin_interfaces/Time (0 <= sec <= {_INT32_MAX})")
    stamp.sec, stamp.nanosec = sec, nanosec


def ns_to_stamp(stamp_ns: int) -> Time:
    """Integer nanoseconds (>= 0, fits the int32 seconds of Time) to builtin_interfaces/Time."""
    out = Time()
    set_stamp(out, stamp_ns)
    return out


def set_header(header: Header, stamp_ns: int, frame_id: str) -> Header:
    """``header`` stamped ``stamp_ns`` in ``frame_id``, in place (a publisher's reused message)."""
    set_stamp(header.stamp, stamp_ns)
    header.frame_id = frame_id
    return header


def make_header(stamp_ns: int, frame_id: str) -> Header:
    return set_header(Header(), stamp_ns, frame_id)


# --------------------------------------------------------------------------- poses


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """geometry_msgs/Pose -> [4, 4] float64 (the quaternion is normalised)."""
    return pose_fields_to_matrix(pose.position, pose.orientation)


def pose_fields_to_matrix(p: Any, o: Any) -> np.ndarray:
    """A position (Point or Vector3: a Pose's or a Transform's) and a Quaternion -> [4, 4] float64,
    the quaternion normalised; MessageError when not finite or the quaternion is zero."""
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    q_xyzw = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
    n = float(np.linalg.norm(q_xyzw))
    if not (np.all(np.isfinite(t)) and np.isfinite(n) and n > 1e-9):
        raise MessageError(f"Pose is not finite or has a zero quaternion: position {t}, orientation xyzw {q_xyzw}")
    return pose_from_tq(t, q_xyzw / n)


def set_pose_fields(position: Any, orientation: Any, T: np.ndarray) -> None:
    """Write the [4, 4] rigid transform T (checked first: finite, 4x4) into a position (Point or
    Vector3: a Pose's or a Transform's) and a Quaternion, in place."""
    T = np.asarray(T, dtype=np.float64)
    rows = T.tolist()
    if T.shape != (4, 4) or not all(map(math.isfinite, chain.from_iterable(rows))):
        raise MessageError(f"pose must be a finite 4x4 matrix, got shape {T.shape}")
    (m00, m01, m02, tx), (m10, m11, m12, ty), (m20, m21, m22, tz), _ = rows
    position.x, position.y, position.z = tx, ty, tz
    orientation.x, orientation.y, orientation.z, orientation.w = quat_xyzw_of(
        m00, m01, m02, m10, m11, m12, m20, m21, m22)


def set_pose(pose: Pose, T: np.ndarray) -> Pose:
    """Write the [4, 4] rigid transform T into ``pose`` in place (checked first: finite, 4x4)."""
    set_pose_fields(pose.position, pose.orientation, T)
    return pose


def matrix_to_pose(T: np.ndarray) -> Pose:
    """[4, 4] rigid transform -> geometry_msgs/Pose."""
    return set_pose(Pose(), T)


def matrix_to_pose_stamped(T_wc: np.ndarray, stamp_ns: int, frame_id: str) -> PoseStamped:
    """Camera-in-world [4, 4] -> PoseStamped in ``frame_id`` (the world frame)."""
    msg = PoseStamped()
    set_pose(msg.pose, T_wc)
    set_header(msg.header, stamp_ns, frame_id)
    return msg


def matrix_to_odometry(T_wc: np.ndarray, stamp_ns: int, frame_id: str, child_frame_id: str) -> Odometry:
    """Camera-in-world [4, 4] -> Odometry (pose only; twist left zero with zero covariance)."""
    return pose_to_odometry(matrix_to_pose_stamped(T_wc, stamp_ns, frame_id), child_frame_id)


def set_tracked_odometry(msg: Odometry, pose_cov: np.ndarray, T_wc: np.ndarray, T_wc_prev: np.ndarray | None,
                         dt_s: float) -> Odometry:
    """Fill ``msg``'s pose covariance [6, 6] (ROS order, world frame) and its twist in the child
    (camera) frame from the motion since ``T_wc_prev`` over ``dt_s``, with a covariance of twice the
    pose's over dt^2 (two poses' noise in one difference); zero twist, covariance -1 (unknown) on its
    diagonal, without a previous pose."""
    msg.pose.covariance = [float(v) for v in np.asarray(pose_cov, np.float64).reshape(36)]
    tw = msg.twist.twist
    if T_wc_prev is None or not dt_s > 0:
        tw.linear.x = tw.linear.y = tw.linear.z = tw.angular.x = tw.angular.y = tw.angular.z = 0.0
        msg.twist.covariance = [-1.0 if i % 7 == 0 else 0.0 for i in range(36)]
        return msg
    d = np.linalg.inv(T_wc_prev) @ T_wc  # the motion in the previous camera frame
    R_cw = T_wc[:3, :3].T
    v = R_cw @ (T_wc[:3, 3] - T_wc_prev[:3, 3]) / dt_s
    w = rotmat_to_rotvec(d[:3, :3]) / dt_s
    tw.linear.x, tw.linear.y, tw.linear.z = (float(x) for x in v)
    tw.angular.x, tw.angular.y, tw.angular.z = (float(x) for x in w)
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R_cw  # world -> child frame
    msg.twist.covariance = [float(x) for x in (2.0 * A @ pose_cov @ A.T / dt_s ** 2).reshape(36)]
    return msg


def pose_to_odometry(pose: PoseStamped, child_frame_id: str, out: Odometry | None = None) -> Odometry:
    """The Odometry of a PoseStamped (its header and pose, which it shares; twist left zero with
    zero covariance): a node publishing both converts the matrix once. ``out``: a publisher's
    Odometry to fill instead of a new one (its twist and covariances are left as they are)."""
    msg = Odometry() if out is None else out
    msg.header = pose.header
    msg.child_frame_id = child_frame_id
    msg.pose.pose = pose.pose
    return msg


def append_to_path(path: Path, pose: PoseStamped, max_len: int = 0) -> Path:
    """Append ``pose`` to ``path`` in place, keep at most ``max_len`` poses (0 = all), and
    stamp the path with the newest pose. Returns ``path`` for chaining."""
    path.poses.append(pose)
    if max_len > 0 and len(path.poses) > max_len:
        del path.poses[: len(path.poses) - max_len]
    path.header.stamp = pose.header.stamp
    if not path.header.frame_id:
        path.header.frame_id = pose.header.frame_id
    return path


# --------------------------------------------------------------------------- PointCloud2

_POINTFIELD_DTYPES: dict[int, np.dtype] = {
    PointField.INT8: np.dtype(np.int8),
    PointField.UINT8: np.dtype(np.uint8),
    PointField.INT16: np.dtype(np.int16),
    PointField.UINT16: np.dtype(np.uint16),
    PointField.INT32: np.dtype(np.int32),
    PointField.UINT32: np.dtype(np.uint32),
    PointField.FLOAT32: np.dtype(np.float32),
    PointField.FLOAT64: np.dtype(np.float64),
}
_DTYPE_POINTFIELDS: dict[np.dtype, int] = {dt: code for code, dt in _POINTFIELD_DTYPES.items()}


def structured_to_pointcloud2(arr: np.ndarray, stamp_ns: int, frame_id: str) -> PointCloud2:
    """Structured array -> unorganised (height 1) or organised PointCloud2, little-endian.

    arr: [N] or [H, W] structured array; each field a scalar or fixed sub-array (-> count)
    of int8/16/32, uint8/16/32, float32/64, or uint64/int64 (split into ``<name>_lo`` /
    ``<name>_hi``, see the module docstring). The dtype's offsets and itemsize (padding)
    become the PointField offsets and point_step, so the bytes are copied once, as is.
    """
    a = np.asarray(arr)
    if a.dtype.names is None:
        raise MessageError(f"PointCloud2 needs a structured array, got dtype {a.dtype}")
    if a.ndim not in (1, 2):
        raise MessageError(f"PointCloud2 needs a [N] or [H, W] structured array, got shape {a.shape}")
    fields: list[PointField] = []
    names = set(a.dtype.names)
    le_fields: dict[str, tuple] = {}
    dtype_fields = a.dtype.fields
    assert dtype_fields is not None  # a structured array (names checked above)
    for name in a.dtype.names:
        ftype, offset = dtype_fields[name][:2]
        base, shape = ftype.base, ftype.shape
        count = int(np.prod(shape)) if shape else 1
        le_fields[name] = (base.newbyteorder("<") if base.itemsize > 1 else base, shape, offset)
        if base.kind in "iu" and base.itemsize == 8:
            if count != 1:
                raise MessageError(f"PointCloud2 field '{name}': 64-bit integer sub-arrays are not supported")
            for part in (f"{name}_lo", f"{name}_hi"):
                if part in names:
                    raise MessageError(f"PointCloud2 field '{name}' (64-bit) clashes with existing field '{part}'")
            hi_type = PointField.INT32 if base.kind == "i" else PointField.UINT32
            fields.append(PointField(name=f"{name}_lo", offset=offset, datatype=PointField.UINT32, count=1))
            fields.append(PointField(name=f"{name}_hi", offset=offset + 4, datatype=hi_type, count=1))
            continue
        code = _DTYPE_POINTFIELDS.get(base.newbyteorder("="))
        if code is None:
            raise MessageError(f"PointCloud2 field '{name}' has dtype {base}, which PointField cannot carry")
        fields.append(PointField(name=name, offset=offset, datatype=code, count=count))
    # Little-endian on the wire; byte-swaps only when the input was big-endian.
    wire = np.dtype({
        "names": list(le_fields),
        "formats": [(b, s) if s else b for b, s, _ in le_fields.values()],
        "offsets": [o for _, _, o in le_fields.values()],
        "itemsize": a.dtype.itemsize,
    })
    a = np.ascontiguousarray(a.astype(wire, copy=False))
    msg = PointCloud2()
    msg.header = make_header(stamp_ns, frame_id)
    msg.height, msg.width = (1, a.shape[0]) if a.ndim == 1 else (a.shape[0], a.shape[1])
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = a.dtype.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.is_dense = False  # we do not scan for NaNs; False is always a safe claim
    msg.data = bytes_array(a) if a.size else array.array("B")
    return msg


def _field_dtype(f: PointField, big: bool) -> np.dtype:
    base = _POINTFIELD_DTYPES.get(int(f.datatype))
    if base is None:
        raise MessageError(f"PointCloud2 field '{f.name}' has unknown datatype {f.datatype}")
    return base.newbyteorder(">" if big else "<") if base.itemsize > 1 else base


def pointcloud2_to_structured(msg: PointCloud2, required: Sequence[str] = ()) -> np.ndarray:
    """PointCloud2 -> [H*W] structured array in native byte order.

    Honours point_step, row_step (row padding is skipped), field offsets, count (-> a
    sub-array field) and is_bigendian. A ``<name>_lo`` / ``<name>_hi`` pair of 4-byte
    integer fields at adjacent offsets comes back as one 64-bit field ``name``.
    ``required`` lists field names that must be present. The result is a view on the
    message buffer for little-endian clouds without row padding.
    """
    big = bool(msg.is_bigendian)
    h, w = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    by_name = _fields_by_name(msg, required)
    buf = _checked_buffer(msg, big)
    wire = _wire_dtype(msg.fields, _joined_64bit(by_name, big), big, point_step)
    if h * w == 0:
        return np.zeros(0, dtype=wire.newbyteorder("="))
    if row_step == w * point_step:
        out = np.frombuffer(buf, dtype=wire, count=h * w)
    else:
        out = np.ndarray(shape=(h, w), dtype=wire, buffer=buf, strides=(row_step, point_step)).reshape(-1)
    if (big and sys.byteorder == "little") or (not big and sys.byteorder == "big"):
        out = out.astype(wire.newbyteorder("="))
    return out


def _fields_by_name(msg: PointCloud2, required: Sequence[str]) -> dict[str, PointField]:
    """The cloud's fields by name; MessageError for a repeated, missing required or absent field."""
    by_name: dict[str, PointField] = {}
    for f in msg.fields:
        if f.name in by_name:
            raise MessageError(f"PointCloud2 has field '{f.name}' twice")
        by_name[f.name] = f
    missing = [n for n in required if n not in by_name and not (f"{n}_lo" in by_name and f"{n}_hi" in by_name)]
    if missing:
        raise MessageError(f"PointCloud2 lacks required field(s) {missing}; it has {list(by_name)}")
    if not by_name:
        raise MessageError("PointCloud2 has no fields")
    return by_name


def _checked_buffer(msg: PointCloud2, big: bool) -> np.ndarray:
    """The data buffer, after checking that every field fits point_step and the data the rows."""
    h, w = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    for f in msg.fields:
        dt = _field_dtype(f, big)
        count = int(f.count)
        if count < 1:
            raise MessageError(f"PointCloud2 field '{f.name}' has count {count}, must be >= 1")
        if f.offset + dt.itemsize * count > point_step:
            raise MessageError(
                f"PointCloud2 field '{f.name}' (offset {f.offset}, {dt.itemsize * count} bytes) "
                f"does not fit point_step {point_step}"
            )
    if h * w and row_step < w * point_step:
        raise MessageError(f"PointCloud2 row_step {row_step} is less than width*point_step = {w * point_step}")
    buf = _buffer(msg.data)
    if buf.size != row_step * h:
        raise MessageError(
            f"PointCloud2 data has {buf.size} bytes, expected row_step*height = {row_step}*{h} = {row_step * h}"
        )
    return buf


def _joined_64bit(by_name: dict[str, PointField], big: bool) -> dict[str, tuple[np.dtype, int]]:
    """stem -> (64-bit dtype, offset) for each ``stem_lo`` / ``stem_hi`` pair that is one split
    64-bit field: the 8 bytes are contiguous, low word first on little-endian wires and high
    word first on big-endian ones, so one 8-byte field covers both."""
    joined: dict[str, tuple[np.dtype, int]] = {}
    for name, lo in by_name.items():
        if not name.endswith("_lo"):
            continue
        stem = name[:-3]
        hi = by_name.get(f"{stem}_hi")
        if (
            hi is None or stem in by_name or lo.datatype != PointField.UINT32 or lo.count != 1 or hi.count != 1
            or hi.datatype not in (PointField.UINT32, PointField.INT32)
        ):
            continue
        start = lo.offset if not big else hi.offset
        if (hi.offset - lo.offset) != (4 if not big else -4):
            continue
        base = np.dtype(np.int64 if hi.datatype == PointField.INT32 else np.uint64)
        joined[stem] = (base.newbyteorder(">" if big else "<"), start)
    return joined


def _wire_dtype(fields: Sequence[PointField], joined: dict[str, tuple[np.dtype, int]], big: bool,
                point_step: int) -> np.dtype:
    """The structured dtype of one point on the wire: plain fields, joined 64-bit ones instead of
    their halves, in offset order."""
    consumed = {f"{stem}{half}" for stem in joined for half in ("_lo", "_hi")}
    names, formats, offsets = [], [], []
    for f in fields:
        if f.name in consumed:
            continue
        dt = _field_dtype(f, big)
        names.append(f.name)
        formats.append((dt, (int(f.count),)) if f.count > 1 else dt)
        offsets.append(int(f.offset))
    for stem, (dt, start) in joined.items():
        names.append(stem)
        formats.append(dt)
        offsets.append(start)
    order = np.argsort(offsets, kind="stable")
    return np.dtype({
        "names": [names[i] for i in order],
        "formats": [formats[i] for i in order],
        "offsets": [offsets[i] for i in order],
        "itemsize": point_step,
    })
