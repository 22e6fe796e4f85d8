"""A lossy link for the map deltas, put beside a graph by tests and benchmarks (no node knows it).

The mapper publishes ``memgs/map/delta``; a merger whose ``delta_topic`` is :data:`LOSSY_DELTA_TOPIC`
reads what this relay forwards from it, minus every n-th message: loss on the link, as a radio
gives it. The merger must find the gap and resync from a snapshot (``nodes/merger/node.py``).
The relay forwards the serialized messages as they came (nothing decoded), on its own context.

    with lossy_deltas(domain_id, namespace, every=5) as relay:
        run_pipeline(RunOptions(..., overrides={**overrides, **LOSSY_MERGER}))
    relay.dropped  # deltas that never reached the merger
"""
from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import PointCloud2

from memgs_ros.orchestration.processes import spin_in_background, stop_spinning
from memgs_ros.ros import qos

__all__ = ["DELTA_TOPIC", "LOSSY_DELTA_TOPIC", "LOSSY_MERGER", "DeltaRelay", "lossy_deltas"]

DELTA_TOPIC = "memgs/map/delta"
LOSSY_DELTA_TOPIC = "memgs/map/delta_lossy"
LOSSY_MERGER = {"merger.delta_topic": LOSSY_DELTA_TOPIC}  # the override that puts the relay on the merger's input


class DeltaRelay:
    """Forwards ``DELTA_TOPIC`` to ``LOSSY_DELTA_TOPIC`` on ``node``, dropping every ``every``-th
    message (0: none). The counts are read from other threads: one lock, two integers."""

    def __init__(self, node: Any, every: int) -> None:
        if every < 0:
            raise ValueError(f"every must be >= 0, got {every}")
        self.every = every
        self.forwarded = 0
        self.dropped = 0
        self._lock = threading.Lock()
        # The merger's own QoS for deltas: reliable, so every loss is this relay's.
        self._pub = node.create_publisher(PointCloud2, LOSSY_DELTA_TOPIC, qos.reliable(50))
        node.create_subscription(PointCloud2, DELTA_TOPIC, self._on_delta, qos.reliable(50), raw=True)

    def readers(self) -> int:
        """Subscriptions matched to the lossy topic (the merger, once discovery has run)."""
        return self._pub.get_subscription_count()

    def _on_delta(self, raw: bytes) -> None:
        with self._lock:
            n = self.forwarded + self.dropped + 1
            drop = self.every > 0 and n % self.every == 0
            if drop:
                self.dropped += 1
            else:
                self.forwarded += 1
        if not drop:
            self._pub.publish(raw)


@contextmanager
def lossy_deltas(domain_id: int, namespace: str, every: int) -> Iterator[DeltaRelay]:
    """A :class:`DeltaRelay` in ``namespace`` on ``domain_id``, spinning on a thread of its own
    until the block ends. Start it before the graph: deltas sent before it subscribed are lost too."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    context = rclpy.Context()
    rclpy.init(args=["--ros-args", "-r", f"__ns:={ns}"], context=context, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=context)
    node = rclpy.create_node("memgs_delta_relay", context=context)
    thread = None
    try:
        relay = DeltaRelay(node, every)
        executor.add_node(node)
        thread = spin_in_background(executor)
        yield relay
    finally:
        stop_spinning(executor, thread)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
