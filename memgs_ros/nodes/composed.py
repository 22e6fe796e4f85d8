"""The mapping graph (merger, mapper, keyframe_sampler, tracker) as components of one process.

    ros2 run memgs_ros composed [--param NODE:NAME:=VALUE ...] \
        --ros-args --params-file config/realsense_d435i.yaml [-r __ns:=/uav1]
    ros2 launch memgs_ros memgs.launch.py composed:=true

The ROS 2 component way for a robot whose CPU and GPU share one memory (a Jetson): Python,
torch, numba, OpenCV and the ROS client libraries load once instead of four times. One
single-threaded executor runs every node's callbacks, none of which waits: the work runs on the
nodes' own threads (the tracker's back end, the mapper's session and its kernel threads). Each
node keeps its name, reads its own section of the params file and publishes and subscribes as
when alone; the mapper's and sampler's niceness then applies to their worker threads, not to the
process the tracker shares. ``memgs run --composed`` runs the same set in the runner's process.

``--param NODE:NAME:=VALUE`` (before ``--ros-args``; the value is read as YAML, as ``-p`` reads
it) sets one node's parameter over the params file: ROS's own ``-p NODE:NAME:=VALUE`` does not
reach a node in a namespace, and a ``-p NAME:=VALUE`` would reach all four, which refuse a
parameter they do not declare. The launch file passes its camera topics and map path this way.
"""
from __future__ import annotations

import argparse
import functools
import importlib
import sys
from collections.abc import Callable, Sequence

import yaml
from rclpy.node import Node
from rclpy.parameter import Parameter

from memgs_ros.nodes.registry import GRAPH, NODES
from memgs_ros.ros.node_main import run_nodes


def components(overrides: dict[str, list[Parameter]] | None = None) -> list[Callable[[], Node]]:
    """The graph's Node classes in the start order of ``registry.GRAPH`` (sinks first), each with
    its own parameter overrides."""
    out: list[Callable[[], Node]] = []
    for name in GRAPH:
        module, cls = NODES[name]
        node_cls = getattr(importlib.import_module(module), cls)
        out.append(functools.partial(node_cls, parameter_overrides=list((overrides or {}).get(name, []))))
    return out


def parse_params(args: Sequence[str]) -> dict[str, list[Parameter]]:
    """``--param NODE:NAME:=VALUE`` options -> {node: [Parameter]}; SystemExit naming a bad one."""
    ap = argparse.ArgumentParser(prog="composed", description=__doc__.split("\n\n")[0])
    ap.add_argument("--param", action="append", default=[], metavar="NODE:NAME:=VALUE",
                    help="one node's parameter, over the params file (repeatable)")
    out: dict[str, list[Parameter]] = {}
    for item in ap.parse_args(list(args)).param:
        node, sep, rest = item.partition(":")
        name, eq, value = rest.partition(":=")
        if not (sep and eq and name) or node not in GRAPH:
            ap.error(f"--param {item!r}: expected NODE:NAME:=VALUE with NODE one of {', '.join(GRAPH)}")
        out.setdefault(node, []).append(Parameter(name, value=yaml.safe_load(value)))
    return out


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    own, ros = (argv[:argv.index("--ros-args")], argv[argv.index("--ros-args"):]) if "--ros-args" in argv \
        else (argv, [])
    return run_nodes(components(parse_params(own)), "composed", ros)


if __name__ == "__main__":
    sys.exit(main())
