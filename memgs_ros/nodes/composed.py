"""The mapping graph (merger, mapper, keyframe_sampler, tracker) as components of one process.

    ros2 run memgs_ros composed --ros-args --params-file config/realsense_d435i.yaml [-r __ns:=/uav1]
    ros2 launch memgs_ros memgs.launch.py composed:=true

The ROS 2 component way for a robot whose CPU and GPU share one memory (a Jetson): Python,
torch, numba, OpenCV and the ROS client libraries load once instead of four times. One
single-threaded executor runs every node's callbacks, none of which waits: the work runs on the
nodes' own threads (the tracker's back end, the mapper's session and its kernel threads). Each
node keeps its name, reads its own section of the params file and publishes and subscribes as
when alone; the mapper's and sampler's niceness then applies to their worker threads, not to the
process the tracker shares. ``memgs run --composed`` runs the same set in the runner's process.
"""
from __future__ import annotations

import importlib
import sys
from collections.abc import Callable

from rclpy.node import Node

from memgs_ros.nodes.registry import GRAPH, NODES
from memgs_ros.ros.node_main import run_nodes


def components() -> list[Callable[[], Node]]:
    """The graph's Node classes in the start order of ``registry.GRAPH`` (sinks first)."""
    out = []
    for name in GRAPH:
        module, cls = NODES[name]
        out.append(getattr(importlib.import_module(module), cls))
    return out


def main(args: list[str] | None = None) -> int:
    return run_nodes(components(), "composed", args)


if __name__ == "__main__":
    sys.exit(main())
