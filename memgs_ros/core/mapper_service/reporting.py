"""How the mapper's ROS-free services report: the stats poster they are given (the node's
``NodeStats`` is one), which failed commands are worth a problem, and the training rate."""
from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol, TypeVar

from memgs_ros.core.runtime.stat_fields import Stat
from memgs_ros.core.runtime.worker import WorkerStopped

F = TypeVar("F")

__all__ = ["IterationRate", "StatsPoster", "report_failure", "reportable_error"]


class StatsPoster(Protocol):
    """Counters, gauges and problems posted from any thread (applied later, on the node's)."""

    def post_add(self, stat: Stat[int], n: int = 1) -> None: ...

    def post_set(self, stat: Stat[F], value: F) -> None: ...

    def post_problem(self, kind: str, message: str) -> None: ...


def reportable_error(future: Future[Any]) -> BaseException | None:
    """The error of a finished command, or None when it succeeded, was cancelled or met a stopped
    worker (the node is shutting down)."""
    err = None if future.cancelled() else future.exception()
    return None if isinstance(err, WorkerStopped) else err


def report_failure(posts: StatsPoster, command: str) -> Callable[[Future[Any]], None]:
    """A done-callback for a session command nobody waits on: its error reaches the stats
    (``problem.command_failed``) instead of vanishing with the future."""
    def done(future: Future[Any]) -> None:
        err = reportable_error(future)
        if err is not None:
            posts.post_problem("command_failed", f"{command} failed: {type(err).__name__}: {err}")
    return done


class IterationRate:
    """Training iterations per second between two readings: what the cores left the mapper (it
    runs niced below the tracker, so this falls while tracking needs the CPU and rises when it
    idles)."""

    def __init__(self, now_s: float) -> None:
        self._mark = (now_s, -1)  # (time, iteration) at the last reading; -1: none yet

    def update(self, now_s: float, iteration: int) -> float | None:
        """The rate since the last reading (None at the first, or when no time passed)."""
        last_t, last_it = self._mark
        rate = round((iteration - last_it) / (now_s - last_t), 1) if now_s > last_t and last_it >= 0 else None
        self._mark = (now_s, iteration)
        return rate
