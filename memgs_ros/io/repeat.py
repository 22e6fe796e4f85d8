"""A long flight made of a short one: any source played forward, backward, forward ... (``--repeat N``).

A drone flies over the same room again and again; a recording of one pass does not show what
that does to a map. :class:`RepeatedSource` plays a source ``passes`` times, every other pass in
reverse, on one continuous clock: pass p covers [t0 + p * span, t0 + (p + 1) * span], where t0
and t0 + span are the source's first and last frame stamps, so the camera turns round at each
end instead of jumping back. The turning frame is shown once (5 passes of 200 frames: 996
frames). Frames keep their images and ground-truth poses; ground truth (``ground_truth()``) is
re-stamped the same way, so every pass can be scored against it.

A source that can load a frame by index (:class:`~memgs_ros.io.tum.TumFolder`) is read again
on every pass, as a camera would deliver it; any other is kept in memory from its first pass.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from typing import Protocol, runtime_checkable

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import interpolate_poses
from memgs_ros.errors import ConfigError, DataError

__all__ = ["MAX_PASSES", "IndexedSource", "RepeatedSource", "pass_of", "repeat_stamps"]

MAX_PASSES = 1000


@runtime_checkable
class PlannedSource(Protocol):
    """A source that knows the stamps of the frames it will yield before reading them."""

    name: str

    @property
    def camera(self) -> PinholeCamera: ...

    def __iter__(self) -> Iterator[Frame]: ...

    def __len__(self) -> int: ...

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]: ...

    def frame_stamps(self) -> np.ndarray: ...


@runtime_checkable
class IndexedSource(PlannedSource, Protocol):
    """A planned source that also loads frame ``k`` of its plan alone (DataError: unreadable,
    counted in its ``skipped``; ``strict``: such a frame ends the replay)."""

    strict: bool

    def load(self, k: int) -> Frame: ...


def repeat_stamps(stamps_ns: np.ndarray,  # [N] the source's stamps, increasing
                  first_ns: int, last_ns: int, passes: int) -> list[np.ndarray]:
    """The stamps [N] of every pass (a list of ``passes`` arrays, in source order: pass 1 runs
    them backward) on the one clock of the module docstring; ``first_ns`` / ``last_ns`` are the
    source's first and last frame stamps."""
    s = np.asarray(stamps_ns, dtype=np.int64)
    span = int(last_ns) - int(first_ns)
    out = []
    for p in range(passes):
        out.append(s + p * span if p % 2 == 0 else (p + 1) * span + 2 * int(first_ns) - s)
    return out


def pass_of(stamps_ns: np.ndarray,  # [M] stamps on the repeated clock
            first_ns: int, last_ns: int, passes: int) -> np.ndarray:
    """[M] int: the pass (0-based) each stamp of the repeated clock falls in; a turning frame
    belongs to the pass it ends."""
    span = max(int(last_ns) - int(first_ns), 1)
    return np.clip((np.asarray(stamps_ns, np.int64) - int(first_ns) - 1) // span, 0, passes - 1)


class RepeatedSource:
    """``source`` played ``passes`` times, every other pass backward (module docstring).

    ``source`` must know its frame stamps up front (``frame_stamps()``: TUM folders, bags and the
    synthetic room do). ``skipped``: the frames skipped while reading, by kind (the source's own
    count, once per pass read).
    """

    def __init__(self, source: PlannedSource, passes: int) -> None:
        if not isinstance(passes, int) or not 1 <= passes <= MAX_PASSES:
            raise ConfigError(f"repeat must be an integer in [1, {MAX_PASSES}], got {passes!r}")
        if not isinstance(source, PlannedSource):
            raise ConfigError(f"{getattr(source, 'name', source)!r} cannot be repeated: it does not know its "
                              "frames' stamps before playing (TUM folders, bags and synthetic specs do)")
        self.source = source
        self.passes = passes
        self.name = source.name if passes == 1 else f"{source.name} x{passes} (forward and back)"
        self._stamps = np.asarray(source.frame_stamps(), dtype=np.int64)
        if len(self._stamps) == 0:
            raise DataError(f"{source.name}: no frames to repeat")
        self.first_ns, self.last_ns = int(self._stamps[0]), int(self._stamps[-1])

    @property
    def camera(self) -> PinholeCamera:
        return self.source.camera

    @property
    def skipped(self) -> dict[str, int]:
        return dict(getattr(self.source, "skipped", {}))

    def __len__(self) -> int:
        n = len(self._stamps)
        return n + (self.passes - 1) * (n - 1)

    def frame_stamps(self) -> np.ndarray:
        """[len(self)] the stamps the frames will carry, in playing order."""
        out = []
        for p, s in enumerate(repeat_stamps(self._stamps, self.first_ns, self.last_ns, self.passes)):
            order = s if p % 2 == 0 else s[::-1]
            out.append(order if p == 0 else order[1:])
        return np.concatenate(out)

    def pass_of(self, stamps_ns: np.ndarray) -> np.ndarray:
        """[M] the pass (0-based) of each stamp on this source's clock."""
        return pass_of(stamps_ns, self.first_ns, self.last_ns, self.passes)

    def _restamp(self, frame: Frame, p: int) -> Frame:
        s = int(frame.stamp_ns)
        span = self.last_ns - self.first_ns
        t = s + p * span if p % 2 == 0 else (p + 1) * span + 2 * self.first_ns - s
        return frame if t == s else replace(frame, stamp_ns=t)

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
            order = kept[::-1] if p % 2 else kept
            for frame in order[1:]:  # the turning frame was the last of the pass before
                yield self._restamp(frame, p)

    def _indexed(self, source: IndexedSource) -> Iterator[Frame]:
        n = len(self._stamps)
        for p in range(self.passes):
            ks = range(n) if p % 2 == 0 else range(n - 1, -1, -1)
            for j, k in enumerate(ks):
                if p > 0 and j == 0:
                    continue  # the turning frame was the last of the pass before
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
        stamps = np.concatenate(repeat_stamps(s, self.first_ns, self.last_ns, self.passes))
        poses = np.concatenate([T] * self.passes)
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0])  # a turning pose appears in two passes
        return stamps[keep], poses[keep]
