"""The calibration from the config against TUM's bags (issue 15): a bag whose camera_info is the ROS
default must map as well as the TUM folder it was made from.

TUM's published ROS 1 bags carry the ROS default camera_info (fx = fy = 525, cx = 319.5,
cy = 239.5, no distortion) instead of the freiburg calibration. This script:

1. converts a TUM folder into a ROS 1 bag in TUM's layout (``memgs convert FOLDER X.bag``);
2. rewrites that bag's camera_info messages to the ROS default, as TUM's bags have them;
3. runs ``memgs eval`` on the rewritten bag and on the folder, both with ``--config`` (default
   tum_fr1, whose calibration overrides camera_info), same seed and settings;
4. prints PSNR (every tracked frame and keyframes) and ATE of both and their differences, and
   checks the targets: PSNR within 0.3 dB, ATE within 0.2 cm (exit 1 when one is missed).

``--baseline`` adds a third run on the bag with ``tracker.camera_info_override=false``: the
number before the fix (the nodes trust the placeholder camera_info).

    python benchmarks/bench_calibration.py --scale 0.5 --set mapper.final_iterations=600
    python benchmarks/bench_calibration.py --max-frames 20 --set mapper.final_iterations=30  # smoke test
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from _common import TUM_HELP, run_memgs, tum_path_or_exit, uptime

from memgs_ros.core.geometry.camera import PinholeCamera

# What TUM's ROS 1 bags publish on /camera/rgb/camera_info (reference section 6).
ROS_DEFAULT = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
PSNR_TARGET_DB = 0.3
ATE_TARGET_CM = 0.2


def memgs(*args: str) -> None:
    """Run a memgs command in a child process, its output on the terminal; raise on failure."""
    code = run_memgs(args, echo=True).returncode
    if code != 0:
        raise SystemExit(f"memgs {args[0]} failed with exit code {code}")


def rewrite_camera_info(src: Path, dst: Path) -> int:
    """Copy the ROS 1 bag ``src`` to ``dst`` with every CameraInfo replaced by the ROS default
    calibration (scaled to its image size, no distortion). Returns the messages rewritten."""
    from rosbags.rosbag1 import Reader, Writer

    from memgs_ros.io.bag_writer import MessageFactory, ros1_typestore

    ts = ros1_typestore()
    factory = MessageFactory(ts, ros1=True)
    rewritten = 0
    tmp = dst.with_name(dst.name + ".partial")
    tmp.unlink(missing_ok=True)
    with Reader(src) as reader:
        writer = Writer(tmp)
        writer.set_compression(Writer.CompressionFormat.BZ2)  # as TUM's bags
        with writer:
            conns: dict[int, Any] = {}
            for conn, stamp_ns, raw in reader.messages():
                if conn.id not in conns:
                    conns[conn.id] = writer.add_connection(conn.topic, conn.msgtype, typestore=ts)
                if conn.msgtype == "sensor_msgs/msg/CameraInfo":
                    info = ts.deserialize_ros1(raw, conn.msgtype)
                    camera = ROS_DEFAULT.fitted(int(info.width), int(info.height))
                    raw = ts.serialize_ros1(factory.camera_info(info.header, camera), conn.msgtype)
                    rewritten += 1
                writer.write(conns[conn.id], stamp_ns, raw)
    os.replace(tmp, dst)
    return rewritten


def headline(eval_json: Path) -> dict[str, float | None]:
    r = json.loads(eval_json.read_text())
    traj = r.get("trajectory") or {}
    return {"psnr_db": r["frames_quality"]["psnr_db"], "psnr_kf_db": r["keyframes_quality"]["psnr_db"],
            "ate_cm": traj["rmse_m"] * 100 if traj.get("rmse_m") is not None else None,
            "gaussians": r["gaussians"], "frames": r["frames"], "poses": r["poses"]}


def _fmt(v: float | None, digits: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("source", nargs="?", type=Path, default=None, help=TUM_HELP)
    p.add_argument("--config", default="tum_fr1", help="config with the calibration (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("results/bench_calibration"), help="output folder")
    p.add_argument("--max-frames", type=int, default=0, help="use only the first N frames (0 = all)")
    p.add_argument("--scale", type=float, default=None, help="mapping resolution scale (memgs eval --scale)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                   help="parameter override for every run (repeatable)")
    p.add_argument("--baseline", action="store_true",
                   help="also run the bag with tracker.camera_info_override=false (the number before the fix)")
    p.add_argument("--no-lpips", action="store_true")
    p.add_argument("--json", type=Path, default=None, help="summary JSON (default: OUT/bench_calibration.json)")
    args = p.parse_args(argv)
    args.source = tum_path_or_exit(p, args.source, flag="SOURCE")
    if args.max_frames < 0 or (args.scale is not None and not args.scale > 0):
        p.error("--max-frames must be >= 0 and --scale positive")

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    load = uptime()
    print(f"machine: {os.cpu_count()} cores, {load}")

    converted, tum_like = out / "converted.bag", out / "tum_like.bag"
    for path in (converted, tum_like):
        path.unlink(missing_ok=True)
    memgs("convert", str(args.source), str(converted), "--no-progress",
          *(["--max-frames", str(args.max_frames)] if args.max_frames else []))
    n = rewrite_camera_info(converted, tum_like)
    converted.unlink()
    from memgs_ros.io.sources import open_source

    bag_camera = open_source(tum_like).camera
    print(f"{tum_like}: {n} camera_info messages rewritten to fx {bag_camera.fx} fy {bag_camera.fy} "
          f"cx {bag_camera.cx} cy {bag_camera.cy}, distortion {bag_camera.dist}")

    common = ["--config", args.config, "--seed", str(args.seed), "--no-plots"]
    common += ["--max-frames", str(args.max_frames)] if args.max_frames else []
    common += ["--scale", str(args.scale)] if args.scale is not None else []
    common += ["--no-lpips"] if args.no_lpips else []
    for item in args.set:
        common += ["--set", item]
    runs = {"bag": [str(tum_like)], "folder": [str(args.source)]}
    if args.baseline:
        runs["bag_no_override"] = [str(tum_like), "--set", "tracker.camera_info_override=false"]
    results: dict[str, dict[str, float | None]] = {}
    for name, run_args in runs.items():
        t0 = time.monotonic()
        memgs("eval", run_args[0], "--out", str(out / name), *common, *run_args[1:])
        results[name] = {**headline(out / name / "eval.json"), "wall_s": round(time.monotonic() - t0, 1)}

    bag, folder = results["bag"], results["folder"]
    print()
    print("| run | PSNR dB | PSNR kf dB | ATE cm | Gaussians | poses / frames | wall s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, r in results.items():
        print(f"| {name} | {_fmt(r['psnr_db'])} | {_fmt(r['psnr_kf_db'])} | {_fmt(r['ate_cm'])} | {r['gaussians']} | "
              f"{r['poses']} / {r['frames']} | {r['wall_s']} |")
    diffs: dict[str, float | None] = {}
    for key in ("psnr_db", "psnr_kf_db", "ate_cm"):
        a, b = bag[key], folder[key]
        diffs[key] = None if a is None or b is None else a - b
    print(f"bag - folder: PSNR {_fmt(diffs['psnr_db'], 3)} dB, PSNR kf {_fmt(diffs['psnr_kf_db'], 3)} dB, "
          f"ATE {_fmt(diffs['ate_cm'], 3)} cm")
    ok_psnr = diffs["psnr_db"] is not None and abs(diffs["psnr_db"]) <= PSNR_TARGET_DB
    ok_ate = diffs["ate_cm"] is not None and abs(diffs["ate_cm"]) <= ATE_TARGET_CM
    print(f"target PSNR within {PSNR_TARGET_DB} dB: {'met' if ok_psnr else 'MISSED'}; "
          f"ATE within {ATE_TARGET_CM} cm: {'met' if ok_ate else 'MISSED'}")
    from memgs_ros.evaluation.runs import write_json

    summary = out / "bench_calibration.json" if args.json is None else args.json
    write_json(summary, {"uptime_before": load, "argv": sys.argv[1:], "source": str(args.source),
                         "config": args.config, "camera_info_rewritten": n, "results": results,
                         "bag_minus_folder": diffs, "targets_met": {"psnr": ok_psnr, "ate": ok_ate}})
    print(f"wrote {summary}")
    return 0 if ok_psnr and ok_ate else 1


if __name__ == "__main__":
    sys.exit(main())
