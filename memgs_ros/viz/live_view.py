"""The live view of a run in one Rerun recording, without ROS: what the Rerun bridge logs and when.

The bridge node decodes its messages and hands them here. Every camera pose is a frame of the
view's timeline; later data of the same stamp (a render, a keyframe) is logged at that frame.
Keyframe frusta are drawn once a camera is known and moved when bundle adjustment or a loop
closure moves them noticeably. Each log call is timed into ``counters`` (``log_us_total``,
``log_us.<what>``, ``logged.<what>``): Rerun's own cost, as the bridge's stats report it.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np

from memgs_ros.core.gaussians.records import GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.runtime.telemetry_fields import ViewFields

__all__ = ["LiveView"]

MOVE_MIN = 1e-3  # a keyframe moved by more than 1 mm or ~0.06 degrees is drawn again


class LiveView:
    """Logs a run's poses, keyframes, views, map and scalars to ``rec`` through ``log`` (the
    :mod:`memgs_ros.viz.rerun_log` module, loaded once rerun is known to be there).

    stamps_kept: recent pose stamps whose frame index later data of the same stamp finds.
    """

    def __init__(self, log: ModuleType, rec: Any, stats: ViewFields, frustum_m: float, jpeg_quality: int,
                 log_sh: bool, stamps_kept: int = 120) -> None:
        self.log, self.rec, self.stats = log, rec, stats
        self.frustum_m, self.jpeg_quality, self.log_sh = frustum_m, jpeg_quality, log_sh
        self._stamps_kept = stamps_kept
        self.frame_index = -1
        self.stamp_ns = 0
        self._frame_of_stamp: OrderedDict[int, int] = OrderedDict()
        self.camera: PinholeCamera | None = None
        self._camera_logged: PinholeCamera | None = None  # the camera of the last frustum at world/camera
        self.keyframes: dict[int, int] = {}  # stamp -> keyframe index
        self.keyframe_poses: dict[int, np.ndarray] = {}  # keyframe index -> T_wc [4, 4] as last logged
        self._closing = False

    def _now(self, stamp_ns: int | None = None) -> Any:
        """The LogTime of ``stamp_ns`` (its frame index when seen) or of the latest frame."""
        if stamp_ns is not None and stamp_ns in self._frame_of_stamp:
            return self.log.LogTime(self._frame_of_stamp[stamp_ns], stamp_ns)
        return self.log.LogTime(max(self.frame_index, 0), self.stamp_ns)

    def _timed(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        if self._closing:
            return None  # the recording is being closed: nothing more goes into it
        t0 = time.perf_counter()
        out = fn(self.rec, *args)
        us = int((time.perf_counter() - t0) * 1e6)
        self.stats.log_us_total += us
        self.stats.log_us[what] += us
        self.stats.logged[what] += 1
        return out

    def pose(self, stamp_ns: int, T_wc: np.ndarray) -> None:  # [4, 4]
        """The camera pose of a new frame; its frustum once per camera (the viewer keeps the latest)."""
        self.frame_index += 1
        self.stamp_ns = stamp_ns
        self._frame_of_stamp[stamp_ns] = self.frame_index
        while len(self._frame_of_stamp) > self._stamps_kept:
            self._frame_of_stamp.popitem(last=False)
        camera = self.camera if self.camera != self._camera_logged else None
        self._camera_logged = self.camera
        self._timed("pose", self.log.log_camera, T_wc, self._now(stamp_ns), camera)

    def trajectory(self, T_wc: np.ndarray) -> None:  # [M, 4, 4]
        if len(T_wc) >= 2:
            self._timed("trajectory", self.log.log_trajectory, T_wc, self._now())

    def set_camera(self, camera: PinholeCamera) -> None:
        """The keyframes' camera; keyframes that came before the first one get their frusta now."""
        first = self.camera is None
        self.camera = camera
        if first:
            for index, T in self.keyframe_poses.items():
                self._timed("keyframe", self.log.log_keyframe, index, T, self._now(), camera, self.frustum_m)

    def keyframe(self, stamp_ns: int, T_wc: np.ndarray) -> None:  # [4, 4]
        if stamp_ns in self.keyframes:
            return  # a repeated copy (TRANSIENT_LOCAL) of one already logged
        index = self.keyframes[stamp_ns] = len(self.keyframes)
        self.keyframe_poses[index] = T_wc
        self._timed("keyframe", self.log.log_keyframe, index, T_wc, self._now(stamp_ns), self.camera, self.frustum_m)

    def keyframes_moved(self, poses: list[tuple[int, np.ndarray]]) -> None:
        """(stamp, T_wc) of keyframes BA or a loop closure moved; only those that moved by more
        than MOVE_MIN are drawn again (BA sends its whole window after every run; most barely move)."""
        for stamp_ns, T in poses:
            index = self.keyframes.get(stamp_ns)
            if index is not None and np.abs(T[:3] - self.keyframe_poses[index][:3]).max() > MOVE_MIN:
                self.keyframe_poses[index] = T
                self._timed("keyframe_moved", self.log.log_keyframe, index, T, self._now())

    def views(self, stamp_ns: int, render: np.ndarray, frame: np.ndarray | None) -> float | None:
        """A render and the source frame of its stamp (when kept); their PSNR (dB) when both are there."""
        return self._timed("views", self.log.log_views, render, frame, self._now(stamp_ns), self.jpeg_quality)

    def map(self, records: GaussianRecords) -> None:
        self._timed("map", self.log.log_map, records, self._now(), self.log_sh)

    def scalars(self, node: str, numbers: dict[str, float]) -> None:
        self._timed("stats", self.log.log_scalars, node, numbers, self._now())

    def close(self) -> None:
        """Nothing more goes in; waits for rerun's own threads (file sink, gRPC stream) to write it all."""
        self._closing = True
        self.log.finish(self.rec)
