"""A replay's frames without ROS: the order, loops and skips the bag player publishes them in.

:class:`ReplayFeed` hands out the next good frame with its replay stamp (shifted by whole loops,
so stamps never go backwards), skipping and counting frames that would break the nodes (a stamp
going backwards, a camera changed); :class:`Preloaded` decodes a source into memory up front.
"""
from __future__ import annotations

import time
from collections.abc import Iterable, Iterator

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.errors import ConfigError, MemgsError
from memgs_ros.io.skips import SkipLog

__all__ = ["DEFAULT_PERIOD_NS", "Preloaded", "ReplayFeed", "frames_total", "open_frames", "replay_frames"]

DEFAULT_PERIOD_NS = 33_333_333  # loop gap for a one-frame source (30 Hz)


def open_frames(spec: str, folder_camera: PinholeCamera | None, strict: bool, bag_topics: str = "") -> Iterable[Frame]:
    """The source ``spec`` names (a TUM folder, a bag, ``synthetic:...``), checked before the first
    frame: ConfigError when empty, and a TUM folder that names no camera (nor has ``folder_camera``)
    fails here. ``bag_topics``: ``BagTopics.parse``'s text."""
    if not spec:
        raise ConfigError("parameter 'source' is empty: give a TUM folder, bag or 'synthetic:...' spec")
    from memgs_ros.io.bag_reader import BagTopics  # heavy readers only when replaying files
    from memgs_ros.io.sources import open_source

    # A TUM folder's depth PNGs as stored: a 16UC1 replay publishes them unchanged (FrameOutbox).
    source = open_source(spec, default_camera=folder_camera, strict=strict, raw_depth=True,
                         topics=BagTopics.parse(bag_topics))
    _ = source.camera
    return source


def replay_frames(frames: Iterable[Frame], preload_mb: int, max_frames: int, loop: bool, repeat: int,
                  repeat_forward: bool) -> tuple[Iterable[Frame], str]:
    """What a player replays of ``frames``: decoded up front when ``preload_mb`` > 0 (``Preloaded``;
    up to ``max_frames`` unless looping or repeating, where it counts the frames played), then
    played ``repeat`` times (``RepeatedSource``: after preloading, the passes share its frames).
    Returns the frames and a line saying which topics of a bag were found by type and what was
    preloaded ("" when neither)."""
    from memgs_ros.io.repeat import RepeatedSource

    note = getattr(frames, "topic_choice", "")  # a bag whose topics were found by type
    if preload_mb > 0:
        t0 = time.monotonic()
        frames = Preloaded(frames, preload_mb, 0 if loop or repeat > 1 else max_frames)
        note += ("; " if note else "") + (f"preloaded {len(frames)} frames ({frames.nbytes / 1e6:.0f} MB) in "
                                          f"{time.monotonic() - t0:.1f} s")
    if repeat > 1:
        frames = RepeatedSource(frames, repeat, repeat_forward)  # type: ignore[arg-type]
    return frames, note


class ReplayFeed:
    """The frames of ``source`` in replay order: ``next()`` gives the next good frame and its replay
    stamp (ns), or None at the end (after ``max_frames`` when > 0).

    With ``loop`` the source is read again at its end, each pass shifted by its length plus one
    frame period. A frame whose stamp does not follow the last one of its pass, or whose camera is
    not the first frame's (the nodes keep one calibration), is skipped and counted
    (``skipped()``); with ``strict`` it raises DataError instead, as does a read error.
    """

    def __init__(self, source: Iterable[Frame], loop: bool = False, max_frames: int = 0, strict: bool = False) -> None:
        self.source = source
        self._loop, self._max_frames = loop, max_frames
        self._skips = SkipLog("bag_player", strict)  # the source counts its own skips
        self._it: Iterator[Frame] = iter(source)
        self._first_camera: PinholeCamera | None = None
        self._loop_offset_ns = 0
        self._first_src_ns: int | None = None  # first / last source stamp of the current pass
        self._last_src_ns: int | None = None
        self._period_ns = DEFAULT_PERIOD_NS
        self._handed = 0  # frames handed out so far

    def skipped(self) -> dict[str, int]:
        """Frames skipped so far (by the source and here), by kind."""
        return {**getattr(self.source, "skipped", {}), **self._skips.counts}

    def next(self) -> tuple[Frame, int] | None:
        """The next good frame and its replay stamp; None at the end. Raises MemgsError when the
        source cannot be read (or, with ``strict``, holds a bad frame)."""
        if self._max_frames and self._handed >= self._max_frames:
            return None
        while True:
            frame = next(self._it, None)
            if frame is None and self._loop and self._first_src_ns is not None:
                self._start_pass()
                frame = next(self._it, None)
            if frame is None:
                return None
            problem = self._bad_frame(frame)
            if problem is None:
                break
            self._skips.skip(*problem)
        if self._first_src_ns is None:
            self._first_src_ns = frame.stamp_ns
        elif self._last_src_ns is not None and frame.stamp_ns > self._last_src_ns and self._handed < 2:
            self._period_ns = frame.stamp_ns - self._last_src_ns
        self._last_src_ns = frame.stamp_ns
        self._handed += 1
        return frame, frame.stamp_ns + self._loop_offset_ns

    def _start_pass(self) -> None:
        assert self._first_src_ns is not None
        span = (self._last_src_ns or self._first_src_ns) - self._first_src_ns
        self._loop_offset_ns += span + self._period_ns
        self._first_src_ns = self._last_src_ns = None
        self._it = iter(self.source)

    def _bad_frame(self, frame: Frame) -> tuple[str, str] | None:
        """(kind, detail) when ``frame`` must be skipped."""
        if self._last_src_ns is not None and frame.stamp_ns <= self._last_src_ns:
            return "stamp_backwards", f"{frame.stamp_ns} after {self._last_src_ns}"
        if self._first_camera is None:
            self._first_camera = frame.camera
        elif frame.camera != self._first_camera:
            return "camera_changed", f"{frame.camera} (first frame: {self._first_camera})"
        return None


class Preloaded:
    """The frames of ``source`` decoded into memory up front, so that a replay only publishes (a
    camera's cost, not a file decoder's). Iterates like the source: a read error met while
    preloading is raised where it happened, after the frames read before it.

    Raises ConfigError when the frames need more than ``budget_mb``; ``max_frames`` > 0 stops
    reading there. Knows its frames' stamps (``frame_stamps``), so a replay can repeat the
    preloaded frames (:class:`~memgs_ros.io.repeat.RepeatedSource`) without holding them twice.
    """

    def __init__(self, source: Iterable[Frame], budget_mb: int, max_frames: int = 0) -> None:
        self._source = source
        self.frames: list[Frame] = []
        self.nbytes = 0
        self.error: MemgsError | None = None
        seen: set[int] = set()  # a lap shown again (synthetic laps) holds its images once
        try:
            for frame in source:
                if id(frame.rgb) not in seen:
                    seen.add(id(frame.rgb))
                    depth = frame.depth_m
                    self.nbytes += frame.rgb.nbytes + (0 if depth is None else depth.raw.nbytes
                                                       if isinstance(depth, DepthUnits) else depth.nbytes)
                if self.nbytes > budget_mb * 1e6:
                    raise ConfigError(f"the source does not fit preload_mb={budget_mb} MB ({len(self.frames)} "
                                      "frames did): raise preload_mb, or set it to 0 to decode frames as they go out")
                self.frames.append(frame)
                if max_frames and len(self.frames) >= max_frames:
                    break
        except ConfigError:
            raise
        except MemgsError as err:  # a strict source's bad frame: the replay fails there, as without preloading
            self.error = err

    @property
    def skipped(self) -> dict[str, int]:
        """The source's own count of skipped bad frames, by kind."""
        return dict(getattr(self._source, "skipped", {}))

    @property
    def name(self) -> str:
        return str(getattr(self._source, "name", "preloaded frames"))

    @property
    def camera(self) -> PinholeCamera:
        if not self.frames:
            raise ConfigError(f"{self.name}: no frames preloaded")
        return self.frames[0].camera

    def frame_stamps(self) -> np.ndarray:
        """[N] int64 the stamps of the preloaded frames, in order."""
        return np.array([f.stamp_ns for f in self.frames], dtype=np.int64)

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The source's ground truth (none when it offers none)."""
        gt = getattr(self._source, "ground_truth", None)
        return gt() if gt is not None else (np.zeros(0, np.int64), np.zeros((0, 4, 4)))

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        yield from self.frames
        if self.error is not None:
            raise self.error


def frames_total(frames: Iterable[Frame], max_frames: int) -> int:
    """len(frames) capped at ``max_frames`` (0 = no cap); 0 when the source has no length."""
    try:
        n = len(frames)  # type: ignore[arg-type]
    except TypeError:
        return max_frames
    return min(n, max_frames) if max_frames else n
