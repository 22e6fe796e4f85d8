"""Every node of the package, in one place: executable name -> (module, Node class).

Literals only, so that ``setup.py`` reads it without importing the package (console scripts),
and the launch file, the runner, the Rerun bridge and the parameter reference take their node
lists from here.
"""
from __future__ import annotations

NODES: dict[str, tuple[str, str]] = {
    "tracker": ("memgs_ros.nodes.tracker.node", "TrackerNode"),
    "keyframe_sampler": ("memgs_ros.nodes.keyframe_sampler.node", "KeyframeSamplerNode"),
    "mapper": ("memgs_ros.nodes.mapper.node", "MapperNode"),
    "merger": ("memgs_ros.nodes.merger.node", "MergerNode"),
    "bag_player": ("memgs_ros.nodes.bag_player.node", "BagPlayer"),
    "recorder": ("memgs_ros.nodes.recorder.node", "RecorderNode"),
    "rerun_bridge": ("memgs_ros.nodes.rerun_bridge.node", "RerunBridgeNode"),
}
# The mapping graph (what a robot runs), in the runner's start order: sinks first, so that
# nothing a source publishes is lost.
GRAPH: tuple[str, ...] = ("merger", "mapper", "keyframe_sampler", "tracker")
# Executables that run several nodes: name -> module (its ``main``).
COMPOSED: dict[str, str] = {"composed": "memgs_ros.nodes.composed"}


def node_name(module: str) -> str:
    """The node a module belongs to: ``memgs_ros.nodes.<name>.node`` (or any module of that
    node's package) -> ``<name>``."""
    parts = module.split(".")
    if len(parts) < 3 or parts[:2] != ["memgs_ros", "nodes"]:
        raise ValueError(f"{module} is not a node's module")
    return parts[2]
