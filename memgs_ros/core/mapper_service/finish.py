"""The mapper's finish, without ROS: insert what is queued, stop training, run the final
iterations, flush every change, then the closing snapshot and a last checkpoint.

A receiver cannot see that the last delta was lost (no later seq shows the gap): the latched
snapshot after the flush lets every receiver end on the final map. It waits until the flush is
acknowledged: sent at once, the two whole maps would share a slow link, and the flush, which every
receiver in step needs, would arrive later. A receiver that died stays matched until its lease
runs out, so the wait is bounded (``FLUSH_ACK_TIMEOUT_S``): the snapshot goes anyway.
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from memgs_ros.core.map_io.answers import MapAnswer
from memgs_ros.core.runtime.worker import WorkerStopped
from memgs_ros.errors import DataError

if TYPE_CHECKING:
    from memgs_ros.core.mapper_service.session import MappingSession

__all__ = ["FLUSH_ACK_TIMEOUT_S", "FinalPlan", "FinishSteps", "finish_map"]

FLUSH_ACK_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class FinalPlan:
    """The final iterations (``MappingSession.finish``; the mapper's ``final_*`` parameters)."""

    iterations: int = 0
    densify: bool = True
    budget_s: float = 0.0
    total_iterations: int = 0


@dataclass(frozen=True)
class FinishSteps:
    """The node's side of the finish. ``flush()``: the exact delta, its future resolved once its
    messages are out; ``snapshot()``: the closing snapshot, its future giving (rows, Gaussians,
    seq); ``save()``: the last checkpoint (its errors are counted where it is written);
    ``receivers_acked()``: every receiver acknowledged what was sent; ``wait(future)`` and
    ``sleep(s)``: awaitables that do not hold the caller's event loop; ``log``: an info line."""

    flush: Callable[[], Future[Any]]
    snapshot: Callable[[], Future[tuple[Any, int, int]]]
    save: Callable[[], Future[Any]]
    receivers_acked: Callable[[], bool]
    wait: Callable[[Future[Any]], Awaitable[Any]]
    sleep: Callable[[float], Awaitable[None]]
    log: Callable[[str], None]


async def finish_map(session: MappingSession, plan: FinalPlan, steps: FinishSteps,
                     ack_timeout_s: float = FLUSH_ACK_TIMEOUT_S, clock: Callable[[], float] = time.monotonic) -> str:
    """Run the finish (module docstring); the answer (``MapAnswer``'s message) names the closing
    snapshot's seq, the map's size and its delta epoch."""
    done = await steps.wait(session.finish(plan.iterations, plan.densify, plan.budget_s, plan.total_iterations))
    steps.log(f"final {done.final_iterations} iterations in {done.seconds:.1f} s")
    await steps.wait(steps.flush())  # resolved after the flush's messages: they are out
    end = clock() + ack_timeout_s
    while not steps.receivers_acked() and clock() < end:
        await steps.sleep(0.02)
    _, _, seq = await steps.wait(steps.snapshot())
    with contextlib.suppress(OSError, DataError, WorkerStopped):  # counted as checkpoint_failed
        await steps.wait(steps.save())
    return MapAnswer(seq, session.status.gaussians, done.epoch).message()
