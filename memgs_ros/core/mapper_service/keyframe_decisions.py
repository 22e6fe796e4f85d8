"""When the tracker decided on each keyframe, kept until the keyframe's parts are all in."""
from __future__ import annotations

__all__ = ["DecisionTimes"]


class DecisionTimes:
    """Keyframe stamp -> the tracker's decision on it (its pose's publication time on the
    tracker's wall clock, ns; 0 unknown), from which the keyframe's latency to its first training
    step counts. Taken when the keyframe's bundle completes; bounded: once more than ``limit``
    wait (poses whose bundle never completed), only the newest ``keep`` stay."""

    def __init__(self, limit: int = 64, keep: int = 32) -> None:
        self.limit, self.keep = limit, keep
        self._decided: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._decided)

    def decided(self, stamp_ns: int, decided_ns: int) -> None:
        """Keyframe ``stamp_ns``'s pose was published at ``decided_ns``."""
        self._decided[stamp_ns] = decided_ns

    def take(self, stamp_ns: int) -> int:
        """The decision time of a keyframe whose bundle completed (0 unknown); forgets it."""
        decided = self._decided.pop(stamp_ns, 0)
        if len(self._decided) > self.limit:
            self._decided = dict(list(self._decided.items())[-self.keep:])
        return decided
