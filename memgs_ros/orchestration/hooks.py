"""Public hooks for harnesses that start and watch the node graph their own way.

``run_pipeline`` starts the nodes, watches them and drives the run's end. A harness that must
place the nodes itself (``test/system/harness/bench_two_hosts.py`` runs the drone's nodes in one
network namespace and a ground station in another) repeats three of its steps; these are those
steps under names that stay, so the harness imports nothing private. Each takes the harness's own
watcher, which needs only the attributes of :class:`GraphWatcher` that the step names.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

from memgs_ros.core.maps.answers import MapAnswer
from memgs_ros.orchestration.pipeline import _compare_maps, _wait_for_graph

__all__ = ["GraphWatcher", "NodeChecker", "compare_maps", "parse_map_answer", "wait_for_graph"]


class NodeChecker(Protocol):
    def check(self) -> None:
        """Raise PipelineError (with the node's log) when a node process has ended."""


class GraphWatcher(Protocol):
    """What the steps read of a harness's watcher (``pipeline``'s own observer has all of it)."""

    node: Any  # an rclpy Node in the graph's namespace and domain (wait_for_graph, compare_maps)
    # "mapper" / "merger": the last PointCloud2 on memgs/mapper/snapshot / memgs/map/gaussians
    # (latched subscriptions the watcher keeps; compare_maps clears it first)
    maps: dict[str, Any]
    snapshot_client: Any  # Trigger client of memgs/mapper/publish_snapshot (compare_maps)
    publish_map_client: Any  # Trigger client of memgs/merger/publish_map (compare_maps)

    def call(self, client: Any, timeout_s: float) -> str:
        """Call a Trigger service and return its message; PipelineError when it fails."""


def wait_for_graph(watcher: GraphWatcher, procs: NodeChecker, nodes: Sequence[str], deadline: float) -> None:
    """Block until every node in ``nodes`` (graph node names) publishes the topic that says it is
    up, so the first frame reaches all of them; PipelineError past ``deadline`` (time.monotonic())."""
    _wait_for_graph(watcher, procs, list(nodes), deadline)  # type: ignore[arg-type]


def parse_map_answer(message: str) -> MapAnswer:
    """A map service's Trigger answer (the mapper's finish: seq, gaussians, epoch)."""
    return MapAnswer.parse(message)


def compare_maps(watcher: GraphWatcher, final_seq: int, epoch: int, deadline: float) -> tuple[bool, float]:
    """Have the mapper and the merger publish their whole maps, wait until both hold ``final_seq``
    of ``epoch`` and compare them: (identical within 1e-6, largest absolute difference; inf when
    their ids differ). PipelineError when they do not arrive by ``deadline`` (time.monotonic())."""
    return _compare_maps(watcher, final_seq, epoch, deadline)  # type: ignore[arg-type]
