"""The replay service, without ROS: how a replay's frames are paced, on both ends of the graph.

Two pacings (``Pacing``): live, where the player keeps the recorded rate (``RealTimeClock``) and
the graph drops what it cannot take, as from a camera; and lockstep, where the player sends the next
frame only once the mapper acknowledged this one, so a replay is deterministic and loses nothing.

The player's side: ``StartGate`` (when the first frame goes out), ``RealTimeClock``, ``AckWait``
(the acknowledgement awaited). The mapper's side: ``FrameAcknowledger`` (when a frame's training is
queued and acknowledged) over ``AckWindow`` (which frames may be acknowledged now). The nodes feed
these what they read from the ROS graph; times are seconds on one monotonic clock.

Why a window. A lockstep replay is deterministic because every frame's work reaches the mapping
session's one queue in a fixed order: a keyframe's insertion, then that frame's ``train`` command,
then the next frame's. Acknowledging a frame after its training had finished kept the tracker, the
sampler and the messages idle while the mapper trained, and the mapper idle while they worked.
With a window of W frames, frame j is acknowledged as soon as at most W frames' training (j's
included) is unfinished: with W = 1 the tracker works on frame j+1 while the mapper trains frame
j. The session's command order does not change (frame j's train command is queued before its
acknowledgement, so before anything frame j+1 causes), and neither does the map. W = 0 is the
old rule. Training commands finish in order (one queue), so the unfinished ones are the newest.

Why a keyframe's frame waits. The tracker answers every frame it handled (``processed``); a
keyframe's answer can come before the keyframe's parts are all in. A frame's training is queued
after its keyframe's insertion (the session's one queue keeps that order), so a keyframe's frame
waits until its bundle is complete (inserted or refused), and any frame for the keyframe-pose
messages the tracker names in its answer (refined, loop-corrected, culled: their own topics, in
no order with it), at most ``PART_WAIT_S``.
"""
from __future__ import annotations

import enum
import functools
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

__all__ = ["AckWait", "AckWindow", "FrameAcknowledger", "Pacing", "RealTimeClock", "StartGate"]


class Pacing(str, enum.Enum):
    """How a replay's frames go through the graph: the ``pacing`` parameter of the player and the
    mapper, set for both from one value by ``memgs run`` (``--realtime``: live)."""

    LIVE = "live"  # the recorded rate (x rate); the graph drops what it cannot take, as from a camera
    LOCKSTEP = "lockstep"  # each frame acknowledged before the next: deterministic, nothing dropped

    @property
    def acknowledged(self) -> bool:
        """Every frame waits for the mapper's acknowledgement: the player sends the next one after it,
        the mapper trains ``iterations_per_frame`` for it, and the tracker takes it however late."""
        return self is Pacing.LOCKSTEP

    @classmethod
    def choices(cls) -> tuple[str, ...]:
        return tuple(p.value for p in cls)


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


@dataclass
class _Frame:
    stamp_ns: int
    trained: Future[Any]
    acked: bool = False


class AckWindow:
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


_EARLY_KEPT = 256  # parts kept for frames the tracker has not yet announced
PART_WAIT_S = 5.0  # a frame waits this long for its pose messages, then trains without them


class FrameAcknowledger:
    """Queues each announced frame's training (``train()``, a session command) and calls
    ``acknowledge(stamp_ns)`` once the frame is due, then ``ack_ms(ms)`` with the time from the
    tracker's word on the frame to its acknowledgement.

    One thread calls it (the node's executor thread); a training command completes on the
    session's worker, so its completion comes back through ``hand_over(fn)``, which runs ``fn``
    on that one thread. ``clock``: seconds, for the acknowledgement times.
    """

    def __init__(self, window: int, train: Callable[[], Future[Any]],
                 hand_over: Callable[[Callable[[], None]], None], acknowledge: Callable[[int], None],
                 ack_ms: Callable[[float], None], clock: Callable[[], float] = time.perf_counter) -> None:
        self._acks = AckWindow(window)
        self._train, self._hand_over, self._acknowledge, self._ack_ms = train, hand_over, acknowledge, ack_ms
        self._clock = clock
        # Frames announced whose training waits for parts of the frame still on their way: "bundle"
        # (its keyframe's messages), or the keyframe poses the tracker sent with it ("refined",
        # "loop", "culled", on topics of their own: DDS keeps no order across topics).
        self._awaiting: dict[int, set[str]] = {}
        self._early: dict[int, set[str]] = {}  # parts that came before the tracker's word on their frame
        self._announced_at: dict[int, float] = {}  # when the tracker's word on a frame came

    @property
    def awaiting(self) -> frozenset[int]:
        """Stamps of frames whose training waits for a part."""
        return frozenset(self._awaiting)

    def processed(self, stamp_ns: int, keyframe: bool, bundle_complete: bool,
                  parts: frozenset[str] = frozenset()) -> None:
        """The tracker handled frame ``stamp_ns`` (``keyframe``: it made one, whose bundle is
        ``bundle_complete`` or not yet; ``parts``: the pose messages it sent with the frame): queue
        its training now, or once every part is in (its commands queued first: the map's order)."""
        self.expire_parts()
        self._announced_at[stamp_ns] = self._clock()
        waits = set(parts) - self._early.pop(stamp_ns, set())
        if keyframe and not bundle_complete:
            waits.add("bundle")
        if waits:
            self._awaiting[stamp_ns] = waits
            return
        self._queue(stamp_ns)

    def expire_parts(self) -> None:
        """Stop waiting for pose messages announced more than ``PART_WAIT_S`` ago (each frame's
        announcement runs this, and a timer for the last frame, which no announcement follows). A
        pose message that never comes (sent before this mapper subscribed: a restart) holds no frame
        longer; a keyframe's bundle is still waited for, as always."""
        now = self._clock()
        for old in [k for k in self._awaiting if now - self._announced_at.get(k, now) > PART_WAIT_S]:
            self._awaiting[old] &= {"bundle"}
            if not self._awaiting[old]:
                del self._awaiting[old]
                self._queue(old)

    def part_arrived(self, stamp_ns: int, part: str) -> None:
        """A part of frame ``stamp_ns`` arrived and its command is queued: the frame's training
        follows once nothing else is awaited."""
        waits = self._awaiting.get(stamp_ns)
        if waits is None:
            if part != "bundle":  # a complete bundle before the word is already counted as seen
                self._early.setdefault(stamp_ns, set()).add(part)
                while len(self._early) > _EARLY_KEPT:  # parts of frames no word will come for (a restart)
                    del self._early[next(iter(self._early))]
            return
        waits.discard(part)
        if not waits:
            del self._awaiting[stamp_ns]
            self._queue(stamp_ns)

    def bundle_complete(self, stamp_ns: int) -> None:
        """Keyframe ``stamp_ns``'s bundle completed (its insertion is queued, or it was refused)."""
        self.part_arrived(stamp_ns, "bundle")

    def _queue(self, stamp_ns: int) -> None:
        trained = self._train()
        trained.add_done_callback(lambda _f: self._hand_over(self._send_due))
        self._hand_over(functools.partial(self._send_due, (stamp_ns, trained)))

    def _send_due(self, queued: tuple[int, Future[Any]] | None = None) -> None:
        """Handed over (one thread touches the window): take a newly queued frame's training,
        then acknowledge what is due."""
        if queued is not None:
            self._acks.submitted(*queued)
        for stamp in self._acks.due():
            self._acknowledge(stamp)
            announced = self._announced_at.pop(stamp, None)
            if announced is not None:
                self._ack_ms((self._clock() - announced) * 1e3)
