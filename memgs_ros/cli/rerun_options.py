"""The Rerun options of ``memgs run``, ``demo`` and ``eval`` (not a subcommand)."""
from __future__ import annotations

import argparse
from pathlib import Path

from memgs_ros.viz import RerunTarget


def add_rerun_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("Rerun view (needs the [viz] extra: pip install 'memgs_ros[viz]')")
    g.add_argument("--rerun", action="store_true",
                   help="stream the run live to a Rerun viewer: spawns one, or uses the one listening on port 9876")
    g.add_argument("--rerun-url", default="", metavar="URL",
                   help="stream the run live to the Rerun viewer at URL (rerun+http://HOST:9876/proxy)")
    g.add_argument("--rerun-save", type=Path, default=None, metavar="FILE.rrd",
                   help="record the run's Rerun view to this file (with or without a live viewer); "
                        "open it later with `rerun FILE.rrd`")


def rerun_target(args: argparse.Namespace) -> RerunTarget | None:
    """The target the options ask for, checked (ConfigError without rerun-sdk), or None."""
    if not (args.rerun or args.rerun_url or args.rerun_save):
        return None
    target = RerunTarget(spawn=bool(args.rerun), connect_url=args.rerun_url, save_path=args.rerun_save)
    target.check()
    return target
