"""Follow the mapper's map from its deltas: the merger's replica and the Rerun view's copy.

The deltas carry every change of the map, so a receiver keeps its own :class:`MapReplica` in step
with them and needs a full map (a mapper snapshot, the merger's ``memgs/map/gaussians``) only to
start late or to repair a gap. A view that asked for the full map every few seconds instead would
cost the sender its encoding and, on a robot's radio link, far more than the deltas' budget.

:class:`MapFollower` applies deltas and full maps and says what each delta did;
:class:`RequestPacer` decides when to ask again for a full map that may not come. Neither
imports ROS: the nodes translate messages and ask through their service clients.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from memgs_ros.core.map_io.map_delta import ApplyStatus, MapMessage, MapReplica, MessageKind

__all__ = ["DeltaOutcome", "MapFollower", "RequestPacer"]

_IN_STEP = (ApplyStatus.APPLIED, ApplyStatus.STALE)


@dataclass(frozen=True)
class DeltaOutcome:
    """What one delta did to the replica.

    status: the replica's answer, or None when the delta was held back (the follower waits for a
    full map). unknown_removals: ids the delta removed that the replica did not hold (ignored).
    """

    seq: int
    status: ApplyStatus | None
    unknown_removals: int = 0

    @property
    def lost_step(self) -> bool:
        """True when this delta put the replica out of step (a gap, a new epoch, a count mismatch,
        a late start): a full map must repair it."""
        return self.status is not None and self.status not in _IN_STEP


class MapFollower:
    """A :class:`MapReplica` kept in step by deltas and repaired by full maps.

    While out of step deltas are held back (at most ``max_buffered``, the oldest dropped first)
    until a full map arrives; those newer than it are then replayed on top of it.
    Not thread-safe: the owning node serialises calls.
    """

    def __init__(self, max_buffered: int = 200) -> None:
        self.replica = MapReplica()
        self.resyncing = False
        self._buffer: deque[MapMessage] = deque(maxlen=max_buffered)

    @property
    def version(self) -> tuple[int, int, int]:
        """(epoch, seq, Gaussians) of the replica: changes whenever the map does."""
        return self.replica.epoch, self.replica.seq, len(self.replica)

    @property
    def in_step(self) -> bool:
        """True when the replica is the sender's map as of its last delta."""
        return self.replica.synced and not self.resyncing

    @property
    def buffered(self) -> int:
        """Deltas held back until the next full map."""
        return len(self._buffer)

    def on_delta(self, msg: MapMessage) -> DeltaOutcome:
        """Apply a delta, or hold it back while out of step."""
        if self.resyncing:
            self._buffer.append(msg)
            return DeltaOutcome(msg.seq, None)
        unknown = self.replica.unknown_removals
        status = self.replica.apply(msg)
        outcome = DeltaOutcome(msg.seq, status, self.replica.unknown_removals - unknown)
        if outcome.lost_step:
            self.resyncing = True
            if status is not ApplyStatus.MISMATCH:  # a mismatched delta is already applied
                self._buffer.append(msg)
        return outcome

    def on_full_map(self, msg: MapMessage) -> tuple[DeltaOutcome, ...] | None:
        """Load a full map (a snapshot) and replay the held-back deltas newer than it; what each
        replayed delta did, or None when the map was not taken (not a snapshot, or older than the
        replica). A further gap among the replayed deltas holds the rest back again."""
        if msg.kind is not MessageKind.SNAPSHOT or self.replica.apply(msg) is not ApplyStatus.APPLIED:
            return None
        pending = sorted((d for d in self._buffer if d.epoch == self.replica.epoch and d.seq > self.replica.seq),
                         key=lambda d: d.seq)
        self._buffer.clear()
        self.resyncing = False
        return tuple(self.on_delta(d) for d in pending)


class RequestPacer:
    """When to ask (again) for a full map that may not come.

    Requests go at least ``interval_s`` apart; while unanswered the wait doubles up to
    ``max_backoff`` times (a snapshot is megabytes, and each request makes the mapper publish a
    new one into its one-deep latched history, replacing one still on its way: asking every second
    while a busy sender answers late could keep replacing it before it ever arrives whole).
    ``start_after_s``: a receiver started after the sender went quiet (finished, or idle) would
    wait for a delta that never comes, so it asks once this long after ``started_s`` unless a
    delta came first (None: never).
    Times are seconds on one monotonic clock, passed in by the caller.
    """

    def __init__(self, interval_s: float, max_backoff: int = 1, start_after_s: float | None = None,
                 started_s: float = 0.0) -> None:
        self.interval_s = interval_s
        self.max_backoff = max_backoff
        self._start_at = math.inf if start_after_s is None else started_s + start_after_s
        self._last = -math.inf
        self._unanswered = 0  # requests since the last answer (the backoff)

    def heard(self) -> None:
        """The stream is alive: no start-up request is needed any more."""
        self._start_at = math.inf

    def answered(self) -> None:
        """A full map arrived and was taken: the backoff starts over."""
        self._unanswered = 0

    def ask(self, now_s: float, out_of_step: bool) -> bool:
        """True when a request should go now (the caller sends it: recorded as sent)."""
        if out_of_step:
            wait = self.interval_s * min(2 ** self._unanswered, self.max_backoff)
            if now_s - self._last < wait:
                return False
            self._unanswered = min(self._unanswered + 1, 16)  # 2**16: past any backoff cap
        elif now_s <= self._start_at:
            return False
        self._start_at = math.inf
        self._last = now_s
        return True
