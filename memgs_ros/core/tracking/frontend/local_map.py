"""The tracker's sparse map: keyframes, map points, observations, covisibility.

The map has one owner, the tracker's front-end thread: it tracks against the map, inserts
keyframes and commits what the back-end (``backend.TrackingBackend``) sends back. The back-end
works on immutable copies (``snapshot``), so nothing here is locked.

Memory stays bounded on long runs: the tracker removes keyframes over its cap
(``remove_keyframe``), points seen by no keyframe turn bad, and ``compact`` drops bad points
once they are half the store. Point ids are array indices, so compaction renumbers them; it
bumps ``layout_version`` and keeps the last renumbering so that a bundle adjustment that took
its snapshot before the compaction can still commit (``commit_refinement(layout_version=...)``).
"""
from __future__ import annotations

from collections import Counter
from itertools import chain

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose, nearest_pose_distance
from memgs_ros.core.tracking.frontend.map_edits import MapEdits
from memgs_ros.core.tracking.frontend.map_snapshot import MapSnapshot
from memgs_ros.core.tracking.frontend.map_types import PointStore, SparseKeyframe
from memgs_ros.core.tracking.kernel_calls import View, count_seen_kernel


class SparseMap(MapEdits):
    """Keyframes and map points of one tracking segment."""

    def __init__(self, first_keyframe_id: int = 0) -> None:
        self.keyframes: dict[int, SparseKeyframe] = {}
        self._pts = PointStore()
        self.observations: list[dict[int, int]] = []  # point id -> {keyframe id: keypoint index}
        self._next_kf_id = first_keyframe_id  # ids stay unique across segments
        self.version = 0  # bumped on every BA commit
        self.layout_version = 0  # bumped when compaction renumbers the point ids
        self.pose_epoch = 0  # bumped by loop corrections: BA results from an older epoch are stale
        self._last_renumbering = np.zeros(0, np.int64)  # old id -> new id (-1 dropped) of the last compaction
        self.keyframes_removed = 0
        self.points_compacted = 0

    # -- points -------------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        """Point ids in use, bad ones included (the store's length)."""
        return self._pts.size

    @property
    def n_good_points(self) -> int:
        return int((~self._pts.bad[: self._pts.size]).sum())

    def _grow(self, extra: int) -> None:
        p = self._pts
        need = p.size + extra
        cap = len(p.pos)
        if need <= cap:
            return
        new_cap = max(need, 2 * cap, 1024)

        def g(a: np.ndarray, fill: object = 0) -> np.ndarray:
            out = np.full((new_cap,) + a.shape[1:], fill, dtype=a.dtype)
            out[: len(a)] = a
            return out

        p.pos, p.desc, p.octave = g(p.pos), g(p.desc), g(p.octave)
        p.n_visible, p.n_found, p.first_kf = g(p.n_visible), g(p.n_found), g(p.first_kf)
        p.n_obs = g(p.n_obs)
        p.bad = g(p.bad, True)

    def add_points(self, pos_w: np.ndarray, desc: np.ndarray, octave: np.ndarray,
                   kf_id: int, kp_idx: np.ndarray) -> np.ndarray:
        """New points [K, 3] seen by keyframe ``kf_id`` at keypoints ``kp_idx`` [K]; returns ids [K]."""
        k = len(pos_w)
        self._grow(k)
        p = self._pts
        ids = np.arange(p.size, p.size + k)
        p.pos[ids], p.desc[ids], p.octave[ids] = pos_w, desc, octave
        p.n_visible[ids], p.n_found[ids], p.n_obs[ids] = 1, 1, 1
        p.first_kf[ids], p.bad[ids] = kf_id, False
        p.size += k
        self.observations.extend({kf_id: int(i)} for i in kp_idx)
        self.keyframes[kf_id].point_ids[kp_idx] = ids
        return ids

    def add_observations(self, point_ids: np.ndarray, kf_id: int, kp_idx: np.ndarray) -> None:
        kf = self.keyframes[kf_id]
        for pid, i in zip(point_ids.tolist(), kp_idx.tolist()):
            if self._pts.bad[pid] or kf_id in self.observations[pid]:
                continue
            self.observations[pid][kf_id] = i
            self._pts.n_obs[pid] += 1
            kf.point_ids[i] = pid

    def remove_observation(self, pid: int, kf_id: int) -> None:
        i = self.observations[pid].pop(kf_id, None)
        if i is not None:
            self._pts.n_obs[pid] -= 1
        kf = self.keyframes.get(kf_id)
        if i is not None and kf is not None and kf.point_ids[i] == pid:
            kf.point_ids[i] = -1
        if not self.observations[pid]:
            self._pts.bad[pid] = True

    def set_bad(self, pids: np.ndarray) -> None:
        for pid in np.asarray(pids).tolist():
            for kf_id, i in self.observations[pid].items():
                kf = self.keyframes.get(kf_id)
                if kf is not None and kf.point_ids[i] == pid:
                    kf.point_ids[i] = -1
            self.observations[pid] = {}
            self._pts.bad[pid] = True
            self._pts.n_obs[pid] = 0

    def export_points(self) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """Copies of the store's (pos, desc, octave, n_visible, n_found, first_kf) and the good mask [n_points]."""
        p, n = self._pts, self._pts.size
        return tuple(a[:n].copy() for a in (p.pos, p.desc, p.octave, p.n_visible, p.n_found, p.first_kf)), ~p.bad[:n]

    def restore_points(self, *arrays: np.ndarray) -> None:
        """Fill an empty store with ``export_points``' arrays (good points); observations from the keyframes."""
        self._grow(len(arrays[0]))
        p, n = self._pts, len(arrays[0])
        for name, arr in zip(("pos", "desc", "octave", "n_visible", "n_found", "first_kf"), arrays):
            getattr(p, name)[:n] = arr
        p.bad[:n], p.size = False, n
        self.observations = [{} for _ in range(n)]
        for kf in self.keyframes.values():
            for i in np.flatnonzero(kf.point_ids >= 0).tolist():
                self.observations[int(kf.point_ids[i])][kf.keyframe_id] = i
        p.n_obs[:n] = [len(o) for o in self.observations]
        p.bad[:n] = p.n_obs[:n] == 0

    def point_arrays(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(pos [K, 3], desc [K, 32], octave [K]) copies for point ids [K]."""
        p = self._pts
        return p.pos[ids].copy(), p.desc[ids].copy(), p.octave[ids].copy()

    def store(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The point store's (pos [N, 3], desc [N, 32], octave [N]) themselves, not copies, for the
        front-end's kernels to read in place (index = point id; rows past ``n_points`` unused).
        Valid until the next change to the map."""
        p = self._pts
        return p.pos, p.desc, p.octave

    def count_seen(self, ids: np.ndarray, T_cw: np.ndarray, view: View, found: np.ndarray) -> None:
        """Compiled ``count_visible`` of the points ``ids`` in ``view`` at T_cw, and ``count_found``
        of ``found``, in one call."""
        count_seen_kernel(self._pts.pos, ids, T_cw, view, found, self._pts.n_visible, self._pts.n_found)

    def n_observations(self, ids: np.ndarray) -> np.ndarray:
        """[K] number of keyframes observing each point id (0 for bad points)."""
        return self._pts.n_obs[ids]

    def reference_keyframes(self, ids: np.ndarray) -> np.ndarray:
        """[K] the keyframe that created each point id (it may have been removed since)."""
        return self._pts.first_kf[np.asarray(ids, np.int64)].copy()

    def good(self, ids: np.ndarray) -> np.ndarray:
        return ~self._pts.bad[ids]

    def count_visible(self, ids: np.ndarray) -> None:
        np.add.at(self._pts.n_visible, ids, 1)

    def count_found(self, ids: np.ndarray) -> None:
        np.add.at(self._pts.n_found, ids, 1)

    def cull_points(self, current_kf_id: int, min_found_ratio: float, min_obs: int) -> int:
        """Mark recent points bad when rarely found or seen by too few keyframes; returns count."""
        p = self._pts
        ids = np.flatnonzero(~p.bad[: p.size] & (p.first_kf[: p.size] >= current_kf_id - 3))
        if len(ids) == 0:
            return 0
        ratio = p.n_found[ids] / np.maximum(p.n_visible[ids], 1)
        n_obs = p.n_obs[ids]
        age = current_kf_id - p.first_kf[ids]
        bad = (ratio < min_found_ratio) | ((age >= 2) & (n_obs < min_obs))
        self.set_bad(ids[bad])
        return int(bad.sum())

    # -- keyframes ----------------------------------------------------------------------
    @property
    def next_keyframe_id(self) -> int:
        return self._next_kf_id

    def new_keyframe_id(self) -> int:
        self._next_kf_id += 1
        return self._next_kf_id - 1

    def add_keyframe(self, kf: SparseKeyframe) -> None:
        self.keyframes[kf.keyframe_id] = kf

    def remove_keyframe(self, kf_id: int) -> None:
        """Forget keyframe ``kf_id`` and its observations; points it alone saw turn bad."""
        kf = self.keyframes.pop(kf_id, None)
        if kf is None:
            return
        p = self._pts
        for pid in kf.point_ids[kf.point_ids >= 0].tolist():
            obs = self.observations[pid]
            if obs.pop(kf_id, None) is not None:
                p.n_obs[pid] -= 1
            if not obs:
                p.bad[pid] = True
                p.n_obs[pid] = 0
        self.keyframes_removed += 1

    def cap_keyframes(self, cap: int, protected: set[int]) -> None:
        """Remove the most redundant keyframes (nearest pose to another) outside ``protected``
        until at most ``cap`` remain, then compact the points nobody sees any more."""
        ids = sorted(self.keyframes)
        while len(ids) > cap:
            nearest = nearest_pose_distance(invert_pose(np.stack([self.keyframes[i].T_cw for i in ids])))
            nearest[[j for j, i in enumerate(ids) if i in protected]] = np.inf
            j = int(np.argmin(nearest))
            if not np.isfinite(nearest[j]):
                break  # everything left is in use
            self.remove_keyframe(ids.pop(j))
        self.compact()

    def compact(self, min_bad: int = 1024, min_fraction: float = 0.5) -> bool:
        """Drop bad points once there are at least ``min_bad`` and ``min_fraction`` of the store
        (the defaults renumber rarely: each compaction at least halves the store).

        Renumbers the good points 0..n-1 (keyframe point_ids and observations follow); returns
        whether it compacted. Holders of old ids must translate them with ``renumber``.
        """
        p = self._pts
        n = p.size
        keep = ~p.bad[:n]
        n_keep = int(keep.sum())
        n_bad = n - n_keep
        if n_bad == 0 or n_bad < min_bad or n_bad < min_fraction * n:
            return False
        new_id = np.full(n, -1, np.int64)
        new_id[keep] = np.arange(n_keep)
        cap = max(1024, 2 * n_keep)

        def shrink(a: np.ndarray, fill: object = 0) -> np.ndarray:
            out = np.full((cap,) + a.shape[1:], fill, dtype=a.dtype)
            out[:n_keep] = a[:n][keep]
            return out

        p.pos, p.desc, p.octave = shrink(p.pos), shrink(p.desc), shrink(p.octave)
        p.n_visible, p.n_found, p.first_kf = shrink(p.n_visible), shrink(p.n_found), shrink(p.first_kf)
        p.n_obs, p.bad = shrink(p.n_obs), shrink(p.bad, True)
        p.size = n_keep
        self.observations = [self.observations[i] for i in np.flatnonzero(keep).tolist()]
        for kf in self.keyframes.values():
            has = kf.point_ids >= 0
            kf.point_ids[has] = new_id[kf.point_ids[has]]
        self._last_renumbering = new_id
        self.layout_version += 1
        self.points_compacted += n_bad
        return True

    def renumber(self, point_ids: np.ndarray, layout_version: int) -> np.ndarray | None:
        """Point ids [K] taken at ``layout_version`` in today's numbering (-1 for dropped ones),
        or None when more than one compaction happened since (the ids are meaningless now)."""
        if layout_version == self.layout_version:
            return np.asarray(point_ids, np.int64)
        if layout_version == self.layout_version - 1:
            return self._last_renumbering[np.asarray(point_ids, np.int64)]
        return None

    def cull_redundant_keyframes(self, candidates: list[int], ratio: float, observers: int,
                            protected: set[int]) -> list[int]:
        """Remove the keyframes of ``candidates`` (outside ``protected``) whose good points are at
        least ``ratio`` seen by ``observers`` other keyframes each (ORB-SLAM's culling rule), judged
        one after the other: a removed keyframe no longer counts as an observer of the next.
        Returns the removed ids (``remove_keyframe``: their observations go, points they alone saw
        turn bad)."""
        out: list[int] = []
        if ratio <= 0.0:
            return out
        for kf_id in candidates:
            kf = self.keyframes.get(kf_id)
            if kf is None or kf_id in protected:
                continue
            pids = kf.point_ids[kf.point_ids >= 0]
            pids = pids[~self._pts.bad[pids]]
            if len(pids) == 0:
                continue
            if np.count_nonzero(self._pts.n_obs[pids] > observers) >= ratio * len(pids):
                out.append(kf_id)
                self.remove_keyframe(kf_id)
        return out

    def covisible(self, point_ids: np.ndarray, k: int, exclude: int | None = None) -> list[int]:
        """The ``k`` keyframes observing most of ``point_ids``, most first."""
        # Counted in C (a Counter over the chained observation dicts' keys), in first-seen order
        # as the loop it replaced, so equal counts keep their order.
        obs = self.observations
        counts = Counter(chain.from_iterable(map(obs.__getitem__, np.asarray(point_ids).tolist())))
        if exclude is not None:
            counts.pop(exclude, None)
        return [kf for kf, _ in sorted(counts.items(), key=lambda kv: -kv[1])[:k]]

    def mask_of(self, ids: np.ndarray) -> np.ndarray:
        """[n_points] bool, True at the point ids ``ids`` (ids past the store are ignored): a
        membership test in O(points) without np.isin's sort."""
        mask = np.zeros(self._pts.size, dtype=bool)
        ids = np.asarray(ids, np.int64)
        mask[ids[(ids >= 0) & (ids < self._pts.size)]] = True
        return mask

    def points_of(self, kf_ids: list[int]) -> np.ndarray:
        """Unique good point ids observed by the keyframes ``kf_ids``."""
        arrs = [self.keyframes[i].point_ids for i in kf_ids if i in self.keyframes]
        if not arrs:
            return np.zeros(0, np.int64)
        # A mask over the store instead of np.unique: O(points) without a sort (0.5 -> 0.05 ms
        # for a 10-keyframe local map); the result is the same sorted unique ids.
        seen = np.zeros(self._pts.size, dtype=bool)
        for a in arrs:
            seen[a[a >= 0]] = True
        seen &= ~self._pts.bad[: self._pts.size]
        return np.flatnonzero(seen)

    def snapshot(self) -> MapSnapshot:
        """An immutable copy for the back-end (poses, keypoint-to-point links, the point store)."""
        ids = sorted(self.keyframes)
        kfs = [self.keyframes[k] for k in ids]
        n = self._pts.size
        p = self._pts
        return MapSnapshot(
            np.array(ids, np.int64), np.stack([kf.T_cw for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
            tuple(kf.feats for kf in kfs),
            np.concatenate([kf.point_ids for kf in kfs]) if kfs else np.zeros(0, np.int64),
            np.r_[0, np.cumsum([len(kf.point_ids) for kf in kfs], dtype=np.int64)].astype(np.int64),
            p.pos[:n].copy(), p.desc[:n].copy(), p.octave[:n].copy(), ~p.bad[:n],
            self.layout_version, self.pose_epoch)

    def merge_point(self, src: int, dst: int) -> None:
        """Fuse point ``src`` into ``dst`` (a loop's duplicate): its observations move to ``dst``
        where the keyframe does not see ``dst`` yet, then ``src`` turns bad."""
        if src == dst or self._pts.bad[dst]:
            return
        for kf_id, i in list(self.observations[src].items()):
            kf = self.keyframes.get(kf_id)
            if kf is not None and kf_id not in self.observations[dst] and kf.point_ids[i] == src:
                self.observations[dst][kf_id] = i
                self._pts.n_obs[dst] += 1
                kf.point_ids[i] = dst
        self._pts.n_visible[dst] += self._pts.n_visible[src]
        self._pts.n_found[dst] += self._pts.n_found[src]
        self.set_bad(np.array([src]))
