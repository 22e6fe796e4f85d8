"""The tracker's back-end actor: local BA, place recognition, loop closing and global BA.

``TrackingBackend`` is a ``CommandWorker``: the front-end submits requests, each with an
immutable ``MapSnapshot`` of its map, and gets a ``Future`` per request whose result is a
correction (``LocalBAOutcome``, ``PlaceOutcome``, ``GlobalBAOutcome``). The front-end, which owns
the map, commits them at its next frame. The back-end's own state (keyframe database, loop
detector, the global BA in progress) is touched by its worker thread only.

Scheduling, on the one thread:

- requests run in order; a local BA request that is still queued when a newer one arrives is
  superseded (its future gives None): only the newest keyframe's window matters;
- a global BA runs one Levenberg-Marquardt iteration at a time as the worker's background work,
  so local BA and place recognition go on between its iterations; a newer global BA request
  supersedes the one in progress (whose result would be stale).

Without a thread (``threaded=False``: acknowledged replays, tests, benchmarks) every request runs
inline inside ``submit``, background work included, so results are deterministic.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.runtime.worker import CommandWorker, WorkerStopped
from memgs_ros.core.tracking.backend.ba_problem import SnapshotProblem, global_problem, local_problem
from memgs_ros.core.tracking.backend.bundle_adjustment import (
    BAAux,
    BAGeometry,
    BAState,
    camera_shift_ratio,
    local_bundle_adjustment,
)
from memgs_ros.core.tracking.backend.global_ba import global_ba_iterations
from memgs_ros.core.tracking.backend.lm import LMProgress
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.features.vocabulary import BowVector, Vocabulary
from memgs_ros.core.tracking.frontend.map_snapshot import MapSnapshot
from memgs_ros.core.tracking.loop_closing.loops import LoopCorrection
from memgs_ros.core.tracking.loop_closing.place_recognition import LoopStats, PlaceOutcome, PlaceRecognition

logger = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True, eq=False)
class LocalBAOutcome:
    """A local BA result: free keyframes ``kf_ids`` [F] with T_cw [F, 4, 4]; point_ids [P] with
    points_w [P, 3] (numbered at ``layout_version``); outlier (point id, keyframe id) observations;
    ``pose_epoch`` of the snapshot (stale after a loop correction); time_s spent."""

    kf_ids: tuple[int, ...]
    T_cw: np.ndarray
    point_ids: np.ndarray
    points_w: np.ndarray
    outliers: tuple[tuple[int, int], ...]
    layout_version: int
    pose_epoch: int
    time_s: float
    # Not to be committed: it moved the new keyframe over ``ba_max_shift_ratio`` (this ratio).
    shift_refused: float = 0.0


@dataclass(frozen=True, eq=False)
class GlobalBAOutcome:
    """A global BA's correction (None: superseded, too small a map or no improvement) and counters."""

    correction: LoopCorrection | None
    stats: LoopStats


@dataclass(eq=False)
class _GlobalBAJob:
    """The global BA in progress (worker thread only)."""

    sp: SnapshotProblem
    geometry: BAGeometry
    iterations: Iterator[LMProgress[BAState, BAAux]]
    done: Future[GlobalBAOutcome]
    last: LMProgress[BAState, BAAux] | None = None
    spent_s: float = 0.0


# The back-end's thread yields the core to the frame path (tracking is the real-time job; BA,
# place recognition and loop closing take what is left, like the mapper).
BACKEND_NICENESS = 5


class TrackingBackend(CommandWorker):
    """See the module docstring. ``vocabulary`` None: no place recognition; ``loop_closure``:
    look for loops (RGB-D); ``ba_fixed_count``: window keyframes fixed when none outside is."""

    def __init__(self, cfg: TrackerConfig, K: np.ndarray, bf: float, image_size: tuple[int, int],
                 inv_sigma_levels: np.ndarray, vocabulary: Vocabulary | None, loop_closure: bool,
                 ba_fixed_count: int, threaded: bool) -> None:
        super().__init__("memgs-tracking-backend", niceness=BACKEND_NICENESS)
        self.cfg, self.K, self.bf, self.inv_sigma_levels = cfg, K, bf, inv_sigma_levels
        self.ba_fixed_count = ba_fixed_count
        self.threaded = threaded
        self.places = None if vocabulary is None else PlaceRecognition(
            cfg, vocabulary, K, bf, image_size, inv_sigma_levels, loop_closure)
        self._gba: _GlobalBAJob | None = None
        if threaded:
            self.start()

    # ------------------------------------------------------------------ requests
    def local_ba(self, snap: MapSnapshot, kf_id: int) -> Future[LocalBAOutcome | None]:
        """Local BA around keyframe ``kf_id``; None when superseded or nothing improved."""
        older = self._drop_queued(lambda c: c.name == "local_ba") if self.threaded else None
        if older is not None:
            older.future.set_result(None)  # superseded: the newer window covers this keyframe
        return self.submit("local_ba", lambda: self._local_ba(snap, kf_id))

    def place_recognition(self, snap: MapSnapshot, kf_id: int) -> Future[PlaceOutcome]:
        """Index keyframe ``kf_id`` and look for a loop (every keyframe, in order)."""
        if self.places is None:
            raise WorkerStopped(f"{self.name} has no vocabulary: place recognition is off")
        places = self.places
        return self.submit("place_recognition", lambda: places.process(snap, kf_id))

    def forget_keyframes(self, kf_ids: tuple[int, ...]) -> Future[None]:
        """Keyframes culled from the map leave the keyframe database (and are never indexed)."""
        places = self.places
        if places is None:
            raise WorkerStopped(f"{self.name} has no vocabulary: place recognition is off")
        return self.submit("forget", lambda: places.forget(kf_ids))

    def load_places(self, vectors: list[tuple[int, BowVector]]) -> Future[None] | None:
        """A loaded map's keyframe vectors into the loop-search database (None: no place recognition)."""
        places = self.places
        if places is None:
            return None
        return self.submit("load_places", lambda: places.load(vectors))

    def global_ba(self, snap: MapSnapshot) -> Future[GlobalBAOutcome]:
        """Global BA of the whole snapshot, run between other requests; a LoopCorrection with the
        new poses and points (``is_global_ba``) when it lowered the cost."""
        done: Future[GlobalBAOutcome] = Future()
        started = self.submit("global_ba", lambda: self._start_global_ba(snap, done))
        started.add_done_callback(lambda f: _forward_failure(f, done))
        return done

    # ------------------------------------------------------------------ worker side
    def submit(self, name: str, run: Callable[[], T]) -> Future[T]:
        """Queue ``run`` (threaded), or run it now with any background work it starts (inline)."""
        if self.threaded:
            return super().submit(name, run)
        self._check_open()
        future: Future[T] = Future()
        try:
            future.set_result(run())
        except Exception as err:  # noqa: BLE001 - handed to the caller through its future, as threaded
            future.set_exception(err)
        while self._has_background():
            self._background()
        return future

    @property
    def alive(self) -> bool:
        return super().alive if self.threaded else not self._closed

    def close(self, timeout_s: float = 30.0, drain: bool = False) -> bool:
        """Stop the worker; queued requests (unless ``drain``) and a global BA in progress fail
        with WorkerStopped (the latter once the thread has ended: until then it is the worker's)."""
        ended = super().close(timeout_s, drain)
        if not ended:
            return False
        job, self._gba = self._gba, None
        if job is not None and not job.done.done():
            job.done.set_exception(WorkerStopped(f"{self.name} closed before the global BA finished"))
        return ended

    def _local_ba(self, snap: MapSnapshot, kf_id: int) -> LocalBAOutcome | None:
        t0 = time.perf_counter()
        cfg = self.cfg
        sp = local_problem(snap, kf_id, cfg.ba_window, self.ba_fixed_count, self.inv_sigma_levels)
        if sp is None:
            return None
        res = local_bundle_adjustment(sp.problem, self.K, self.bf, cfg.ba_huber_px, cfg.ba_max_iterations)
        if not np.isfinite(res.final_cost) or res.final_cost > res.initial_cost:
            return None
        free = ~sp.problem.fixed
        out = LocalBAOutcome(tuple(c for c, f in zip(sp.cams, free) if f), res.T_cw[free], sp.point_ids,
                             res.points_w, sp.outliers(res.obs_inlier), sp.layout_version, sp.pose_epoch,
                             time.perf_counter() - t0)
        if cfg.ba_max_shift_ratio > 0 and cfg.mode == "rgbd" and kf_id in sp.cams:
            ratio = camera_shift_ratio(sp.problem, res.T_cw, sp.cams.index(kf_id))
            if ratio > cfg.ba_max_shift_ratio:
                logger.debug("local BA of keyframe %d not committed: it moved the keyframe %.3f of its "
                             "median depth", kf_id, ratio)
                return replace(out, shift_refused=ratio)
        return out

    def _start_global_ba(self, snap: MapSnapshot, done: Future[GlobalBAOutcome]) -> None:
        if self._gba is not None:  # a newer snapshot: the older result would be discarded at commit
            self._gba.done.set_result(GlobalBAOutcome(None, LoopStats(global_ba_discarded=1)))
            self._gba = None
        t0 = time.perf_counter()
        sp = global_problem(snap, self.inv_sigma_levels)
        if sp is None:
            done.set_result(GlobalBAOutcome(None, LoopStats()))
            return
        cfg = self.cfg
        g, iterations = global_ba_iterations(sp.problem, self.K, self.bf, cfg.ba_huber_px,
                                             cfg.loop_global_ba_iterations)
        self._gba = _GlobalBAJob(sp, g, iterations, done, spent_s=time.perf_counter() - t0)

    def _has_background(self) -> bool:
        return self._gba is not None

    def _background(self) -> float:
        """One global BA iteration; the result once it stops or its time budget is spent."""
        job = self._gba
        assert job is not None
        t0 = time.perf_counter()
        try:
            progress = next(job.iterations, None)
            job.spent_s += time.perf_counter() - t0
            if progress is not None:
                job.last = progress
            if progress is None or job.spent_s > self.cfg.loop_global_ba_budget_s:
                self._gba = None
                job.done.set_result(self._finish_global_ba(job))
        except Exception as err:  # noqa: BLE001 - a failed global BA must not end the worker
            self._gba = None
            logger.warning("global bundle adjustment failed: %s", err)
            job.done.set_exception(err)
        return 0.0

    def _finish_global_ba(self, job: _GlobalBAJob) -> GlobalBAOutcome:
        assert job.last is not None
        res = job.geometry.result(job.last)
        sp, dt = job.sp, job.spent_s
        if not np.isfinite(res.final_cost) or res.final_cost >= res.initial_cost:
            return GlobalBAOutcome(None, LoopStats(global_ba_discarded=1, global_ba_time_s=dt))
        ids = np.array(sp.cams, np.int64)
        T_cw_old = sp.problem.T_cw
        D = invert_pose(res.T_cw) @ T_cw_old  # T_wc_new T_cw_old: world-frame corrections (snapshot)
        logger.info("global BA: %d keyframes %d points %d observations, cost %.0f -> %.0f in %.2f s",
                    len(ids), len(sp.point_ids), len(sp.problem.obs_cam), res.initial_cost, res.final_cost, dt)
        correction = LoopCorrection(ids, D, int(ids[-1]), -1, np.zeros(0, np.int64), np.zeros(0, np.int64),
                                    sp.layout_version, 0, dt, sp.point_ids, res.points_w,
                                    sp.outliers(res.obs_inlier), sp.pose_epoch, invert_pose(res.T_cw))
        return GlobalBAOutcome(correction, LoopStats(global_ba_time_s=dt))


def _forward_failure(started: Future[None], done: Future[GlobalBAOutcome]) -> None:
    """A global BA request that never started (worker closed or dead) fails its result future too."""
    err = WorkerStopped("the global BA request was cancelled") if started.cancelled() else started.exception()
    if err is not None and not done.done():
        done.set_exception(err)


__all__ = ["GlobalBAOutcome", "LocalBAOutcome", "TrackingBackend"]
