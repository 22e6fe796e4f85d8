"""Edits of the sparse map that the back-end computes elsewhere and commits on the tracking thread:
a loop closure's correction of keyframes and points, and a bundle adjustment's refinement (a mixin
of ``local_map.SparseMap``)."""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.frontend.map_types import PointStore, SparseKeyframe

__all__ = ["MapEdits"]


class MapEdits:
    """Mixin of ``SparseMap``: ``apply_loop_correction`` and ``commit_refinement``."""

    keyframes: dict[int, SparseKeyframe]
    observations: list[dict[int, int]]
    version: int
    layout_version: int
    pose_epoch: int
    _pts: PointStore

    def remove_observation(self, pid: int, kf_id: int) -> None:
        raise NotImplementedError

    def renumber(self, point_ids: np.ndarray, layout_version: int) -> np.ndarray | None:
        raise NotImplementedError

    def apply_loop_correction(self, kf_ids: np.ndarray, D: np.ndarray, newer_D: np.ndarray,
                              newer_than: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Move keyframes ``kf_ids`` [N] by their world-frame corrections ``D`` [N, 4, 4]
        (T_wc <- D T_wc); keyframes newer than ``newer_than`` that are not listed move by
        ``newer_D`` [4, 4]; every point moves with the keyframe that created it (or, when that
        one is gone, with a keyframe observing it). Bumps ``pose_epoch`` so that bundle
        adjustments snapshotted before are discarded. Returns {kf_id: (old T_cw, new T_cw)}.
        """
        table = {int(k): Dk for k, Dk in zip(np.asarray(kf_ids).tolist(), D)}
        eye = np.eye(4)

        def correction(kf_id: int) -> np.ndarray | None:
            c = table.get(kf_id)
            if c is None and kf_id > newer_than:
                c = newer_D
            return c

        moved: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for kf_id, kf in self.keyframes.items():
            c = correction(kf_id)
            if c is None:
                continue
            T_new = kf.T_cw @ invert_pose(c)  # (D T_wc)^-1
            moved[kf_id] = (kf.T_cw.copy(), T_new)
            kf.T_cw = T_new
        p = self._pts
        ids = np.flatnonzero(~p.bad[: p.size])
        refs = p.first_kf[ids]
        uniq, inv = np.unique(refs, return_inverse=True)
        per_ref = [correction(int(r)) for r in uniq.tolist()]
        Dp = np.stack([eye if c is None else c for c in per_ref])[inv]  # [P, 4, 4]
        missing = np.array([c is None for c in per_ref], bool)[inv]
        for j in np.flatnonzero(missing).tolist():  # creator gone: follow an observing keyframe
            for kf_id in self.observations[int(ids[j])]:
                c = correction(kf_id)
                if c is not None:
                    Dp[j] = c
                    break
        pos = p.pos[ids]
        p.pos[ids] = np.einsum("pij,pj->pi", Dp[:, :3, :3], pos) + Dp[:, :3, 3]
        self.pose_epoch += 1
        self.version += 1
        return moved

    def commit_refinement(self, kf_ids: list[int], T_cw: np.ndarray, point_ids: np.ndarray,
                          points_w: np.ndarray, outliers: list[tuple[int, int]],
                          layout_version: int | None = None,
                          pose_epoch: int | None = None) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Write BA results; returns {kf_id: (old T_cw, new T_cw)} for the keyframes moved.

        T_cw: [F, 4, 4] for ``kf_ids``; point_ids: [P] with points_w [P, 3]; outliers: (point id,
        keyframe id) observations to drop. ``layout_version``: the point numbering the ids were
        taken in (None: today's); results older than the last compaction but one are discarded.
        ``pose_epoch``: the epoch of the snapshot; results from before a loop correction are discarded.
        """
        moved: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if pose_epoch is not None and pose_epoch != self.pose_epoch:
            return moved
        point_ids = np.asarray(point_ids, np.int64)
        if layout_version is not None and layout_version != self.layout_version:
            renumbered = self.renumber(np.concatenate([point_ids, np.array([o[0] for o in outliers],
                                                                           np.int64)]), layout_version)
            if renumbered is None:
                return moved
            point_ids, out_ids = renumbered[: len(point_ids)], renumbered[len(point_ids):]
            outliers = [(int(i), k) for i, (_, k) in zip(out_ids.tolist(), outliers, strict=True) if i >= 0]
        for kf_id, T in zip(kf_ids, T_cw):
            kf = self.keyframes.get(kf_id)
            if kf is not None:
                moved[kf_id] = (kf.T_cw.copy(), T.copy())
                kf.T_cw = T.copy()
        live = point_ids >= 0
        point_ids, points_w = point_ids[live], np.asarray(points_w)[live]
        ok = ~self._pts.bad[point_ids]
        self._pts.pos[point_ids[ok]] = points_w[ok]
        for pid, kf_id in outliers:
            self.remove_observation(pid, kf_id)
        self.version += 1
        return moved
