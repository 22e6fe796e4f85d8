"""Benchmark: message codecs at 640x480 (and a map-sized PointCloud2), median of many calls.

encode = numpy -> message (numpy_to_image / depth_to_image / structured_to_pointcloud2),
decode = message -> numpy (image_decoding.decode_rgb / decode_depth, codecs.pointcloud2_to_structured).
rclpy serialize/deserialize of the same messages is shown for scale (what DDS adds per hop).
Prints a table and writes JSON (default results/bench_codecs.json). The machine is shared:
``uptime`` load is recorded before and after.

    python benchmarks/bench_codecs.py
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _common import write_results


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=100)
    parser.add_argument("--points", type=int, default=100_000, help="PointCloud2 size")
    parser.add_argument("--out", type=Path, default=Path("results/bench_codecs.json"))
    args = parser.parse_args()

    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image

    from memgs_ros.io import image_decoding
    from memgs_ros.ros import codecs, images

    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 5.0, (480, 640)).astype(np.float32)
    bgr_msg = images.numpy_to_image(np.ascontiguousarray(rgb[:, :, ::-1]), "bgr8", 0, "c")
    rgb_msg = images.numpy_to_image(rgb, "rgb8", 0, "c")
    f32_msg = images.depth_to_image(depth, "32FC1", 0, "c")
    u16_msg = images.depth_to_image(depth, "16UC1", 0, "c")
    # A map delta: id (uint64), position, and the 56 other float32 of an SH-degree-3 Gaussian.
    cloud = np.zeros(args.points, [("id", "<u8"), ("xyz", "<f4", (3,)), ("params", "<f4", (56,))])
    cloud_msg = codecs.structured_to_pointcloud2(cloud, 0, "map")
    rgb_wire = serialize_message(rgb_msg)
    r, rp = args.repeats, max(5, args.repeats // 10)
    rows = [
        ("rgb8", "encode", median_ms(lambda: images.numpy_to_image(rgb, "rgb8", 0, "c"), r)),
        ("rgb8", "decode", median_ms(lambda: image_decoding.decode_rgb(rgb_msg), r)),
        ("bgr8", "decode to RGB", median_ms(lambda: image_decoding.decode_rgb(bgr_msg), r)),
        ("32FC1", "encode", median_ms(lambda: images.depth_to_image(depth, "32FC1", 0, "c"), r)),
        ("32FC1", "decode", median_ms(lambda: image_decoding.decode_depth(f32_msg), r)),
        ("16UC1 mm", "encode", median_ms(lambda: images.depth_to_image(depth, "16UC1", 0, "c"), r)),
        ("16UC1 mm", "decode", median_ms(lambda: image_decoding.decode_depth(u16_msg), r)),
        ("rgb8", "rclpy serialize", median_ms(lambda: serialize_message(rgb_msg), r)),
        ("rgb8", "rclpy deserialize", median_ms(lambda: deserialize_message(rgb_wire, Image), r)),
        (f"PointCloud2 {args.points} x {cloud.dtype.itemsize} B", "encode",
         median_ms(lambda: codecs.structured_to_pointcloud2(cloud, 0, "map"), rp)),
        (f"PointCloud2 {args.points} x {cloud.dtype.itemsize} B", "decode",
         median_ms(lambda: codecs.pointcloud2_to_structured(cloud_msg), rp)),
        (f"PointCloud2 {args.points} x {cloud.dtype.itemsize} B", "rclpy serialize",
         median_ms(lambda: serialize_message(cloud_msg), rp)),
    ]
    load_after = os.getloadavg()[0]

    print(f"{'message':34s} {'step':18s} {'median ms':>10s}")
    for what, step, ms in rows:
        print(f"{what:34s} {step:18s} {ms:10.3f}")
    print(f"load average before/after: {load_before:.1f} / {load_after:.1f} (2 shared cores)")
    write_results(args.out, {
        "rows": [{"message": w, "step": s, "median_ms": m} for w, s, m in rows],
        "repeats": args.repeats, "load_before": load_before, "load_after": load_after,
    })
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
