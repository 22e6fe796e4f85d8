"""Service calls whose answers nobody waits for: each reply still has an owner.

A node on a single-threaded executor must not block on a reply, and a future dropped unread is
where an error goes to disappear: :func:`call_trigger` hands every call a done-callback that
counts and logs a refusal or a failed call on the node's stats. :class:`PacedRequests` asks a
service for a full map when a :class:`RequestPacer` says so (the merger, the Rerun bridge).
"""
from __future__ import annotations

import time
from typing import Any

from rclpy.client import Client
from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger

from memgs_ros.core.map_io.follower import RequestPacer
from memgs_ros.core.runtime.stat_fields import Stat
from memgs_ros.ros.diagnostics import NodeStats

__all__ = ["PacedRequests", "call_trigger", "call_within"]


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


class PacedRequests:
    """Trigger requests to ``service``, sent when ``pacer`` says so and the service is up, counted
    as ``counter``; a refused or failed one is ``problem.<kind>`` ("``what``: why").
    ``one_at_a_time``: none goes while the last one is unanswered."""

    def __init__(self, node: Node, service: str, stats: NodeStats, pacer: RequestPacer, counter: Stat[int],
                 kind: str, what: str, one_at_a_time: bool = False) -> None:
        self.client = node.create_client(Trigger, service)
        self.pacer = pacer
        self._stats, self._counter, self._kind, self._what = stats, counter, kind, what
        self._one_at_a_time = one_at_a_time
        self._last: Future | None = None

    def ask(self, out_of_step: bool) -> None:
        """Send a request if one is due (see :meth:`RequestPacer.ask`)."""
        if self._one_at_a_time and self._last is not None and not self._last.done():
            return
        if self.client.service_is_ready() and self.pacer.ask(time.monotonic(), out_of_step):
            self._last = call_trigger(self.client, self._stats, self._kind, self._what)
            self._stats.post_add(self._counter)  # counted with the next stats message


async def call_within(node: Node, client: Client, request: Any, timeout_s: float) -> Any | None:
    """In a coroutine callback: the answer of ``client`` to ``request``, or None when none came
    within ``timeout_s`` (a one-shot timer cancels the call; the executor runs on meanwhile)."""
    future = client.call_async(request)
    timer = node.create_timer(timeout_s, future.cancel)
    try:
        return await future
    finally:
        timer.cancel()
        node.destroy_timer(timer)
