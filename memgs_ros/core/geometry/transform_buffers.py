"""Transforms as a robot's TF tree holds them, without ROS: a window of stamped poses of one frame
in another (odometry), read at a stamp, and static frames chained from child to parent. The
TF listeners (``ros/tf.py``) feed them from ``/tf`` and ``/tf_static``."""
from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from memgs_ros.core.geometry.poses import interpolate_poses

__all__ = ["MAX_GAP_S", "PoseWindow", "StaticFrames"]

MAX_GAP_S = 0.5  # poses further apart than this are not interpolated across


class PoseWindow:
    """The latest poses ``T`` [4, 4] of one frame in another, by stamp (a bounded window in stamp
    order): what a flight controller's or wheel odometry's ``odom -> base_link`` says."""

    def __init__(self, window: int = 400, max_gap_s: float = MAX_GAP_S) -> None:
        self.stamps: deque[int] = deque(maxlen=window)
        self.poses: deque[np.ndarray] = deque(maxlen=window)
        self.max_gap_ns = int(max_gap_s * 1e9)

    def add(self, stamp_ns: int, T: np.ndarray) -> None:
        """A pose at ``stamp_ns``; one at a stamp already held is ignored, one from before the
        newest (time went back: a bag looped) starts the window over."""
        if self.stamps and stamp_ns <= self.stamps[-1]:
            if stamp_ns == self.stamps[-1]:
                return
            self.stamps.clear()
            self.poses.clear()
        self.stamps.append(int(stamp_ns))
        self.poses.append(T)

    def at(self, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        """The pose at ``stamp_ns``: interpolated between the two around it (at most
        ``max_gap_s`` apart), else the nearest if it lies within ``tolerance_ns`` (no
        extrapolation past that); None otherwise."""
        if not self.stamps:
            return None
        stamps = list(self.stamps)
        i = bisect.bisect_left(stamps, stamp_ns)
        if 0 < i < len(stamps):
            pair, valid = interpolate_poses(np.array(stamps[i - 1:i + 1]), np.stack([self.poses[i - 1], self.poses[i]]),
                                            np.array([stamp_ns]), max_gap_ns=self.max_gap_ns)
            if valid[0]:
                return pair[0]
        best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - stamp_ns))
        return self.poses[best] if abs(stamps[best] - stamp_ns) <= tolerance_ns else None


class StaticFrames:
    """Static transforms (child -> its parent and ``T_parent_child``), chained on lookup: a camera's
    mount as a robot description and a camera driver give it (``base_link -> camera_link ->
    camera_color_optical_frame``)."""

    def __init__(self) -> None:
        self.parents: dict[str, tuple[str, np.ndarray]] = {}

    def set(self, parent: str, child: str, T: np.ndarray) -> None:
        self.parents[child] = (parent, T)

    def lookup(self, parent: str, child: str) -> np.ndarray | None:
        """``T_parent_child`` [4, 4] along the chain, or None (a broken chain or a cycle)."""
        T, frame = np.eye(4), child
        for _ in range(64):
            if frame == parent:
                return T
            if frame not in self.parents:
                return None
            frame, T_up = self.parents[frame]
            T = T_up @ T
        return None
