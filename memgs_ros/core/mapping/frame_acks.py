"""The mapper's lockstep acknowledgement, without ROS: when a replayed frame's training is queued
and when the player may have the frame's acknowledgement.

The tracker answers every frame it handled (``processed``); a keyframe's answer can come before
the keyframe's parts are all in. A frame's training is queued after its keyframe's insertion (the
session's one queue keeps that order), so a keyframe's frame waits until its bundle is complete
(inserted or refused). The acknowledgement then goes as the window allows (``LockstepAcks``).
"""
from __future__ import annotations

import functools
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from memgs_ros.core.mapping.lockstep import LockstepAcks

__all__ = ["LockstepAcknowledger"]


class LockstepAcknowledger:
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
        self._acks = LockstepAcks(window)
        self._train, self._hand_over, self._acknowledge, self._ack_ms = train, hand_over, acknowledge, ack_ms
        self._clock = clock
        self._awaiting: set[int] = set()  # keyframes announced, their bundle not yet complete
        self._announced_at: dict[int, float] = {}  # when the tracker's word on a frame came

    @property
    def awaiting(self) -> frozenset[int]:
        """Keyframe stamps whose frame waits for its bundle."""
        return frozenset(self._awaiting)

    def processed(self, stamp_ns: int, keyframe: bool, bundle_complete: bool) -> None:
        """The tracker handled frame ``stamp_ns`` (``keyframe``: it made one, whose bundle is
        ``bundle_complete`` or not yet): queue its training now, or once its bundle is in."""
        self._announced_at[stamp_ns] = self._clock()
        if keyframe and not bundle_complete:
            self._awaiting.add(stamp_ns)
            return
        self._queue(stamp_ns)

    def bundle_complete(self, stamp_ns: int) -> None:
        """Keyframe ``stamp_ns``'s bundle completed (its insertion is queued, or it was refused):
        the training of a frame that waited for it is queued after it."""
        if stamp_ns in self._awaiting:
            self._awaiting.discard(stamp_ns)
            self._queue(stamp_ns)

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
