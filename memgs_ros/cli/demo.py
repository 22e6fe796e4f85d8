"""``memgs demo``: the main job on the embedded synthetic room, no download needed.

Generates a synthetic RGB-D sequence, writes it as a ROS 2 mcap bag, and replays the bag
through the full graph (separate processes over DDS), printing the run's summary.
"""
from __future__ import annotations

import argparse
import time

from memgs_ros.cli.run import (
    add_graph_arguments,
    check_config,
    check_out_dir,
    options_from_args,
    print_summary,
    print_trajectory_error,
)

HELP = "run the whole SLAM graph on the embedded synthetic sequence"
DEFAULT_SPEC = "synthetic:w=320,h=240,n=60,seed=0"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--spec", default=DEFAULT_SPEC, help="synthetic sequence spec (see memgs synth --help)")
    add_graph_arguments(p)


def run(args: argparse.Namespace) -> int:
    from memgs_ros.io.bag_writer import write_bag
    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.orchestration.pipeline import run_pipeline

    spec = parse_spec(args.spec)
    options = options_from_args(args, str(args.out / "synthetic.mcap"))
    check_config(options.config, dict(options.overrides))  # before generating anything or starting a node
    check_out_dir(args.out)
    bag = args.out / "synthetic.mcap"
    t0 = time.perf_counter()
    result = write_bag(generate_frames(spec), bag)
    print(f"wrote {bag} ({result}) in {time.perf_counter() - t0:.1f} s")
    summary = run_pipeline(options)
    print_summary(summary, args.json, options.record)
    print_trajectory_error(str(bag), summary.trajectory_path)
    return 0

