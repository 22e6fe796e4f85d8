"""How often the mapper sends what it sends unasked, decided without ROS: the periodic map deltas
(one at a time, sized to the link's budget, none while a receiver lags or once the finish began)
and the live view (one render at a time, never the same view of the same map twice)."""
from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from memgs_ros.core.mapper_service.session_records import SessionStatus

__all__ = ["DeltaPacer", "LiveView", "delta_rows"]


def delta_rows(budget_kbytes_per_s: float, rate_hz: float, row_bytes: int) -> int:
    """Rows a periodic delta may carry: the link budget over the delta rate (at least one)."""
    return max(1, int(budget_kbytes_per_s * 1000.0 / rate_hz / row_bytes))


class DeltaPacer:
    """The periodic deltas. ``tick`` (a timer's) never waits for the session (it would starve the
    finish service): one periodic delta at a time, ``send(rows)`` queuing it; none while a receiver
    has not acknowledged the last (``receivers_acked()`` false: ``on_wait()``, counted by the node),
    so the next delta carries the map as it is then rather than queue deltas that newer ones
    outdate and that the final flush would wait behind (5 deltas, 4.5 s at 5 Mbit/s); none once
    ``finishing`` (the final flush carries every change: a periodic delta then only delays it).
    One thread calls it."""

    def __init__(self, rows: int, send: Callable[[int], Future[Any]], receivers_acked: Callable[[], bool],
                 on_wait: Callable[[], None]) -> None:
        self.rows = rows
        self._send, self._receivers_acked, self._on_wait = send, receivers_acked, on_wait
        self.pending: Future[Any] | None = None  # the periodic delta in flight (or the last one)
        self.finishing = False  # set once by the finish service, never cleared

    def tick(self) -> Future[Any] | None:
        """Queue the next periodic delta when one is due; the one in flight (None before any)."""
        if self.finishing:
            return self.pending
        if not self._receivers_acked():
            self._on_wait()
            return self.pending
        if self.pending is None or self.pending.done():
            self.pending = self._send(self.rows)
        return self.pending


class LiveView:
    """The live render at the latest tracked pose: a tick is skipped while the last render waits,
    and when neither the pose nor the map changed (the same view again is bytes for nothing: after
    the last frame it would share a slow link with the final flush, a 230 kB view a second: 37 %
    of 5 Mbit/s). One thread calls it."""

    def __init__(self) -> None:
        self._pending: Future[Any] | None = None
        self._last: tuple[int, ...] = ()  # the last live render's (pose stamp, map version)

    def due(self, stamp_ns: int, status: SessionStatus) -> bool:
        """Whether to render the pose of stamp ``stamp_ns`` of the map ``status`` describes now."""
        if self._pending is not None and not self._pending.done():
            return False
        key = (stamp_ns, status.iteration, status.gaussians, status.keyframes)
        if key == self._last:
            return False
        self._last = key
        return True

    def started(self, render: Future[Any]) -> None:
        """The render ``due`` allowed was queued."""
        self._pending = render
