"""``memgs convert``: TUM folder, TUM ROS 1 bag or synthetic spec -> ROS 2 bag (MCAP or sqlite3), or
-> ROS 1 ``.bag`` in the layout of TUM's published bags."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "convert a TUM folder, a TUM ROS 1 bag or a synthetic spec into a ROS 2 bag (or a TUM-layout ROS 1 .bag)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="TUM RGB-D folder, ROS 1 .bag, ROS 2 bag, or 'synthetic:...' spec")
    p.add_argument("out", type=Path, help="output bag: .mcap or .db3 file, or a bag directory (must not exist); "
                   "a .bag file is a ROS 1 bag in TUM's layout (bz2, TUM's topics and tf frames)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default=None,
                   help="bag storage (default: from the output suffix, else mcap)")
    p.add_argument("--max-frames", type=int, default=None, help="convert only the first N frames")
    p.add_argument("--max-dt", type=float, default=0.02, help="colour/depth pairing tolerance, s (default 0.02)")
    p.add_argument("--camera-frame", default="camera_rgb_optical_frame",
                   help="frame id of the images and the tf child (default: %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import time

    from tqdm import tqdm

    from memgs_ros.errors import ConfigError, DataError
    from memgs_ros.io.bag_reader import BagSource
    from memgs_ros.io.bag_writer import write_bag, write_ros1_tum_bag
    from memgs_ros.io.sources import open_source

    if args.out.exists():  # before reading the source, so the error is not lost behind a progress bar
        raise DataError(f"{args.out}: already exists; refusing to overwrite")
    ros1 = args.out.suffix == ".bag"
    if ros1 and args.storage is not None:
        raise ConfigError("--storage is for ROS 2 bags; a .bag output is always a ROS 1 bag")
    t0 = time.perf_counter()
    src = open_source(args.source, max_dt_s=args.max_dt, max_frames=args.max_frames)
    frames = tqdm(src, total=len(src), desc="convert", unit="frame", disable=args.no_progress)
    if ros1:  # TUM's frame ids (/openni_rgb_optical_frame ...): --camera-frame does not apply
        res = write_ros1_tum_bag(frames, args.out)
    else:
        res = write_bag(frames, args.out, storage=args.storage, camera_frame_id=args.camera_frame)
    dt = time.perf_counter() - t0
    gt = src.ground_truth()[0]
    print(f"{src.name} -> {res.path}: {res.frames} frames, {res.bytes / 1e6:.1f} MB, {dt:.2f} s "
          f"({res.frames / max(dt, 1e-9):.1f} frames/s); ground truth samples in source: {len(gt)}")
    if isinstance(src, BagSource) and src.skipped:
        print("skipped: " + ", ".join(f"{k}: {v}" for k, v in sorted(src.skipped.items())))
    return 0
