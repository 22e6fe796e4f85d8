"""Work handed from other threads to a node's executor thread, and the waits of its coroutine
callbacks, which never hold the executor."""
from __future__ import annotations

import queue
from collections.abc import Callable
from concurrent.futures import Future
from typing import TypeVar

from rclpy.node import Node
from rclpy.task import Future as RclpyFuture
from rclpy.timer import Timer

__all__ = ["HandOver"]

T = TypeVar("T")


class HandOver:
    """Functions handed over from other threads (a mapping session's worker and outbox, which
    never call ROS themselves) run on ``node``'s executor thread, in the order handed over; a
    guard condition wakes the executor for them."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self._queue: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        self._ready = node.create_guard_condition(self._run)
        self._closed = False

    def __call__(self, fn: Callable[[], None]) -> None:
        """From any thread: run ``fn`` on the executor's thread."""
        self._queue.put(fn)
        self._ready.trigger()

    def close(self) -> None:
        """What is handed over from now on is dropped: the publishers it would use were made by a
        configuration that a lifecycle cleanup has since destroyed (a map loaded at run time)."""
        self._closed = True

    def _run(self) -> None:
        while True:
            try:
                fn = self._queue.get_nowait()
            except queue.Empty:
                return
            if not self._closed:
                fn()

    async def result(self, future: Future[T]) -> T:
        """Await a future of another thread in a coroutine callback without holding the executor:
        the future's completion is handed over, and the guard condition wakes the executor."""
        woken = RclpyFuture()
        future.add_done_callback(lambda _f: self(lambda: woken.set_result(None)))
        await woken
        return future.result(timeout=0)

    async def sleep(self, seconds: float) -> None:
        """Let a coroutine callback wait ``seconds`` on a one-shot timer of the node."""
        woken = RclpyFuture()
        timer: Timer | None = None

        def fire() -> None:
            assert timer is not None
            timer.cancel()
            self._node.destroy_timer(timer)
            woken.set_result(None)

        timer = self._node.create_timer(seconds, fire)
        await woken
