"""When a replay's frames go out, without ROS: the start rule and the lockstep acknowledgement.

The bag player feeds these what it reads from the ROS graph (match counts, readers) and the
acknowledgements it receives; times are seconds on one monotonic clock, passed in by the caller.
"""
from __future__ import annotations

__all__ = ["AckWait", "RealTimeClock", "StartGate"]


class StartGate:
    """The first frame goes out once a color reader (and, in lockstep, an acknowledging publisher)
    has matched, every named reader is matched, and the match counts of all topics have been steady
    for ``settle_s`` (so a subscriber's depth and info readers, discovered a moment after its color
    reader, get the first frame too); or, whatever is missing, ``start_delay_s`` after ``created_s``.
    """

    def __init__(self, settle_s: float, start_delay_s: float, created_s: float, acker: str) -> None:
        self.settle_s = min(settle_s, start_delay_s)
        self.start_delay_s = start_delay_s
        self.created_s = created_s
        self.acker = acker  # names the acknowledging publisher in what is missing
        self._counts: tuple[int, ...] = ()
        self._steady_since = created_s

    def ready(self, now_s: float, counts: tuple[int, ...], has_acker: bool,
              unmatched: list[str]) -> tuple[bool, list[str]]:
        """(start now, what is missing when starting without it). ``counts``: subscription counts of
        the frame topics, color first; ``unmatched``: the named readers not matched yet."""
        has_reader = bool(counts) and counts[0] > 0
        if counts != self._counts:
            self._counts, self._steady_since = counts, now_s
        if has_reader and has_acker and not unmatched and now_s - self._steady_since >= self.settle_s:
            return True, []
        if now_s - self.created_s >= self.start_delay_s:
            missing = [] if has_reader else ["a color subscriber"]
            missing += [] if has_acker else [self.acker]
            return True, missing + unmatched
        return False, []


class AckWait:
    """Lockstep: the stamp of the frame whose acknowledgement the replay waits for, and the frames
    it went on without one (after ``timeout_s``)."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.awaiting_ns: int | None = None
        self.timeouts = 0
        self._sent_s = 0.0

    def sent(self, stamp_ns: int, now_s: float) -> None:
        self.awaiting_ns, self._sent_s = stamp_ns, now_s

    def ack(self, stamp_ns: int, now_s: float) -> float | None:
        """Seconds from publication to this acknowledgement; None when it is not for the frame
        awaited (a late or repeated one), which changes nothing."""
        if self.awaiting_ns is None or stamp_ns != self.awaiting_ns:
            return None
        self.awaiting_ns = None
        return now_s - self._sent_s

    def expire(self, now_s: float) -> int | None:
        """The stamp given up on when its acknowledgement is overdue (counted in ``timeouts``)."""
        if self.awaiting_ns is None or now_s - self._sent_s <= self.timeout_s:
            return None
        stamp, self.awaiting_ns = self.awaiting_ns, None
        self.timeouts += 1
        return stamp


class RealTimeClock:
    """Real-time pacing: the frame stamped ``stamp_ns`` goes out at start + (stamp_ns - first
    stamp) / ``rate``, never skipping frames (a slow machine just plays late)."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.t0: float | None = None  # when the first frame went out; None before the start
        self._stamp0_ns = 0

    def start(self, now_s: float, stamp0_ns: int) -> None:
        self.t0, self._stamp0_ns = now_s, stamp0_ns

    def due(self, stamp_ns: int) -> float:
        assert self.t0 is not None, "start() first"
        return self.t0 + (stamp_ns - self._stamp0_ns) * 1e-9 / self.rate
