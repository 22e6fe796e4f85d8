"""The front-end's side of the back-end: requests out, corrections in, committed to its map.

``BackendLink`` lives on the tracking thread with the map it commits to. At each keyframe it
takes one ``MapSnapshot`` and asks the back-end for a local BA (deferred while the previous one
runs: each starts from its predecessor's result) and place recognition; at the start of each
frame (``poll``) it commits the results that have arrived: local BA refinements,
loop corrections (after which it asks for a global BA) and global BAs. A result computed
before another correction moved the map is stale and dropped (``pose_epoch``); one taken
before a compaction is renumbered or dropped (``layout_version``); one for an earlier map
segment is dropped. What it hands out (refined and loop-corrected keyframe poses, path
corrections, counters) is the tracker's to poll.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, wait
from dataclasses import dataclass
from typing import Any

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.backend.actor import GlobalBAOutcome, LocalBAOutcome, TrackingBackend
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.features.vocabulary import KeyframeDatabase
from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap
from memgs_ros.core.tracking.loop_closing.loops import LoopCorrection
from memgs_ros.core.tracking.loop_closing.place_recognition import LoopStats, PlaceOutcome

logger = logging.getLogger(__name__)

Moved = dict[int, tuple[np.ndarray, np.ndarray]]  # keyframe id -> (old T_cw, new T_cw)


@dataclass(frozen=True, eq=False)
class KeyframesMoved:
    """Keyframes a committed result moved; ``loop``: a loop correction or global BA (the tracker's
    last good pose moves too), else a local BA (only the pose tracking continues from)."""

    moved: Moved
    loop: bool


@dataclass(frozen=True, eq=False)
class _Request:
    kind: str  # "local_ba", "place" or "global_ba"
    segment_id: int
    future: Future[Any]


class BackendLink:
    """Requests in flight and the commit of their results (tracking thread only; see module docstring)."""

    def __init__(self, backend: TrackingBackend, cfg: TrackerConfig) -> None:
        self.backend, self.cfg = backend, cfg
        self.keyframe_db = KeyframeDatabase()  # the front-end's copy, for relocalisation
        self.stats = LoopStats()
        self.ba_runs = 0
        self.ba_refused = 0  # local BAs not committed: they moved their new keyframe too far
        self.ba_time_s = 0.0  # local BA time (threaded); every inline back-end second (acknowledged replay)
        self.refined: list[tuple[int, np.ndarray]] = []
        self.loop_refined: list[tuple[int, np.ndarray]] = []
        self.loop_done: list[dict[int, np.ndarray]] = []
        # Keyframe poses T_cw as the corrected path last saw them (creation, then each loop commit):
        # loop corrections are expressed against these, so the path also takes the local BA
        # refinements made since (frames were tracked near the keyframe's first pose).
        self._path_T_cw: dict[int, np.ndarray] = {}
        self._requests: deque[_Request] = deque()
        self._gba_followup_at: int | None = None  # keyframe id that triggers the follow-up global BA
        # The newest keyframe whose local BA waits for the one in flight: a BA must start from the
        # previous one's result, else it would overwrite that refinement with older poses.
        self._ba_deferred: tuple[int, int] | None = None  # (keyframe id, segment id)
        self._removed: set[int] = set()  # culled keyframes: never indexed again

    # ------------------------------------------------------------------ requests
    def keyframe_added(self, smap: SparseMap, kf: SparseKeyframe, segment_id: int) -> list[KeyframesMoved]:
        """Ask for the new keyframe's local BA and place recognition (and a due follow-up global
        BA). Inline, the results are committed at once and returned."""
        t0 = time.perf_counter()
        self._path_T_cw[kf.keyframe_id] = kf.T_cw.copy()
        want_ba = self.cfg.ba_enabled and len(smap.keyframes) >= 2
        if not want_ba and self.backend.places is None:
            return []
        snap = smap.snapshot()
        if want_ba and any(r.kind == "local_ba" for r in self._requests):
            self._ba_deferred = (kf.keyframe_id, segment_id)  # newest only: an older deferred one is covered
        elif want_ba:
            self._request("local_ba", segment_id, lambda: self.backend.local_ba(snap, kf.keyframe_id))
        if self.backend.places is not None:
            self._request("place", segment_id, lambda: self.backend.place_recognition(snap, kf.keyframe_id))
        due = self._gba_followup_at is not None and kf.keyframe_id >= self._gba_followup_at
        if due and not any(r.kind == "global_ba" for r in self._requests):
            # The keyframes made since the loop track against the old map: one more global BA
            # ties them (and the loop) in. Once per loop.
            self._gba_followup_at = None
            self._request("global_ba", segment_id, lambda: self.backend.global_ba(snap))
        if self.backend.threaded:
            return []
        moved = self.poll(smap, segment_id)
        self.ba_time_s += time.perf_counter() - t0
        return moved

    def keyframes_loaded(self, smap: SparseMap) -> None:
        """A loaded map's keyframes: the corrected path takes their poses as it saw them."""
        self._path_T_cw.update({k: kf.T_cw.copy() for k, kf in smap.keyframes.items()})

    def keyframes_removed(self, kf_ids: list[int], segment_id: int) -> None:
        """Keyframes culled from the map: out of both place-recognition databases (the back-end's
        when it next runs: an answer it sends for them meanwhile is not indexed here)."""
        self._removed.update(kf_ids)
        for k in kf_ids:
            self.keyframe_db.remove(k)
            self._path_T_cw.pop(k, None)
        if self.backend.places is not None:
            ids = tuple(kf_ids)
            self._request("forget", segment_id, lambda: self.backend.forget_keyframes(ids))

    def _request(self, kind: str, segment_id: int, make: Callable[[], Future[Any]]) -> None:
        try:
            self._requests.append(_Request(kind, segment_id, make()))
        except Exception as err:  # noqa: BLE001 - a back-end that stopped must not stop tracking
            logger.warning("tracking back-end refused %s: %s", kind, err)

    def _request_global_ba(self, smap: SparseMap, segment_id: int) -> None:
        if self.cfg.loop_global_ba_followup_keyframes > 0 and self._gba_followup_at is None:
            self._gba_followup_at = max(smap.keyframes) + self.cfg.loop_global_ba_followup_keyframes
        snap = smap.snapshot()
        self._request("global_ba", segment_id, lambda: self.backend.global_ba(snap))

    # ------------------------------------------------------------------ results
    def poll(self, smap: SparseMap, segment_id: int) -> list[KeyframesMoved]:
        """Commit every result that has arrived, in request order, then ask for a deferred local BA;
        returns what moved."""
        out: list[KeyframesMoved] = []
        while True:
            ready = [r for r in self._requests if r.future.done()]
            if not ready:
                self._request_deferred_ba(smap, segment_id)
                return out
            for r in ready:
                self._requests.remove(r)
                try:
                    result = r.future.result(0)  # ready: never waits
                except Exception as err:  # noqa: BLE001 - a failed refinement must not kill tracking
                    logger.warning("tracking back-end %s failed: %s: %s", r.kind, type(err).__name__, err)
                    continue
                moved = self._commit(smap, r, segment_id, result)
                if moved is not None:
                    out.append(moved)

    def _request_deferred_ba(self, smap: SparseMap, segment_id: int) -> None:
        """Ask for the deferred local BA once none is in flight, on a snapshot that has the last one."""
        if self._ba_deferred is None or any(r.kind == "local_ba" for r in self._requests):
            return
        (kf_id, segment), self._ba_deferred = self._ba_deferred, None
        if segment == segment_id and kf_id in smap.keyframes:
            snap = smap.snapshot()
            self._request("local_ba", segment_id, lambda: self.backend.local_ba(snap, kf_id))

    def in_flight(self, kinds: frozenset[str]) -> bool:
        """Whether a request of ``kinds`` is still unanswered (never, with the back-end inline)."""
        return any(r.kind in kinds and not r.future.done() for r in self._requests)

    def wait(self, smap: SparseMap, segment_id: int, kinds: frozenset[str], timeout_s: float) -> list[KeyframesMoved]:
        """Block until the requests of ``kinds`` are answered (new ones included: a committed loop
        asks for a global BA), committing every result; gives up after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        out = self.poll(smap, segment_id)
        while True:
            pending = [r.future for r in self._requests if r.kind in kinds]
            if not pending or time.monotonic() >= deadline:
                return out
            wait(pending, timeout=deadline - time.monotonic())
            out += self.poll(smap, segment_id)

    def close(self) -> None:
        """Stop the back-end; unanswered requests are dropped (their futures fail)."""
        self.backend.close()
        self._requests.clear()

    def _commit(self, smap: SparseMap, r: _Request, segment_id: int, result: object) -> KeyframesMoved | None:
        if isinstance(result, PlaceOutcome):
            if result.bow is not None and result.kf_id not in self._removed:
                self.keyframe_db.add(result.kf_id, result.bow)  # every segment's: relocalisation filters by the map
            self.stats = self.stats.plus(result.stats)
            if result.loop is None or r.segment_id != segment_id:
                return None
            return self._commit_loop(smap, result.loop, segment_id)
        if isinstance(result, GlobalBAOutcome):
            self.stats = self.stats.plus(result.stats)
            if result.correction is None or r.segment_id != segment_id:
                return None
            return self._commit_loop(smap, result.correction, segment_id)
        if isinstance(result, LocalBAOutcome) and r.segment_id == segment_id:
            return self._commit_local_ba(smap, result)
        return None

    def _commit_local_ba(self, smap: SparseMap, res: LocalBAOutcome) -> KeyframesMoved | None:
        if res.shift_refused:
            self.ba_refused += 1
            return None
        moved = smap.commit_refinement(list(res.kf_ids), res.T_cw, res.point_ids, res.points_w, list(res.outliers),
                                       layout_version=res.layout_version, pose_epoch=res.pose_epoch)
        if not moved:
            return None  # a loop correction came in between: this result is stale
        self.refined.extend((k, invert_pose(new)) for k, (_, new) in sorted(moved.items()))
        self.ba_runs += 1
        if self.backend.threaded:
            self.ba_time_s += res.time_s
        return KeyframesMoved(moved, loop=False)

    def _commit_loop(self, smap: SparseMap, c: LoopCorrection, segment_id: int) -> KeyframesMoved | None:
        """Keyframes and points move, the loop's duplicate points fuse; a loop asks for a global BA."""
        moved = commit_correction(smap, c)
        if moved is None:
            self.stats = self.stats.plus(LoopStats(global_ba_discarded=1))  # another correction came first
            return None
        self.loop_refined.extend((k, invert_pose(new)) for k, (_, new) in sorted(moved.items()))
        # T_wc_new T_cw_path: the path's frames move with their keyframe, BA refinements included.
        self.loop_done.append({k: invert_pose(new) @ self._path_T_cw.get(k, old) for k, (old, new) in moved.items()})
        self._path_T_cw.update((k, new.copy()) for k, (_, new) in moved.items())
        self._path_T_cw = {k: T for k, T in self._path_T_cw.items() if k in smap.keyframes}
        if c.is_global_ba:
            self.stats = self.stats.plus(LoopStats(global_ba_runs=1))
        else:
            self.stats = self.stats.plus(LoopStats(loops_accepted=1, last_loop=(c.query_id, c.candidate_id)))
            if self.cfg.loop_global_ba:
                self._request_global_ba(smap, segment_id)
        return KeyframesMoved(moved, loop=True)


class BackendResults:
    """What a tracker hands out of its back-end link (``_link``, set by the tracker): the
    ``Tracker`` protocol's BA counters and its polls of refined and loop-corrected keyframes."""

    _link: BackendLink

    @property
    def ba_time_s(self) -> float:
        """Seconds of local BA so far (threaded), or of all back-end work done inline (acknowledged replay)."""
        return self._link.ba_time_s

    @ba_time_s.setter
    def ba_time_s(self, value: float) -> None:  # the Tracker protocol's attribute is writeable
        self._link.ba_time_s = value

    @property
    def ba_runs(self) -> int:
        return self._link.ba_runs

    @property
    def ba_refused(self) -> int:
        """Local BAs not committed because they moved their new keyframe too far (``ba_max_shift_ratio``)."""
        return self._link.ba_refused

    @property
    def loop_stats(self) -> LoopStats:
        return self._link.stats

    def poll_refined_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe_id, refined T_wc [4, 4]) from local BA since the last poll, oldest first:
        small refinements the mapper takes as new training poses (its Gaussians stay)."""
        out, self._link.refined = self._link.refined, []
        return out

    def poll_loop_corrected_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe_id, corrected T_wc [4, 4]) of every keyframe a loop closure moved, since the
        last poll, oldest first: the mapper moves each keyframe's Gaussians with it."""
        out, self._link.loop_refined = self._link.loop_refined, []
        return out

    def poll_loop_corrections(self) -> list[dict[int, np.ndarray]]:
        """Loop corrections committed since the last poll, oldest first: {keyframe_id: D [4, 4]}
        with D = T_wc_new T_wc_old^-1 the keyframe's world-frame correction (``AnchoredPath``)."""
        out, self._link.loop_done = self._link.loop_done, []
        return out

    def close(self) -> None:
        """Stop the back-end; requests it has not answered are dropped (idempotent)."""
        self._link.close()


def commit_correction(smap: SparseMap, c: LoopCorrection) -> Moved | None:
    """Apply a loop correction or global BA to ``smap``; None when stale (its ``pose_epoch`` is not
    the map's). Returns {keyframe id: (old T_cw, new T_cw)}."""
    if c.pose_epoch is not None and c.pose_epoch != smap.pose_epoch:
        return None
    kf_ids, D = _correction_table(smap, c)
    q = int(np.flatnonzero(c.kf_ids == c.query_id)[0])
    moved = smap.apply_loop_correction(kf_ids, D, c.D[q], newer_than=c.query_id)
    if c.point_ids is not None and c.points_w is not None:  # global BA: its points, then drop its outliers
        smap.commit_refinement([], np.zeros((0, 4, 4)), c.point_ids, c.points_w, list(c.outliers),
                               layout_version=c.layout_version)
    olds = smap.renumber(c.fuse_points, c.layout_version)
    fuse_kf = c.fuse_kf if c.fuse_kf is not None else np.full(len(c.fuse_kp), c.query_id, np.int64)
    if olds is not None:
        for k, kp, old in zip(fuse_kf.tolist(), c.fuse_kp.tolist(), olds.tolist()):
            fkf = smap.keyframes.get(k)
            if fkf is None or old < 0 or not smap.good(np.array([old]))[0]:
                continue
            cur = int(fkf.point_ids[kp])
            if cur >= 0 and cur != old:
                smap.merge_point(cur, old)
            elif cur < 0 and k not in smap.observations[old]:
                smap.add_observations(np.array([old]), k, np.array([kp]))
    return moved


def _correction_table(smap: SparseMap, c: LoopCorrection) -> tuple[np.ndarray, np.ndarray]:
    """World-frame corrections (ids [M], D [M, 4, 4]) for ``c`` at commit time.

    A global BA's poses replace the current ones (local BA results since its snapshot are
    superseded). Keyframes made after the snapshot take the correction of the snapshot keyframe
    they share most points with: after a loop they track against the old map, which a
    correction barely moves, not against the query keyframe.
    """
    ids, D = c.kf_ids, c.D
    if c.T_wc_new is not None:
        cur = np.stack([smap.keyframes[k].T_cw if k in smap.keyframes else invert_pose(T)
                        for k, T in zip(ids.tolist(), c.T_wc_new)])
        D = c.T_wc_new @ cur
    table = {k: n for n, k in enumerate(ids.tolist())}
    extra_ids, extra_D = [], []
    for k, kf in smap.keyframes.items():
        if k in table or k <= c.query_id:
            continue
        counts: dict[int, int] = {}
        for pid in kf.point_ids[kf.point_ids >= 0].tolist():
            for o in smap.observations[pid]:
                if o in table:
                    counts[o] = counts.get(o, 0) + 1
        if counts:
            extra_ids.append(k)
            extra_D.append(D[table[max(counts, key=counts.__getitem__)]])
    if extra_ids:
        ids = np.concatenate([ids, np.array(extra_ids, np.int64)])
        D = np.concatenate([D, np.stack(extra_D)])
    return ids, D


__all__ = ["BackendLink", "BackendResults", "KeyframesMoved", "commit_correction"]
