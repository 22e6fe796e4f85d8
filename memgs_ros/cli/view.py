"""``memgs view``: show a saved map, its trajectory and keyframes in Rerun (the [viz] extra)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "show a saved map (map.ply, a run folder or a map bundle) with its trajectory and keyframes in Rerun"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("map", type=Path, metavar="MAP",
                   help="map.ply, or a run's output folder; trajectory.txt, keyframes.txt, params.yaml (camera) "
                        "and stats_timeline.jsonl beside it are used when present; or a map bundle (OUT/maps "
                        "for the latest): its map, keyframes and camera")
    p.add_argument("--trajectory", type=Path, default=None, metavar="TUM_FILE",
                   help="camera trajectory (TUM format; default: trajectory.txt beside the map)")
    p.add_argument("--keyframes", type=Path, default=None, metavar="TUM_FILE",
                   help="keyframe poses (TUM format; default: keyframes.txt beside the map)")
    p.add_argument("--save", type=Path, default=None, metavar="FILE.rrd",
                   help="write a Rerun recording instead of opening a viewer (open it with `rerun FILE.rrd`)")
    p.add_argument("--url", default="", metavar="URL",
                   help="send to the Rerun viewer at URL (rerun+http://HOST:9876/proxy) instead of spawning one")
    p.add_argument("--no-sh", action="store_true",
                   help="base colours only (the higher SH coefficients are 90 B a Gaussian)")


def run(args: argparse.Namespace) -> int:
    from memgs_ros.orchestration.saved_run import load_saved_run, log_saved_run
    from memgs_ros.viz import RerunTarget

    # No sink named: open a viewer, as `rerun map.ply` would.
    target = RerunTarget(spawn=not (args.save or args.url), connect_url=args.url, save_path=args.save)
    target.check()  # before reading a big map: rerun-sdk missing or no display is one line
    saved = load_saved_run(args.map, args.trajectory, args.keyframes)
    rec = target.open("memgs_ros", recording_name=str(saved.map_path))
    log_saved_run(rec, saved, sh=not args.no_sh)
    from memgs_ros.viz.rerun_log import finish  # imports rerun: after target.check()

    finish(rec, timeout_s=60.0)
    n_traj = 0 if saved.trajectory is None else len(saved.trajectory[0])
    n_kf = 0 if saved.keyframes is None else len(saved.keyframes[0])
    print(f"{saved.map_path}: {len(saved.records)} Gaussians, {n_traj} poses, {n_kf} keyframes, "
          f"{len(saved.stats)} stats rows")
    for key, path in saved.sources.items():
        if key != "map":
            print(f"  {key:<10} {path}")
    if args.save:
        print(f"wrote {args.save}")
    return 0
