"""An immutable copy of the sparse map: what the front-end hands the back-end with each request.

``SparseMap.snapshot()`` copies the keyframe poses, each keyframe's point id per keypoint and the
point store, and shares the keyframes' ORB features (frozen). The back-end reads only copies, so
the front-end goes on changing its map while a bundle adjustment or a loop search runs; results
name the ``layout_version`` and ``pose_epoch`` they were computed at, and the map's commit
discards or renumbers them.

The observation table (who sees which point) is derived from the keyframes' point ids on first
use, by the back-end: ``SparseMap`` keeps them consistent with its observation dicts.
"""
from __future__ import annotations

import functools
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from memgs_ros.core.tracking.features.features import FrameFeatures


@dataclass(frozen=True, eq=False)
class ObservationTable:
    """Every (keyframe, keypoint) -> point link, sorted by point id, then keyframe id.

    kf: [O] keyframe ids; kf_index: [O] their position in the snapshot; kp: [O] keypoint index;
    point: [O] point id; start: [S + 1] rows of point p are start[p]:start[p + 1].
    """

    kf: np.ndarray
    kf_index: np.ndarray
    kp: np.ndarray
    point: np.ndarray
    start: np.ndarray

    def rows_of(self, point_ids: np.ndarray) -> np.ndarray:
        """Row indices [R] of the observations of ``point_ids`` [K], point by point in the given order."""
        ids = np.asarray(point_ids, np.int64)
        first, n = self.start[ids], self.start[ids + 1] - self.start[ids]
        total = int(n.sum())
        if total == 0:
            return np.zeros(0, np.int64)
        offset = np.repeat(first - (np.cumsum(n) - n), n)
        return offset + np.arange(total)


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """The sparse map at one moment (see the module docstring); never changes after creation.

    kf_ids: [N] sorted keyframe ids; T_cw: [N, 4, 4]; feats: N FrameFeatures; kp_point: [sum M]
    point id per keypoint of every keyframe, back to back (-1 where none), keyframe n's at
    kf_offset[n]:kf_offset[n + 1]. points_w [S, 3], desc [S, 32], octave [S] and good [S] cover the
    point store (point ids are indices; bad entries are meaningless).
    """

    kf_ids: np.ndarray
    T_cw: np.ndarray
    feats: tuple[FrameFeatures, ...]
    kp_point: np.ndarray
    kf_offset: np.ndarray
    points_w: np.ndarray
    desc: np.ndarray
    octave: np.ndarray
    good: np.ndarray
    layout_version: int
    pose_epoch: int

    def __post_init__(self) -> None:
        for a in (self.kf_ids, self.T_cw, self.kp_point, self.kf_offset, self.points_w, self.desc,
                  self.octave, self.good):
            a.flags.writeable = False

    # -- keyframes ---------------------------------------------------------------------
    @functools.cached_property
    def _position(self) -> dict[int, int]:
        return {k: n for n, k in enumerate(self.kf_ids.tolist())}

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._position

    def __len__(self) -> int:
        return len(self.kf_ids)

    def position(self, kf_id: int) -> int:
        """Index of keyframe ``kf_id`` in ``kf_ids`` (KeyError when the snapshot lacks it)."""
        return self._position[kf_id]

    def kf_points(self, kf_id: int) -> np.ndarray:
        """[M] point id per keypoint of keyframe ``kf_id`` (-1 where none)."""
        n = self._position[kf_id]
        return self.kp_point[self.kf_offset[n]:self.kf_offset[n + 1]]

    def kf_feats(self, kf_id: int) -> FrameFeatures:
        return self.feats[self._position[kf_id]]

    def kf_T_cw(self, kf_id: int) -> np.ndarray:
        return self.T_cw[self._position[kf_id]]

    @functools.cached_property
    def keypoints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """uv [sum M, 2], depth_m [sum M] and octave [sum M] of every keyframe's keypoints, back to
        back like ``kp_point`` (built on first use)."""
        if not self.feats:
            return np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64)
        return (np.concatenate([f.uv for f in self.feats]),
                np.concatenate([f.depth_m for f in self.feats]).astype(np.float64),
                np.concatenate([f.octave for f in self.feats]))

    # -- points ------------------------------------------------------------------------
    def point_arrays(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(pos [K, 3], desc [K, 32], octave [K]) for point ids [K]."""
        return self.points_w[ids], self.desc[ids], self.octave[ids]

    def points_of(self, kf_ids: Sequence[int]) -> np.ndarray:
        """Sorted unique good point ids observed by the keyframes ``kf_ids`` (as ``SparseMap.points_of``)."""
        seen = np.zeros(len(self.good), dtype=bool)
        for k in kf_ids:
            if k in self._position:
                a = self.kf_points(k)
                seen[a[a >= 0]] = True
        return np.flatnonzero(seen & self.good)

    @functools.cached_property
    def observations(self) -> ObservationTable:
        """The observation table, built on first use (by the back-end, not the map's owner)."""
        counts = np.diff(self.kf_offset)
        kf_index = np.repeat(np.arange(len(self.kf_ids)), counts)
        kp = np.arange(len(self.kp_point)) - np.repeat(self.kf_offset[:-1], counts)
        has = self.kp_point >= 0
        order = np.argsort(self.kp_point[has], kind="stable")  # keyframes are in id order already
        point, kf_index, kp = self.kp_point[has][order], kf_index[has][order], kp[has][order]
        start = np.r_[0, np.cumsum(np.bincount(point, minlength=len(self.good)))]
        return ObservationTable(self.kf_ids[kf_index], kf_index, kp, point, start)

    def n_observations(self, ids: np.ndarray) -> np.ndarray:
        """[K] keyframes observing each point id."""
        ids = np.asarray(ids, np.int64)
        return self.observations.start[ids + 1] - self.observations.start[ids]

    def covisible(self, point_ids: np.ndarray, k: int, exclude: Collection[int] = ()) -> list[int]:
        """The ``k`` keyframes observing most of ``point_ids``, most first (``SparseMap.covisible``;
        ties go to the keyframe met first, point by point)."""
        kfs = self.observations.kf[self.observations.rows_of(point_ids)]
        if len(kfs) == 0:
            return []
        ids, first, counts = np.unique(kfs, return_index=True, return_counts=True)
        keep = ~np.isin(ids, np.fromiter(exclude, np.int64, len(exclude)))
        ids, first, counts = ids[keep], first[keep], counts[keep]
        return ids[np.lexsort((first, -counts))][:k].tolist()


__all__ = ["MapSnapshot", "ObservationTable"]
