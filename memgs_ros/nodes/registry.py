"""Every node of the package, in one place: executable name -> (module, Node class).

Literals only, so that ``setup.py`` reads it without importing the package (console scripts),
and the launch file, the runner, the Rerun bridge and the parameter reference take their node
lists from here.
"""
from __future__ import annotations

NODES: dict[str, tuple[str, str]] = {
    "tracker": ("memgs_ros.nodes.tracker", "TrackerNode"),
    "keyframe_sampler": ("memgs_ros.nodes.keyframe_sampler", "KeyframeSamplerNode"),
    "mapper": ("memgs_ros.nodes.mapper", "MapperNode"),
    "merger": ("memgs_ros.nodes.merger", "MergerNode"),
    "bag_player": ("memgs_ros.nodes.bag_player", "BagPlayer"),
    "recorder": ("memgs_ros.nodes.recorder", "RecorderNode"),
    "rerun_bridge": ("memgs_ros.nodes.rerun_bridge", "RerunBridgeNode"),
}
# The mapping graph (what a robot runs), in the runner's start order: sinks first, so that
# nothing a source publishes is lost.
GRAPH: tuple[str, ...] = ("merger", "mapper", "keyframe_sampler", "tracker")
# Executables that run several nodes: name -> module (its ``main``).
COMPOSED: dict[str, str] = {"composed": "memgs_ros.nodes.composed"}
