"""The packed ``rgb`` colour of whole-map messages: present, equal to the SH DC colour, harmless."""
from __future__ import annotations

import numpy as np
import pytest

from memgs_ros.core.gaussians.gaussian_map import SH_C0
from memgs_ros.core.gaussians.records import PLY_F_REST, GaussianRecords
from memgs_ros.core.map_io.map_delta import (
    DeltaOutbox,
    MapReplica,
    MessageKind,
    decode,
    encode,
    message_dtype,
    packed_rgb,
    unpack_rgb,
)


def _records(n: int, seed: int = 0) -> GaussianRecords:
    rng = np.random.default_rng(seed)
    f_dc = rng.normal(scale=2.0, size=(n, 3))  # wide: many channels clip at 0 and 1
    return GaussianRecords.from_arrays(np.arange(1, n + 1) * 3, rng.normal(size=(n, 3)), f_dc,
                                       rng.normal(size=(n, PLY_F_REST)), rng.normal(size=n),
                                       rng.normal(size=(n, 3)), rng.normal(size=(n, 4)))


def _expected_rgb(f_dc: np.ndarray) -> np.ndarray:
    """[N, 3] uint8 from the 3DGS colour formula, in float64 (the encoder works in float32)."""
    return np.rint(np.clip(0.5 + SH_C0 * f_dc.astype(np.float64), 0.0, 1.0) * 255).astype(np.uint8)


def test_packed_rgb_matches_the_sh_dc_colour_and_the_pcl_layout() -> None:
    f_dc = np.array([[0.0, 0.0, 0.0], [10.0, -10.0, 0.5 / SH_C0], [-0.5 / SH_C0, 0.25 / SH_C0, 1.0]], np.float32)
    packed = packed_rgb(f_dc)
    assert packed.dtype == np.float32 and packed.shape == (3,)
    bits = packed.view(np.uint32)
    # mid grey; red clipped to 255, green to 0, blue exactly 1.0; then 0, 191 (0.75), 199 (0.782)
    assert bits.tolist() == [0x808080, 0xFF00FF, (0 << 16) | (191 << 8) | 199]
    assert np.all(np.isfinite(packed))  # the zero top byte: never a NaN bit pattern
    # little-endian bytes b, g, r, 0: what RViz's RGB8 and Foxglove's packed-rgb modes read
    assert packed[1:2].tobytes() == bytes([0xFF, 0x00, 0xFF, 0x00])
    assert np.array_equal(unpack_rgb(packed), _expected_rgb(f_dc))


def test_snapshot_and_full_map_carry_rgb_deltas_do_not() -> None:
    rec = _records(50)
    snap = encode(MessageKind.SNAPSHOT, 4, 50, rec, np.zeros(0, np.int64), 3, rgb=True)
    assert snap.dtype == message_dtype(3, rgb=True)
    assert snap.dtype.names[:6] == ("id", "op", "x", "y", "z", "rgb")
    assert message_dtype(3, rgb=True).itemsize == message_dtype(3).itemsize + 4
    assert np.array_equal(unpack_rgb(snap["rgb"][1:]), _expected_rgb(rec.f_dc))
    assert snap["rgb"][0] == 0  # META row
    outbox = DeltaOutbox(sh_degree=3)
    assert "rgb" in outbox.snapshot(rec).dtype.names  # the mapper's snapshots
    assert "rgb" not in outbox.next_delta(_records(60, seed=1)).dtype.names  # its deltas


@pytest.mark.parametrize("degree", [0, 3])
def test_round_trip_with_rgb_is_exact(degree: int) -> None:
    rec = _records(20)
    f_rest = np.zeros_like(rec.f_rest)
    if degree:
        f_rest[:] = rec.f_rest
    rec = GaussianRecords.from_arrays(rec.ids, rec.xyz, rec.f_dc, f_rest, rec.opacity, rec.scale, rec.rot)
    msg = decode(encode(MessageKind.SNAPSHOT, 9, 20, rec, np.zeros(0, np.int64), degree, epoch=70000, rgb=True))
    assert (msg.kind, msg.seq, msg.total, msg.epoch) == (MessageKind.SNAPSHOT, 9, 20, 70000)
    for f in ("ids", "xyz", "f_dc", "f_rest", "opacity", "scale", "rot"):
        assert np.array_equal(getattr(msg.upserts, f), getattr(rec, f)), f
    replica = MapReplica()
    replica.apply(msg)
    assert len(replica) == 20


def test_rgb_survives_pointcloud2_and_decodes_through_it() -> None:
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from sensor_msgs.msg import PointField

    from memgs_ros.ros.codecs import (
        pointcloud2_to_structured,
        structured_to_pointcloud2,
    )

    rec = _records(30)
    cloud = structured_to_pointcloud2(
        encode(MessageKind.SNAPSHOT, 2, 30, rec, np.zeros(0, np.int64), 3, rgb=True), 5, "map")
    field = {f.name: f for f in cloud.fields}["rgb"]
    assert (field.datatype, field.count, field.offset) == (PointField.FLOAT32, 1, 8 + 1 + 12)
    assert cloud.point_step == message_dtype(3).itemsize + 4
    rows = pointcloud2_to_structured(cloud)
    assert np.array_equal(unpack_rgb(rows["rgb"][1:]), _expected_rgb(rec.f_dc))
    got = decode(rows).upserts
    assert np.array_equal(got.f_dc, rec.f_dc) and np.array_equal(got.xyz, rec.xyz)
