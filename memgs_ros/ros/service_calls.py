"""Service calls whose answers nobody waits for: each reply still has an owner.

A node on a single-threaded executor must not block on a reply, and a future dropped unread is
where an error goes to disappear: :func:`call_trigger` hands every call a done-callback that
counts and logs a refusal or a failed call on the node's stats.
"""
from __future__ import annotations

from rclpy.client import Client
from rclpy.task import Future
from std_srvs.srv import Trigger

from memgs_ros.ros.diagnostics import NodeStats

__all__ = ["call_trigger"]


def call_trigger(client: Client, stats: NodeStats, kind: str, what: str) -> Future:
    """Call the std_srvs/Trigger service of ``client`` without waiting; a refusal (``success``
    False) or a failed call is counted as ``problem.<kind>`` and logged once as "``what``: why".
    Returns the call's future (for a caller that keeps one request at a time)."""
    def answered(future: Future) -> None:
        try:  # rclpy's result() never waits: it returns what was set (None when cancelled) or raises
            res = future.result()
        except Exception as err:  # noqa: BLE001 - counted and logged below
            why = f"{type(err).__name__}: {err}"
        else:
            if res is None or res.success:
                return
            why = res.message
        stats.problem(kind, f"{what}: {why}")

    future = client.call_async(Trigger.Request())
    future.add_done_callback(answered)
    return future
