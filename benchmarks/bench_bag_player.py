"""Benchmark: bag_player lockstep throughput over real DDS (player and acker in two processes).

The player runs in its own process and domain; this process subscribes to colour, depth,
camera info and ground truth (RELIABLE), decodes colour and depth with the package codecs,
and acks each stamp once all four messages are in. Throughput = (frames - 1) / (time from
the first colour arrival to the last ack). Inter-ack percentiles show stalls.

Frames: ``--frames random`` makes random RGB-D frames in the player process before it starts
(transport-bound); ``--source SPEC`` replays any source through
``python -m memgs_ros.nodes.bag_player.node`` (includes reading/rendering the source).

``--heartbeat-ms N`` (0 = Fast DDS default) writes a Fast DDS XML profile with that writer
heartbeat period and points FASTRTPS_DEFAULT_PROFILES_FILE at it in both processes: with
the default period (3 s) a lost fragment of a large message stalls the reader until the next
heartbeat. Prints a table and writes JSON (default results/bench_bag_player.json).

``--idle-s S``: instead, what a lockstep player waiting for an ack costs: its process's CPU per
wall second over S seconds, no frame going out (median of ``--repeats``).

    python benchmarks/bench_bag_player.py --frames random --n 100
    python benchmarks/bench_bag_player.py --frames random --n 100 --heartbeat-ms 50
    python benchmarks/bench_bag_player.py --source synthetic:w=640,h=480,n=60 --heartbeat-ms 50
    python benchmarks/bench_bag_player.py --idle-s 10
"""
from __future__ import annotations

import argparse
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import write_results

FASTDDS_XML = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="memgs_default_writer" is_default_profile="true">
    <times>
      <heartbeatPeriod><sec>0</sec><nanosec>{ns}</nanosec></heartbeatPeriod>
    </times>
  </data_writer>
</profiles>
"""


def serve_player(n: int, width: int, height: int) -> int:
    """The player process for --frames random: BagPlayer over pre-made frames."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from memgs_ros.core.geometry.camera import TUM_FR3
    from memgs_ros.core.geometry.frame import Frame
    from memgs_ros.nodes.bag_player.node import BagPlayer

    rng = np.random.default_rng(0)
    cam = TUM_FR3 if width == 640 else TUM_FR3.scaled(width / 640)
    rgb = [rng.integers(0, 256, (cam.height, cam.width, 3), dtype=np.uint8) for _ in range(4)]
    depth = [rng.uniform(0.3, 5.0, (cam.height, cam.width)).astype(np.float32) for _ in range(4)]
    frames = [Frame(10**18 + i * 33_333_333, rgb[i % 4], depth[i % 4], cam, np.eye(4)) for i in range(n)]
    rclpy.init(args=sys.argv)
    node = BagPlayer(frames)
    try:
        rclpy.spin_until_future_complete(node, node.finished)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run_once(cmd: list[str], env: dict[str, str], domain: int, timeout_s: float) -> dict[str, float]:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import Bool, Header

    from memgs_ros.io.image_decoding import decode_depth, decode_rgb
    from memgs_ros.ros import codecs, qos

    proc = subprocess.Popen(cmd, env=dict(env, ROS_DOMAIN_ID=str(domain)), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("bench_acker", context=ctx)
    ack = node.create_publisher(Header, "memgs/frame_ack", qos.reliable(10))
    parts: dict[int, set[str]] = {}
    first: list[float] = []
    acks: list[float] = []
    done: list[bool] = []

    def got(kind: str, msg: object) -> None:
        if kind == "color":
            decode_rgb(msg)
            if not first:
                first.append(time.perf_counter())
        elif kind == "depth":
            decode_depth(msg)
        p = parts.setdefault(codecs.stamp_to_ns(msg.header.stamp), set())
        p.add(kind)
        if len(p) == 4:
            ack.publish(Header(stamp=msg.header.stamp))
            acks.append(time.perf_counter())

    for kind, typ, topic in (("color", Image, "color/image_raw"), ("depth", Image, "depth/image_raw"),
                             ("info", CameraInfo, "color/camera_info"), ("gt", PoseStamped, "groundtruth/pose")):
        node.create_subscription(typ, topic, lambda m, k=kind: got(k, m), qos.reliable(10))
    node.create_subscription(Bool, "memgs/player/done", lambda m: done.append(m.data), qos.latched())
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        end = time.monotonic() + timeout_s
        while not done and time.monotonic() < end and proc.poll() is None:
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    if len(acks) < 2 or not first:
        raise RuntimeError(f"player delivered {len(acks)} frames (exit {proc.returncode}):\n{out[-3000:]}")
    gaps_ms = np.diff(acks) * 1e3
    return {
        "frames": len(acks),
        "fps": (len(acks) - 1) / (acks[-1] - first[0]),
        "gap_p50_ms": float(np.percentile(gaps_ms, 50)),
        "gap_p90_ms": float(np.percentile(gaps_ms, 90)),
        "gap_max_ms": float(gaps_ms.max()),
        "stalls_over_1s": int((gaps_ms > 1000).sum()),
    }


def idle_cpu_fraction(seconds: float, domain: int) -> float:
    """CPU seconds per wall second of a lockstep player (in this process) that has published
    nothing and waits: it has no reader, so only its timer wakes it."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from memgs_ros.nodes.bag_player.node import BagPlayer

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    executor = SingleThreadedExecutor(context=ctx)
    player = BagPlayer(context=ctx, parameter_overrides=[
        Parameter("source", value="synthetic:w=64,h=48,n=2"), Parameter("pacing", value="lockstep"),
        Parameter("start_delay_s", value=600.0)])
    try:
        executor.add_node(player)
        executor.spin_once(timeout_sec=0.1)
        t0, c0 = time.monotonic(), time.process_time()
        while time.monotonic() - t0 < seconds:
            executor.spin_once(timeout_sec=0.1)
        return (time.process_time() - c0) / (time.monotonic() - t0)
    finally:
        executor.shutdown()
        player.destroy_node()
        rclpy.try_shutdown(context=ctx)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--frames", choices=["random"], default="random")
    what.add_argument("--source", help="any source bag_player accepts, e.g. synthetic:w=640,h=480,n=60")
    parser.add_argument("--n", type=int, default=100, help="frames (--frames random)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--heartbeat-ms", type=float, default=0.0, help="Fast DDS writer heartbeat (0 = default)")
    parser.add_argument("--timeout-s", type=float, default=300.0)
    parser.add_argument("--out", type=Path, default=Path("results/bench_bag_player.json"))
    parser.add_argument("--idle-s", type=float, default=0.0, help="measure an idle lockstep player's CPU instead")
    parser.add_argument("--serve-player", action="store_true", help=argparse.SUPPRESS)
    args, _ = parser.parse_known_args()
    if args.serve_player:
        return serve_player(args.n, args.width, args.height)
    if args.idle_s > 0:
        fractions = [idle_cpu_fraction(args.idle_s, random.randrange(100, 200)) for _ in range(args.repeats)]
        print(f"idle lockstep player: {100 * statistics.median(fractions):.1f} % of a core "
              f"(runs: {', '.join(f'{100 * f:.1f}' for f in fractions)}; load {os.getloadavg()[0]:.1f})")
        return 0

    env = dict(os.environ, PYTHONUNBUFFERED="1")
    tmp = tempfile.TemporaryDirectory()
    if args.heartbeat_ms > 0:
        xml = Path(tmp.name) / "fastdds.xml"
        xml.write_text(FASTDDS_XML.format(ns=int(args.heartbeat_ms * 1e6)))
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(xml)
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(xml)  # this process's participant too
    common = ["--ros-args", "-p", "pacing:=lockstep", "-p", "start_delay_s:=60.0", "-p", "ack_timeout_s:=30.0"]
    if args.source:
        cmd = [sys.executable, "-m", "memgs_ros.nodes.bag_player.node", *common, "-p", f"source:={args.source}"]
        label = args.source
    else:
        cmd = [sys.executable, __file__, "--serve-player", "--n", str(args.n), "--width", str(args.width),
               "--height", str(args.height), *common]
        label = f"random {args.width}x{args.height} x{args.n}"
    load_before = os.getloadavg()[0]
    runs = []
    for r in range(args.repeats):
        res = run_once(cmd, env, random.randrange(100, 200), args.timeout_s)
        runs.append(res)
        print(f"run {r}: {res['frames']} frames, {res['fps']:.1f} frames/s, inter-ack p50 {res['gap_p50_ms']:.1f} "
              f"p90 {res['gap_p90_ms']:.1f} max {res['gap_max_ms']:.0f} ms, stalls > 1 s: {res['stalls_over_1s']}")
    load_after = os.getloadavg()[0]
    fps = statistics.median(r["fps"] for r in runs)
    hb = f"{args.heartbeat_ms:g} ms" if args.heartbeat_ms > 0 else "Fast DDS default"
    print(f"\n{'frames':34s} {'heartbeat':18s} {'median frames/s':>16s}")
    print(f"{label:34s} {hb:18s} {fps:16.1f}")
    print(f"load average before/after: {load_before:.1f} / {load_after:.1f} (2 shared cores)")
    write_results(args.out, {"frames": label, "heartbeat_ms": args.heartbeat_ms, "median_fps": fps,
                             "runs": runs, "load_before": load_before, "load_after": load_after})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
