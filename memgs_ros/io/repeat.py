"""A long flight made of a short one: any source played forward, backward, forward ... (``--repeat N``).

A drone flies over the same room again and again; a recording of one pass does not show what
that does to a map. :class:`RepeatedSource` plays a source ``passes`` times, every other pass in
reverse, on one continuous clock: pass p covers [t0 + p * span, t0 + (p + 1) * span], where t0
and t0 + span are the source's first and last frame stamps, so the camera turns round at each
end instead of jumping back. The turning frame is shown once (5 passes of 200 frames: 996
frames). Frames keep their images and ground-truth poses; ground truth (``ground_truth()``) is
re-stamped the same way, so every pass can be scored against it (``RepeatClock``).

A backward pass of a recording shows each image as its camera took it: a rolling shutter read
its rows top to bottom in the recording's time, which runs backward there, so the pass reads them
bottom to top in the replay's. No camera flying that way would; the tracker notices on the frames
and corrects them the other way round (``core/tracking/frontend/readout.py``). ``forward_only``
plays every pass forward instead, the camera jumping back to the start between passes
(``--repeat-forward``); a global shutter (the synthetic room) is right either way.

A source that can load a frame by index (:class:`~memgs_ros.io.tum.TumFolder`) is read again
on every pass, as a camera would deliver it; any other is kept in memory from its first pass.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import interpolate_poses
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.frame_source import FrameSource

__all__ = ["MAX_PASSES", "IndexedSource", "RepeatClock", "RepeatedSource", "pass_of"]

MAX_PASSES = 1000
DEFAULT_GAP_NS = 33_333_333  # a one-frame source: 30 Hz


@runtime_checkable
class PlannedSource(FrameSource, Protocol):
    """A source that knows the stamps of the frames it will yield before reading them."""

    def frame_stamps(self) -> np.ndarray: ...


@runtime_checkable
class IndexedSource(PlannedSource, Protocol):
    """A planned source that also loads frame ``k`` of its plan alone (DataError: unreadable,
    counted in its ``skipped``; ``strict``: such a frame ends the replay)."""

    strict: bool

    def load(self, k: int) -> Frame: ...


@dataclass(frozen=True)
class RepeatClock:
    """The one clock of a repeated source: ``passes`` passes over source stamps ``first_ns`` ..
    ``last_ns``. Back and forth (``forward_only`` False): pass p covers [first + p span,
    first + (p + 1) span] (span = last - first), every other pass backward, the turning frame shown
    once. Forward only: every pass forward, each ``gap_ns`` (a frame period) after the last, the
    camera jumping back to its start between them."""

    first_ns: int
    last_ns: int
    passes: int
    forward_only: bool = False
    gap_ns: int = 0

    @property
    def period_ns(self) -> int:
        """Clock time from the start of one pass to the start of the next."""
        span = self.last_ns - self.first_ns
        return span + self.gap_ns if self.forward_only else span

    def backward(self, p: int) -> bool:
        return not self.forward_only and p % 2 == 1

    def stamp(self, s: np.ndarray | int, p: int) -> np.ndarray | int:
        """Source stamp(s) ``s`` as pass ``p`` shows them."""
        if self.backward(p):
            return (p + 1) * self.period_ns + 2 * self.first_ns - s
        return s + p * self.period_ns

    def skips_first(self, p: int) -> bool:
        """Whether pass ``p``'s first frame is left out (the turning frame, shown by the pass before)."""
        return p > 0 and not self.forward_only

    def pass_of(self, stamps_ns: np.ndarray) -> np.ndarray:
        """[M] int: the pass (0-based) each stamp falls in; a turning frame belongs to the pass it ends."""
        t = np.asarray(stamps_ns, np.int64) - self.first_ns
        period = max(self.period_ns, 1)
        p = t // period if self.forward_only else (t - 1) // period
        return np.clip(p, 0, self.passes - 1)


def pass_of(stamps_ns: np.ndarray,  # [M] stamps on the repeated clock
            first_ns: int, last_ns: int, passes: int) -> np.ndarray:
    """[M] int: the pass (0-based) of each stamp on the back-and-forth clock (``RepeatClock.pass_of``)."""
    return RepeatClock(int(first_ns), int(last_ns), int(passes)).pass_of(stamps_ns)


class RepeatedSource:
    """``source`` played ``passes`` times, every other pass backward, or every pass forward with
    ``forward_only`` (module docstring).

    ``source`` must know its frame stamps up front (``frame_stamps()``: TUM folders, bags and the
    synthetic room do). ``skipped``: the frames skipped while reading, by kind (the source's own
    count, once per pass read).
    """

    def __init__(self, source: PlannedSource, passes: int, forward_only: bool = False) -> None:
        if not isinstance(passes, int) or not 1 <= passes <= MAX_PASSES:
            raise ConfigError(f"repeat must be an integer in [1, {MAX_PASSES}], got {passes!r}")
        if not isinstance(source, PlannedSource):
            raise ConfigError(f"{getattr(source, 'name', source)!r} cannot be repeated: it does not know its "
                              "frames' stamps before playing (TUM folders, bags and synthetic specs do)")
        self.source = source
        self.passes = passes
        how = "forward" if forward_only else "forward and back"
        self.name = source.name if passes == 1 else f"{source.name} x{passes} ({how})"
        self._stamps = np.asarray(source.frame_stamps(), dtype=np.int64)
        if len(self._stamps) == 0:
            raise DataError(f"{source.name}: no frames to repeat")
        gaps = np.diff(self._stamps)
        self.clock = RepeatClock(int(self._stamps[0]), int(self._stamps[-1]), passes, forward_only,
                                 int(np.median(gaps)) if len(gaps) else DEFAULT_GAP_NS)
        self.first_ns, self.last_ns = self.clock.first_ns, self.clock.last_ns

    @property
    def camera(self) -> PinholeCamera:
        return self.source.camera

    @property
    def skipped(self) -> dict[str, int]:
        return dict(getattr(self.source, "skipped", {}))

    def __len__(self) -> int:
        n = len(self._stamps)
        return n * self.passes - sum(self.clock.skips_first(p) for p in range(self.passes))

    def _order(self, p: int) -> range:
        """Indices of the source's frames pass ``p`` shows, in order."""
        n = len(self._stamps)
        ks = range(n - 1, -1, -1) if self.clock.backward(p) else range(n)
        return ks[1:] if self.clock.skips_first(p) else ks

    def frame_stamps(self) -> np.ndarray:
        """[len(self)] the stamps the frames will carry, in playing order."""
        return np.concatenate([np.asarray(self.clock.stamp(self._stamps[list(self._order(p))], p))
                               for p in range(self.passes)])

    def pass_of(self, stamps_ns: np.ndarray) -> np.ndarray:
        """[M] the pass (0-based) of each stamp on this source's clock."""
        return self.clock.pass_of(stamps_ns)

    def _restamp(self, frame: Frame, p: int) -> Frame:
        t = int(self.clock.stamp(int(frame.stamp_ns), p))
        return frame if t == frame.stamp_ns else replace(frame, stamp_ns=t)

    def __iter__(self) -> Iterator[Frame]:
        if self.passes == 1:
            yield from self.source
            return
        if isinstance(self.source, IndexedSource):
            yield from self._indexed(self.source)
            return
        kept: list[Frame] = []
        for frame in self.source:
            kept.append(frame)
            yield frame
        for p in range(1, self.passes):
            order = kept[::-1] if self.clock.backward(p) else kept
            for frame in order[1:] if self.clock.skips_first(p) else order:
                yield self._restamp(frame, p)

    def _indexed(self, source: IndexedSource) -> Iterator[Frame]:
        for p in range(self.passes):
            for k in self._order(p):
                try:
                    frame = source.load(k)
                except DataError:
                    if source.strict:
                        raise
                    continue  # the source counted it in its ``skipped``
                yield self._restamp(frame, p)

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The source's ground truth on the repeated clock: (stamps_ns [M], T_wc [M, 4, 4]),
        its samples between the first and last frame re-stamped into every pass, plus the poses
        interpolated at those two frames (so the turning frames have theirs)."""
        gt_s, gt_T = self.source.ground_truth()
        if self.passes == 1 or len(gt_s) == 0:
            return gt_s, gt_T
        inside = (gt_s > self.first_ns) & (gt_s < self.last_ns)
        ends, valid = interpolate_poses(gt_s, gt_T, np.array([self.first_ns, self.last_ns], np.int64))
        s = np.concatenate([np.array([self.first_ns, self.last_ns], np.int64)[valid], gt_s[inside]])
        T = np.concatenate([ends[valid], gt_T[inside]])
        stamps = np.concatenate([np.asarray(self.clock.stamp(s, p)) for p in range(self.passes)])
        poses = np.concatenate([T] * self.passes)
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0])  # a turning pose appears in two passes
        return stamps[keep], poses[keep]
