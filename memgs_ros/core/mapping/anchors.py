"""Every keyframe a mapper ever inserted: its pose and capture time, also after it left training.

The Gaussians a keyframe created move with its corrections (a loop closure) even once
``max_keyframes`` dropped its view from training, so the mapper keeps each keyframe's latest pose
(~130 B a keyframe); a keyframe the tracker culled hands its Gaussians on to the nearest kept one
(its heir), and a keyframe taken long enough ago marks the map its Gaussians made as settled.
One owner: the ``GaussianMapper`` that holds it.
"""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry.poses import pose_distances

__all__ = ["KeyframeAnchors"]


class KeyframeAnchors:
    """Pose T_wc [4, 4], capture time (ns) and insertion iteration of every keyframe inserted and
    not retired."""

    def __init__(self) -> None:
        self._pose: dict[int, np.ndarray] = {}
        self._stamp: dict[int, int] = {}
        self._iteration: dict[int, int] = {}

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._pose

    def __len__(self) -> int:
        return len(self._pose)

    def add(self, kf_id: int, stamp_ns: int, T_wc: np.ndarray, iteration: int = 0) -> None:
        self._pose[int(kf_id)] = np.array(T_wc, dtype=np.float64)
        self._stamp[int(kf_id)] = int(stamp_ns)
        self._iteration[int(kf_id)] = int(iteration)

    def pose(self, kf_id: int) -> np.ndarray | None:
        return self._pose.get(int(kf_id))

    def move(self, kf_id: int, T_wc: np.ndarray) -> None:
        self._pose[int(kf_id)] = np.array(T_wc, dtype=np.float64)

    def settled(self, before_ns: int, inserted_by: int | None = None) -> list[int]:
        """Ids of the keyframes taken at or before ``before_ns``, or inserted at or before the
        iteration ``inserted_by`` (None: by time only)."""
        return [k for k, s in self._stamp.items()
                if s <= before_ns or (inserted_by is not None and self._iteration[k] <= inserted_by)]

    def retire(self, kf_id: int) -> int | None:
        """Forget keyframe ``kf_id``; returns its heir, the kept keyframe nearest to its pose
        (translation + 0.5 m per radian), or None (unknown, or no other keyframe)."""
        T = self._pose.pop(int(kf_id), None)
        self._stamp.pop(int(kf_id), None)
        self._iteration.pop(int(kf_id), None)
        if T is None or not self._pose:
            return None
        others = list(self._pose)
        return others[int(np.argmin(pose_distances(T, np.stack([self._pose[k] for k in others]))))]
