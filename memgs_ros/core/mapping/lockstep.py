"""Lockstep acknowledgements with a window: which replayed frames may be acknowledged now.

A lockstep replay is deterministic because every frame's work reaches the mapping session's one
queue in a fixed order: a keyframe's insertion, then that frame's ``train`` command, then the
next frame's. The player sends the next frame only after an acknowledgement. Acknowledging a
frame after its training had finished kept the tracker, the sampler and the messages idle while
the mapper trained, and the mapper idle while they worked.

With a window of W frames, frame j is acknowledged as soon as at most W frames' training (j's
included) is unfinished: with W = 1 the tracker works on frame j+1 while the mapper trains frame
j. The session's command order does not change (frame j's train command is queued before its
acknowledgement, so before anything frame j+1 causes), and neither does the map. W = 0 is the
old rule. Training commands finish in order (one queue), so the unfinished ones are the newest.
"""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

__all__ = ["LockstepAcks"]


@dataclass
class _Frame:
    stamp_ns: int
    trained: Future[Any]
    acked: bool = False


class LockstepAcks:
    """Frames whose training was queued, in replay order; ``due()`` says which to acknowledge.
    Not thread-safe: one thread calls it (the mapper node's outgoing callback group)."""

    def __init__(self, window: int = 1) -> None:
        if window < 0:
            raise ValueError(f"the lockstep window must be >= 0 frames, got {window}")
        self.window = int(window)
        self._frames: deque[_Frame] = deque()

    def submitted(self, stamp_ns: int, trained: Future[Any]) -> None:
        """Frame ``stamp_ns``'s training was queued (``trained`` resolves when it has run)."""
        self._frames.append(_Frame(int(stamp_ns), trained))

    def due(self) -> list[int]:
        """Stamps to acknowledge now, oldest first; each is returned once. A frame whose training
        failed counts as finished (the replay goes on; the failure is reported elsewhere)."""
        out: list[int] = []
        unfinished = 0
        for f in self._frames:
            if not f.trained.done():
                unfinished += 1
            if not f.acked:
                if unfinished > self.window:
                    break
                f.acked = True
                out.append(f.stamp_ns)
        while self._frames and self._frames[0].acked and self._frames[0].trained.done():
            self._frames.popleft()
        return out

    @property
    def waiting(self) -> int:
        """Frames queued and not yet acknowledged."""
        return sum(not f.acked for f in self._frames)
