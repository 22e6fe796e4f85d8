"""``memgs demo``: the main job on the embedded synthetic room, no download needed.

Generates a synthetic RGB-D sequence, writes it as a ROS 2 mcap bag, and replays the bag
through the full graph (separate processes over DDS), printing the run's summary.
"""
from __future__ import annotations

import argparse
import time

from memgs_ros.cli.run import add_graph_arguments, options_from_args, print_summary

HELP = "run the whole SLAM graph on the embedded synthetic sequence"
DEFAULT_SPEC = "synthetic:w=320,h=240,n=60,seed=0"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--spec", default=DEFAULT_SPEC, help="synthetic sequence spec (see memgs synth --help)")
    add_graph_arguments(p)


def run(args: argparse.Namespace) -> int:
    from memgs_ros.io.bag_writer import write_bag
    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.orchestration.pipeline import run_pipeline

    args.out.mkdir(parents=True, exist_ok=True)
    bag = args.out / "synthetic.mcap"
    options = options_from_args(args, str(bag))  # checks the arguments before the bag is written
    t0 = time.perf_counter()
    result = write_bag(generate_frames(parse_spec(args.spec)), bag)
    print(f"wrote {bag} ({result}) in {time.perf_counter() - t0:.1f} s")
    summary = run_pipeline(options)
    print_summary(summary, args.json, options.record)
    _print_trajectory_error(str(bag), summary.trajectory_path)
    return 0


def _print_trajectory_error(source: str, trajectory_path: str) -> None:
    """The synthetic room has exact ground truth: say how far the tracker was from it."""
    from memgs_ros.core.trajectory import ate
    from memgs_ros.io.sources import open_source
    from memgs_ros.io.tum import read_trajectory

    gt_stamps, gt_poses = open_source(source).ground_truth()
    est_stamps, est_poses = read_trajectory(trajectory_path)
    err = ate(est_stamps, est_poses, gt_stamps, gt_poses)
    print(f"ATE (SE(3)) {err.rmse_m * 100:.2f} cm RMSE over {err.n_matched} frames")
