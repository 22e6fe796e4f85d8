"""A trajectory re-expressed when keyframes move: each pose kept relative to its reference keyframe.

The tracker publishes every frame's pose once, as odometry. When local bundle adjustment or a
loop correction later moves keyframes, the best estimate of a past frame is its keyframe's new
pose times the relative pose it was tracked with: T_wc(frame) = T_wc(kf) T_kf_frame. ``memgs/path``
and the saved ``trajectory.txt`` show these corrected poses; ``memgs/pose`` / ``memgs/odom``
stay as published.
"""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry import invert_pose
from memgs_ros.core.tracking.config import TrackResult


class AnchoredPath:
    """Frames (stamp_ns, T_wc [4, 4]) anchored to reference keyframes; ``max_len`` = 0 keeps all."""

    def __init__(self, max_len: int = 0) -> None:
        self.max_len = max_len
        self._stamps: list[int] = []
        self._ref: list[int] = []
        self._T_rel: list[np.ndarray] = []  # T_kf_frame, or T_wc when the frame has no keyframe
        self._kf_T_wc: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp_ns: int, T_wc: np.ndarray, ref_kf_id: int, ref_T_wc: np.ndarray | None) -> None:
        """A frame's pose [4, 4] and its reference keyframe (id, current T_wc [4, 4]; -1/None: none)."""
        if ref_kf_id >= 0 and ref_T_wc is not None:
            self._kf_T_wc.setdefault(ref_kf_id, np.array(ref_T_wc, dtype=np.float64))
            rel = invert_pose(self._kf_T_wc[ref_kf_id]) @ T_wc
        else:
            ref_kf_id, rel = -1, np.array(T_wc, dtype=np.float64)
        self._stamps.append(int(stamp_ns))
        self._ref.append(int(ref_kf_id))
        self._T_rel.append(rel)
        if self.max_len and len(self._stamps) > self.max_len:
            drop = len(self._stamps) - self.max_len
            del self._stamps[:drop], self._ref[:drop], self._T_rel[:drop]
            live = set(self._ref)
            self._kf_T_wc = {k: v for k, v in self._kf_T_wc.items() if k in live}

    def set_keyframe(self, kf_id: int, T_wc: np.ndarray) -> bool:
        """Move keyframe ``kf_id`` to T_wc [4, 4]; True when frames of the path follow it."""
        if kf_id not in self._kf_T_wc:
            return False
        self._kf_T_wc[kf_id] = np.array(T_wc, dtype=np.float64)
        return True

    def update(self, result: TrackResult, refined: list[tuple[int, np.ndarray]]) -> bool:
        """One tracked frame and the refined keyframe poses (id, T_wc [4, 4]) polled after it;
        True when earlier poses of the path moved."""
        moved = False
        for kf_id, T_wc in refined:
            moved |= self.set_keyframe(kf_id, T_wc)
        if result.keyframe is not None:
            self._kf_T_wc[result.keyframe.keyframe_id] = np.array(result.keyframe.T_wc, dtype=np.float64)
        if result.T_wc is not None:
            ref = result.reference_keyframe_id
            self.add(result.stamp_ns, result.T_wc, ref, self._kf_T_wc.get(ref))
        return moved

    def keyframe_pose(self, kf_id: int) -> np.ndarray | None:
        return self._kf_T_wc.get(kf_id)

    def poses_following(self, kf_ids: set[int]) -> tuple[np.ndarray, np.ndarray]:
        """(index [K] into the path, T_wc [K, 4, 4]) of the frames anchored to ``kf_ids``."""
        idx = np.flatnonzero(np.isin(np.array(self._ref, np.int64), np.fromiter(kf_ids, np.int64)))
        if len(idx) == 0:
            return idx, np.zeros((0, 4, 4))
        base = np.stack([self._kf_T_wc[self._ref[i]] for i in idx.tolist()])
        return idx, base @ np.stack([self._T_rel[i] for i in idx.tolist()])

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns [N] int64, T_wc [N, 4, 4]) with every keyframe correction applied."""
        if not self._stamps:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        eye = np.eye(4)
        base = np.stack([self._kf_T_wc[r] if r >= 0 else eye for r in self._ref])
        return np.array(self._stamps, np.int64), base @ np.stack(self._T_rel)


__all__ = ["AnchoredPath"]
