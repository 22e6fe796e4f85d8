"""Which incoming frames the tracker takes, decided without ROS: the stamp rules, a live camera's
gate (frames lost in transport, frames before the kernels, stale frames) and the camera the
tracker runs with (the frames that wait for it). The tracker node answers every refused frame on its
``processed`` topic (a player awaiting acknowledgements goes on) and counts it under the kind named here.

Stamp rules (a frame's stamp is its colour image's):
- equal to the previous frame's: a duplicate delivery, refused (``stamp_duplicate``);
- up to ``jump_back_ns`` before the previous one: a late, out-of-order frame, refused
  (``stamp_order``): tracking cannot go back in time;
- more than ``jump_back_ns`` before it: a time reset (a bag replayed in a loop, a restarted sensor
  or sim clock): taken and reported (``time_jump_back``); the order starts again from it;
- more than ``max_ahead_ns`` ahead of the clock (when the clock runs): a broken sensor clock,
  refused (``stamp_future``), so one bad stamp cannot block the frames after it.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from memgs_ros.core.geometry.camera import PinholeCamera, calibration_differences

__all__ = ["CameraSource", "CameraWait", "InfoVerdict", "LiveGate", "StampRules", "StampVerdict"]

T = TypeVar("T")


@dataclass(frozen=True)
class StampVerdict:
    """take: the frame goes on; problem: the kind to count (None: nothing to say); message: its
    log line. A time reset is taken *and* reported."""

    take: bool
    problem: str | None = None
    message: str = ""


_TAKE = StampVerdict(True)


class StampRules:
    """The stamp rules of the module docstring over one stream of frames. ``check`` judges a
    stamp, ``took`` records the stamp of a frame that went on to tracking (a frame refused later,
    e.g. an unreadable image, does not move the order)."""

    def __init__(self, jump_back_ns: int, max_ahead_ns: int) -> None:
        self.jump_back_ns = int(jump_back_ns)
        self.max_ahead_ns = int(max_ahead_ns)
        self.last_ns = -1  # the last stamp taken; -1: none yet

    def check(self, stamp_ns: int, now_ns: int) -> StampVerdict:
        """The verdict on ``stamp_ns`` with the node's clock at ``now_ns`` (<= 0: not running)."""
        if self.max_ahead_ns and now_ns > 0 and stamp_ns - now_ns > self.max_ahead_ns:
            return StampVerdict(False, "stamp_future", f"frame stamp {stamp_ns} is {(stamp_ns - now_ns) * 1e-9:.0f} s "
                                                       "ahead of the clock: dropped (sensor clock wrong?)")
        last = self.last_ns
        if last < 0 or stamp_ns > last:
            return _TAKE
        if stamp_ns == last:
            return StampVerdict(False, "stamp_duplicate", f"frame stamp {stamp_ns} came twice: the copy is dropped")
        if last - stamp_ns <= self.jump_back_ns:
            return StampVerdict(False, "stamp_order", f"frame stamp {stamp_ns} is {(last - stamp_ns) * 1e-6:.1f} ms "
                                                      "before the previous frame: dropped (late, out of order)")
        return StampVerdict(True, "time_jump_back", f"time jumped back {(last - stamp_ns) * 1e-9:.1f} s (bag loop or "
                                                    f"clock reset): tracking goes on from stamp {stamp_ns}, "
                                                    "relocalising in the map")

    def took(self, stamp_ns: int) -> None:
        self.last_ns = int(stamp_ns)


class LiveGate:
    """A live camera's colour frames as they reach the node (``max_age_ns`` 0: an acknowledged replay,
    where every frame is taken and nothing is counted).

    ``admit`` counts the frames the camera published that never arrived (the reader's queue
    overflowed while the tracker was busy, or best-effort transport lost them: a gap in the
    publisher's sequence numbers) and refuses a frame that came before the kernels were in
    (``warming``: waiting for them would make it and the frames behind it stale anyway) or one
    that waited ``max_age_ns`` longer than the least wait seen (``stale``; relative to the least
    wait, so immune to an offset between the camera's clock and the robot's).
    """

    def __init__(self, max_age_ns: int) -> None:
        self.max_age_ns = int(max_age_ns)
        self._last_seq = 0  # the publisher's sequence number last seen (0 = none yet)
        self._least_wait_ns: int | None = None

    def admit(self, seq: int, sent_ns: int, now_ns: int, warm: bool) -> tuple[str | None, int]:
        """(None to take the frame, else "warming" or "stale"; frames lost before it).

        seq: the publisher's sequence number (0: unknown); sent_ns: its publication time on the
        publisher's clock (0: unknown); now_ns: this node's wall clock; warm: the kernels are in."""
        lost = 0
        if seq and self._last_seq and seq > self._last_seq + 1:
            lost = seq - self._last_seq - 1
        if seq:
            self._last_seq = seq  # a smaller one: the publisher restarted; count from it
        if not self.max_age_ns:
            return None, lost
        if not warm:
            return "warming", lost
        if not sent_ns:
            return None, lost
        wait = now_ns - sent_ns
        self._least_wait_ns = wait if self._least_wait_ns is None else min(self._least_wait_ns, wait)
        return (None if wait - self._least_wait_ns <= self.max_age_ns else "stale"), lost


class CameraWait(Generic[T]):
    """Frames that arrive before the first camera calibration (camera topics race at start): at
    most ``maxlen`` wait; ``add`` returns the oldest one it pushed out (to be answered as dropped)."""

    def __init__(self, maxlen: int = 5) -> None:
        self._frames: deque[T] = deque()
        self.maxlen = maxlen

    def __len__(self) -> int:
        return len(self._frames)

    def add(self, frame: T) -> T | None:
        dropped = self._frames.popleft() if len(self._frames) == self.maxlen else None
        self._frames.append(frame)
        return dropped

    def drain(self) -> list[T]:
        """Every waiting frame, oldest first; the wait is empty after."""
        out = list(self._frames)
        self._frames.clear()
        return out


@dataclass(frozen=True)
class InfoVerdict(Generic[T]):
    """What a camera_info meant. kind: "set" (the tracker's camera is now this one: track the
    ``released`` frames that waited for it), "changed" (it differs from the camera in use, which
    is kept), "differs" (override mode, the first camera_info: ``differences`` from the configured
    calibration beyond 1 %) or "" (nothing to do)."""

    kind: str
    released: list[T] = field(default_factory=list)
    differences: list[str] = field(default_factory=list)


class CameraSource(Generic[T]):
    """The camera a tracker runs with. Without a ``calibration`` it is the first valid
    camera_info's, and the frames before it wait (``waiting``). With one (camera_info_override) it
    is the calibration fitted to the first frame's size; camera_info is then only compared with it,
    once. ``camera`` is None until known."""

    def __init__(self, calibration: PinholeCamera | None, wait: int = 5) -> None:
        self.calibration = calibration
        self.camera: PinholeCamera | None = None
        self.waiting: CameraWait[T] = CameraWait(wait)
        self._compared = False

    def info(self, cam: PinholeCamera) -> InfoVerdict[T]:
        """A decoded camera_info (see :class:`InfoVerdict`)."""
        if self.calibration is not None:
            if self._compared:
                return InfoVerdict("")
            self._compared = True
            diffs = calibration_differences(cam, self.calibration)
            return InfoVerdict("differs" if diffs else "", differences=diffs)
        if self.camera is None:
            self.camera = cam
            return InfoVerdict("set", released=self.waiting.drain())
        return InfoVerdict("changed" if cam != self.camera else "")

    def for_frame(self, frame: T, width: int, height: int) -> tuple[bool, T | None]:
        """Whether the camera is known for a frame of ``width`` x ``height`` (override mode: the
        calibration fitted to it on the first frame); else the frame waits, and the one it pushed
        out of the wait is returned (to be answered as dropped). DataError when the calibration does
        not fit the frame's size."""
        if self.camera is not None:
            return True, None
        if self.calibration is None:
            return False, self.waiting.add(frame)
        self.camera = self.calibration.fitted(int(width), int(height))  # DataError: another aspect ratio
        return True, None

