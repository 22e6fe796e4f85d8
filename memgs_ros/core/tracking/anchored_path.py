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

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

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
        keyframes; returns the keyframes that had frames here.

        A frame between its keyframe's first frame and the next keyframe's takes the correction
        interpolated between the two keyframes' (rotation on the geodesic, translation linearly),
        by frame count: the frame just before the next keyframe was tracked almost where that
        keyframe was made, so its correction is nearly that keyframe's; this keeps the corrected
        path continuous across keyframes.
        """
        hit: set[int] = set()
        n = len(self._ref)
        i = 0
        while i < n:
            r = self._ref[i]
            j = i
            while j < n and self._ref[j] == r:
                j += 1  # frames i..j-1 follow keyframe r; frame j starts the next run
            D = corrections.get(r)
            if D is not None:
                hit.add(r)
                D_next = corrections.get(self._ref[j]) if j < n and self._ref[j] > r else None
                for m in range(i, j):
                    Dm = D if D_next is None else _interpolate(D, D_next, (m - i) / (j - i))
                    self._T_wc[m] = Dm @ self._T_wc[m]
            i = j
        return hit

    def reanchor(self, heirs: Mapping[int, int]) -> None:
        """Frames anchored to a culled keyframe follow its heir ({culled id: heir id}) from now on:
        the culled one gets no more corrections."""
        if heirs:
            self._ref = [heirs.get(r, r) for r in self._ref]

    def update(self, result: TrackResult, corrections: Sequence[Mapping[int, np.ndarray]]) -> set[int]:
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


def _interpolate(A: np.ndarray, B: np.ndarray, t: float) -> np.ndarray:
    """The pose [4, 4] a fraction ``t`` of the way from A to B (rotation slerp, translation lerp)."""
    if t <= 0.0:
        return A
    out = np.eye(4)
    out[:3, :3] = A[:3, :3] @ Rotation.from_rotvec(
        t * Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).as_rotvec()).as_matrix()
    out[:3, 3] = (1.0 - t) * A[:3, 3] + t * B[:3, 3]
    return out


class PathChanges:
    """What a published copy of an :class:`AnchoredPath` must change since it was last taken: the
    frames added (``added``) and the keyframes whose frames moved (re-expressed when taken)."""

    def __init__(self, path: AnchoredPath) -> None:
        self.path = path
        self.added = False
        self._stale: set[int] = set()

    def update(self, result: TrackResult, corrections: Sequence[Mapping[int, np.ndarray]],
               heirs: Mapping[int, int] | None = None) -> None:
        """One frame: ``heirs`` ({culled keyframe: heir} since the last), then ``path.update``."""
        self.path.reanchor(heirs or {})
        self._stale |= self.path.update(result, corrections)
        self.added |= result.T_wc is not None

    def take(self) -> tuple[np.ndarray, np.ndarray] | None:
        """None when nothing changed since the last take; else the moved frames (index [K] into the
        path, T_wc [K, 4, 4]; K may be 0), and the changes count as published."""
        if not (self.added or self._stale):
            return None
        moved = self.path.poses_following(self._stale) if self._stale else (np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        self.added, self._stale = False, set()
        return moved


__all__ = ["AnchoredPath", "PathChanges"]
