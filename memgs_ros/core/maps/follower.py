"""Follow the mapper's map from its deltas, as the merger does, to show it without asking for it whole.

A view of the growing map needs the map every few seconds. Asking the merger for its full map
that often costs its encoding, a multi-megabyte message each time (to every subscriber of the
latched topic) and, on a robot's radio link, far more than the deltas' budget. The deltas
already carry every change: :class:`MapFollower` applies them to its own replica, and falls back
to a full map (the merger's ``memgs/map/gaussians``) only to start late or to repair a gap.
"""
from __future__ import annotations

from collections import deque

from memgs_ros.core.maps.map_delta import ApplyStatus, MapMessage, MapReplica, MessageKind

__all__ = ["MapFollower"]


class MapFollower:
    """A :class:`MapReplica` kept in step by deltas and repaired by full maps.

    While out of step (a gap, a new epoch, a count mismatch, a late start) deltas are buffered
    (at most ``max_buffered``) until a full map arrives; those newer than it are then replayed.
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

    def on_delta(self, msg: MapMessage) -> bool:
        """Apply a delta; True when the replica is out of step and needs a full map."""
        if self.resyncing:
            self._buffer.append(msg)
            return True
        status = self.replica.apply(msg)
        if status in (ApplyStatus.APPLIED, ApplyStatus.STALE):
            return False
        self.resyncing = True
        if status is not ApplyStatus.MISMATCH:  # a mismatched delta is already applied
            self._buffer.append(msg)
        return True

    def on_full_map(self, msg: MapMessage) -> bool:
        """Load a full map (a snapshot); True when it was taken (not older than the replica)."""
        if msg.kind is not MessageKind.SNAPSHOT or self.replica.apply(msg) is not ApplyStatus.APPLIED:
            return False
        pending = sorted((d for d in self._buffer if d.epoch == self.replica.epoch and d.seq > self.replica.seq),
                         key=lambda d: d.seq)
        self._buffer.clear()
        self.resyncing = False
        for d in pending:  # a further gap buffers the rest again and asks for another full map
            self.on_delta(d)
        return True
