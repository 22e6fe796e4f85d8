"""A trajectory that follows loop corrections: each pose moves with its reference keyframe.

The tracker publishes every frame's pose once, as odometry. When a loop closure later moves
keyframes, the best estimate of a past frame is its reference keyframe's correction applied to
it: T_wc(frame) <- D_kf T_wc(frame), with D_kf = T_wc_new(kf) T_wc_old(kf)^-1 the keyframe's
world-frame correction (``FeatureTracker.poll_loop_corrections``). ``memgs/path`` and the saved
``trajectory.txt`` show these corrected poses; ``memgs/pose`` / ``memgs/odom`` stay as published.

Local bundle-adjustment refinements are not applied here: re-expressing the frames relative to
BA-refined keyframes made the fr1/rpy trajectory worse (ATE 2.9 -> 3.3-4.0 cm), so they only
go to the mapper (``memgs/keyframe/refined_poses``).
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from memgs_ros.core.tracking.config import TrackResult


class AnchoredPath:
    """Frames (stamp_ns, T_wc [4, 4], reference keyframe id); ``max_len`` = 0 keeps all."""

    def __init__(self, max_len: int = 0) -> None:
        self.max_len = max_len
        self._stamps: list[int] = []
        self._ref: list[int] = []
        self._T_wc: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp_ns: int, T_wc: np.ndarray, ref_kf_id: int) -> None:
        """A frame's pose [4, 4] and the keyframe it was tracked against (-1: none)."""
        self._stamps.append(int(stamp_ns))
        self._ref.append(int(ref_kf_id))
        self._T_wc.append(np.array(T_wc, dtype=np.float64))
        if self.max_len and len(self._stamps) > self.max_len:
            drop = len(self._stamps) - self.max_len
            del self._stamps[:drop], self._ref[:drop], self._T_wc[:drop]

    def correct(self, corrections: Mapping[int, np.ndarray]) -> set[int]:
        """Apply world-frame corrections {kf_id: D [4, 4]} to the frames anchored to those
        keyframes; returns the keyframes that had frames here."""
        hit: set[int] = set()
        for i, r in enumerate(self._ref):
            D = corrections.get(r)
            if D is not None:
                self._T_wc[i] = D @ self._T_wc[i]
                hit.add(r)
        return hit

    def update(self, result: TrackResult, corrections: list[Mapping[int, np.ndarray]]) -> set[int]:
        """The loop corrections committed during ``track()`` (oldest first), then the frame;
        returns the keyframes whose earlier frames moved."""
        moved: set[int] = set()
        for c in corrections:
            moved |= self.correct(c)
        if result.T_wc is not None:
            self.add(result.stamp_ns, result.T_wc, result.reference_keyframe_id)
        return moved

    def poses_following(self, kf_ids: set[int]) -> tuple[np.ndarray, np.ndarray]:
        """(index [K] into the path, T_wc [K, 4, 4]) of the frames anchored to ``kf_ids``."""
        idx = np.flatnonzero(np.isin(np.array(self._ref, np.int64), np.fromiter(kf_ids, np.int64)))
        if len(idx) == 0:
            return idx, np.zeros((0, 4, 4))
        return idx, np.stack([self._T_wc[i] for i in idx.tolist()])

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns [N] int64, T_wc [N, 4, 4]) with every correction applied."""
        if not self._stamps:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        return np.array(self._stamps, np.int64), np.stack(self._T_wc)


__all__ = ["AnchoredPath"]
