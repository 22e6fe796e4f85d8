"""``memgs run``: replay a bag or TUM folder through the four nodes and save the map."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

from memgs_ros.errors import ConfigError, DataError
from memgs_ros.orchestration.run_files import RunOptions, RunSummary, build_params

HELP = "replay a bag, TUM folder or synthetic spec through tracker, sampler, mapper and merger"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bag", required=True, metavar="SOURCE",
                   help="ROS 2 bag (folder, .mcap, .db3), TUM ROS 1 .bag, TUM folder or 'synthetic:...' spec")
    add_graph_arguments(p)


def add_graph_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by ``run`` and ``demo``."""
    p.add_argument("--config", default=None, help="config name in config/ (tum_fr1, synthetic, ...) or a YAML path")
    p.add_argument("--out", type=Path, default=Path("memgs_out"), help="output folder (map.ply, trajectory, logs)")
    p.add_argument("--single-process", action="store_true",
                   help="run all nodes in this process on one multi-threaded executor")
    p.add_argument("--realtime", action="store_true",
                   help="replay at the recorded rate (frames may be dropped) instead of lockstep")
    p.add_argument("--rate", type=float, default=1.0, help="real-time factor with --realtime")
    p.add_argument("--namespace", default="", help="ROS namespace for every node (e.g. /uav1)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: a random free-ish one)")
    p.add_argument("--max-frames", type=int, default=0, help="stop after this many frames (0 = all)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                   help="override a node parameter, e.g. mapper.mapping.resolution_scale=0.25 (repeatable)")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds")
    p.add_argument("--json", type=Path, default=None, help="also write the summary as JSON here")
    p.add_argument("--kill", action="append", default=[], metavar="NODE@SECONDS",
                   help="fault injection: SIGKILL NODE (mapper, merger, ...) this many seconds after the "
                        "player starts and restart it at once (repeatable; separate processes only)")


def guess_config(source: str) -> str:
    s = source.lower()
    for fr in ("freiburg1", "freiburg2", "freiburg3"):
        if fr in s:
            return f"tum_fr{fr[-1]}"
    return "synthetic"


def options_from_args(args: argparse.Namespace, source: str) -> RunOptions:
    kills = {}
    for item in getattr(args, "kill", []):
        node, sep, after = item.partition("@")
        try:
            kills[node.strip()] = float(after)
        except ValueError:
            sep = ""
        if not sep:
            raise ConfigError(f"--kill needs NODE@SECONDS, got '{item}'")
    if not args.rate > 0 or not args.timeout > 0 or args.max_frames < 0:
        raise ConfigError(f"--rate and --timeout must be positive and --max-frames >= 0, got {args.rate}, "
                          f"{args.timeout}, {args.max_frames}")
    overrides = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--set needs NODE.PARAM=VALUE, got '{item}'")
        overrides[key.strip()] = yaml.safe_load(value)
    return RunOptions(
        source=source, config=args.config or guess_config(source), out_dir=args.out,
        single_process=args.single_process, lockstep=not args.realtime, rate=args.rate,
        namespace=args.namespace, domain_id=args.domain_id, max_frames=args.max_frames,
        overrides=overrides, timeout_s=args.timeout, kill_after_s=kills)


def check_inputs(source: str, config: str, max_frames: int = 0, overrides: dict | None = None,
                 out_dir: Path | None = None) -> None:
    """Fail before any node starts, with one line naming the file: the config must load, the
    overrides name real nodes, the source must open (a bag is scanned whole, so a truncated or
    corrupt one is found here rather than by the player in the middle of the run) and the output
    folder must be creatable."""
    from memgs_ros.io.sources import open_source  # opening a source loads the bag readers

    build_params(RunOptions(source=source, config=config, overrides=overrides or {}), Path("map.ply"))
    open_source(source, max_frames=max_frames or None)
    if out_dir is not None:
        if Path(out_dir).exists() and not Path(out_dir).is_dir():
            raise DataError(f"output folder {out_dir}: exists and is not a folder")
        try:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise DataError(f"output folder {out_dir}: {err.strerror or err}") from err


def print_summary(summary: RunSummary, json_path: Path | None) -> None:
    s = summary
    print(f"source        {s.source}")
    print(f"frames        {s.frames} in, {s.poses} poses, {s.lost_frames} lost")
    print(f"keyframes     {s.keyframes}")
    print(f"Gaussians     {s.gaussians}")
    print(f"tracking      {s.tracking_fps:.1f} FPS")
    print(f"map deltas    {s.delta_messages} messages, {s.delta_bytes / 1e6:.2f} MB, "
          f"{s.delta_bytes_per_s / 1e3:.1f} kB/s")
    if s.restarts:
        print(f"faults        restarted {s.restarts}; merger resyncs {s.merger_resyncs}; "
              f"merger == mapper: {s.replica_identical}")
    print(f"wall time     {s.wall_s:.1f} s")
    print(f"map           {s.ply_path}")
    print(f"trajectory    {s.trajectory_path}")
    if json_path is not None:
        json_path.write_text(json.dumps(s.as_dict(), indent=2))


def run(args: argparse.Namespace) -> int:
    # The runner imports every node (rclpy, torch): only when a run starts, not for `memgs --help`.
    from memgs_ros.orchestration.pipeline import run_pipeline

    options = options_from_args(args, args.bag)
    check_inputs(options.source, options.config, options.max_frames, dict(options.overrides), options.out_dir)
    summary = run_pipeline(options)
    print_summary(summary, args.json)
    if not summary.source_complete:
        print(f"memgs run: error: {options.source} failed part-way (see the bag_player log); the map and "
              "trajectory above hold the frames played", file=sys.stderr)
        return 1
    return 0
