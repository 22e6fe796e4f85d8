"""The mapping session: the one owner of the live Gaussian map (an actor).

A ``MappingSession`` owns a ``GaussianMapper`` (map, optimiser state, training keyframes), the
keyframe-stamp table and the delta outbox. One worker thread executes typed commands from one
queue, in the order they were submitted: insert a keyframe, update keyframe poses, rigidly
correct keyframes and their Gaussians, train N steps, cut a delta or snapshot, render a view,
capture state, finish. Every mutation happens on that worker; callers get a
``concurrent.futures.Future`` per command and readers get immutable values (records copied to
host memory, ``SessionStatus``). There are no locks around the map: nothing but the worker
touches it. Two jobs that need no map state leave the worker, so they overlap a training step on
another core: a keyframe's images are prepared (undistorted, resized, pyramid: a pure function of
the config, ``prepare_keyframe``) in the caller's thread, and map snapshots the worker cut are
diffed against what the receiver holds, encoded and published by the outbox, a second actor that
alone owns the delta outbox and sends in the order cut. Both are ``CommandWorker``s
(core/runtime/worker.py): an error in a command reaches its future, a failed training step is an event,
and a worker that stops or dies fails every pending future, the outbox's included.

Free-running (``free_running=True``): between commands the worker trains, one step at a time, so
a command waits at most for the step in progress. Acknowledged pacing: the worker trains only on ``train``
commands ("train N steps, then acknowledge"), the same code path, so a replay is deterministic.

Overload: at most ``insert_queue`` keyframe insertions wait in the queue (free-running only);
when one more arrives, the oldest waiting insertion is dropped whole, its future resolves to None,
and a ``keyframe_overload`` event reports it, as the mapper node did before.

Problems the worker meets (a keyframe it refuses, a failed training step, a dropped keyframe) are
queued as ``SessionEvent``s for the owner to report (``poll_events``): the worker never calls back
into a ROS node.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, replace
from typing import Any, TypeVar

import numpy as np
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.view import view_preparation
from memgs_ros.core.map_io.map_delta import DeltaOutbox
from memgs_ros.core.mapper_service.keyframe_timing import KeyframeTimings
from memgs_ros.core.mapper_service.session_records import (
    DeltaBatch,
    FinishResult,
    RenderedView,
    SessionCounts,
    SessionEvent,
    SessionStatus,
)
from memgs_ros.core.mapper_service.session_tally import SessionTally, StampedKeyframes
from memgs_ros.core.mapping.checkpoint import MapperCheckpoint
from memgs_ros.core.mapping.keyframes import KeyframeInput, TrainingKeyframe
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig, StepStats, prepare_keyframe
from memgs_ros.core.raster.values import render_rgb8
from memgs_ros.core.runtime.worker import BACKGROUND_ERROR_PAUSE_S, Command, CommandWorker, WorkerStopped
from memgs_ros.errors import DataError

logger = logging.getLogger(__name__)

T = TypeVar("T")

# A free-running worker with nothing to train (too few keyframes) waits this long for a command.
_IDLE_WAIT_S = 0.05
# A command that reaches a closed or dead session (or its outbox) fails with this.
SessionError = WorkerStopped


@dataclass(frozen=True)
class _Sent:
    """What the outbox thread has sent (replaced whole, so readers see one consistent value)."""

    seq: int = 0  # the last delta's sequence number
    pending_rows: int = 0  # changed rows not yet in a delta
    messages: int = 0  # deltas sent
    bytes: int = 0  # their size
    snapshots: int = 0  # full maps sent


@dataclass(frozen=True, eq=False)
class _OutboxJob:
    kind: str  # "delta" or "snapshot"
    records: GaussianRecords
    max_rows: int | None
    exact: bool
    publish: Callable[[np.ndarray], None] | None


class _Outbox(CommandWorker):
    """The actor that owns the delta outbox: diffs, encodes and publishes the snapshots the
    session's worker cut, in the order cut (one queue). ``sent`` is an immutable value."""

    def __init__(self, max_sh_degree: int, tolerance: float, epoch: int, niceness: int = 0) -> None:
        super().__init__("mapping-session-outbox", niceness)
        self._box = DeltaOutbox(max_sh_degree, tolerance, epoch=epoch)
        self.sent = _Sent()  # replaced whole by the worker
        self.start()

    def send(self, job: _OutboxJob) -> Future[Any]:
        return self.submit(job.kind, lambda: self._send(job))

    def _send(self, job: _OutboxJob) -> Any:
        box, sent = self._box, self.sent
        if job.kind == "snapshot":
            whole = box.snapshot(job.records)
            if job.publish is not None:
                job.publish(whole)
            self.sent = replace(sent, seq=box.seq, pending_rows=0, snapshots=sent.snapshots + 1)
            return whole, len(job.records), box.seq
        n = n_bytes = 0
        while (rows := box.next_delta(job.records, None if job.exact else job.max_rows,
                                      0.0 if job.exact else None)) is not None:
            n, n_bytes = n + 1, n_bytes + int(rows.nbytes)
            if job.publish is not None:
                job.publish(rows)
            if not job.exact:
                break
        self.sent = replace(sent, seq=box.seq, pending_rows=box.pending_rows, messages=sent.messages + n,
                            bytes=sent.bytes + n_bytes)
        return DeltaBatch(n, box.seq, box.epoch, box.pending_rows)


def _forward(src: Future[Any], dst: Future[Any], errors_only: bool = False) -> None:
    """When ``src`` is done, resolve ``dst`` the same way (if it is not already); with
    ``errors_only`` only a failure is passed on."""
    def done(f: Future[Any]) -> None:
        if dst.done():
            return
        err = f.exception()
        if err is not None:
            dst.set_exception(err)
        elif not errors_only:
            dst.set_result(f.result(0))  # done: never waits
    src.add_done_callback(done)


def _drain(q: queue.SimpleQueue[SessionEvent]) -> list[SessionEvent]:
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


class MappingSession(CommandWorker):
    """The one owner of a live Gaussian map (see module docstring).

    ``checkpoint``: a state to start from (``state_dict`` of an earlier session); ``delta_epoch`` /
    ``delta_tolerance``: the delta outbox's epoch and tolerance; ``merge_cfg``: the MergeConfig;
    ``niceness``: of the worker and outbox threads (and the kernel threads they start), so that a
    mapper sharing its process with the tracker still yields the cores to it.
    """

    def __init__(self, cfg: MappingConfig | None = None, device: torch.device | str = "cpu", *,
                 merge_cfg: Any = None, free_running: bool = True, insert_queue: int = 4,
                 delta_tolerance: float = 1e-3, delta_epoch: int = 0,
                 checkpoint: MapperCheckpoint | None = None, niceness: int = 0) -> None:
        if insert_queue < 1:
            raise DataError(f"insert_queue must be >= 1, got {insert_queue}")
        super().__init__("mapping-session", niceness)
        self.cfg = cfg if cfg is not None else MappingConfig()
        self.free_running = free_running
        self.insert_queue = int(insert_queue)
        self._mapper = GaussianMapper(self.cfg, device=device, merge_cfg=merge_cfg)
        self._device = self._mapper.device  # callers read this, never the mapper
        self._epoch = int(delta_epoch)
        self._render_camera: PinholeCamera | None = None
        self._finished = False
        self._interrupted = threading.Event()  # set from any thread: a finish in progress stops early
        self._training = free_running
        self._tally = SessionTally()
        self._counters = self._tally.counts
        self._keys = StampedKeyframes(self._mapper, self._counters)  # keyframe stamp -> id
        self._captured: tuple[int, int] | None = None  # (iteration, keyframes) of the last state_dict
        self._pending_inserts = 0  # changed under the worker's condition only
        self._events: queue.SimpleQueue[SessionEvent] = queue.SimpleQueue()
        self._intake = KeyframeTimings()
        self._iterations_final = 0
        if checkpoint is not None:
            self._load(checkpoint)
        self.resumed_stamps: frozenset[int] = frozenset(self._keys.ids)
        self._status = SessionStatus()
        self._publish_status()
        self._outbox = _Outbox(self.cfg.max_sh_degree, delta_tolerance, delta_epoch, niceness)
        self.start()

    # ------------------------------------------------------------------ readers
    @property
    def status(self) -> SessionStatus:
        """The latest status (an immutable value the worker replaces; only the worker reads the
        map: a caller reading tensors the worker resizes can crash the process) with the insert
        queue's length now."""
        sent = self._outbox.sent
        return replace(self._status, alive=self.alive and self._outbox.alive,
                       insert_queue=self._pending_inserts, delta_seq=sent.seq,
                       delta_pending_rows=sent.pending_rows,
                       counters=SessionCounts.with_outbox(self._status.counters, sent.messages, sent.bytes,
                                                          sent.snapshots))

    @property
    def device(self) -> torch.device:
        return self._device

    def poll_events(self) -> list[SessionEvent]:
        """Problems met since the last call, oldest first."""
        return _drain(self._events)

    # ----------------------------------------------------------------- commands
    def insert_keyframe(self, kf: KeyframeInput, received_cpu_s: float = 0.0) -> Future[int | None]:
        """Queue a keyframe. The future gives the Gaussians seeded, or None when the keyframe was
        refused (counted as an event), dropped for overload, or came after ``finish``.

        On the CPU the images are prepared here, in the caller's thread, overlapping the worker's
        training step; on a GPU the worker uploads the compact images and prepares them on the
        device between two steps. ``received_cpu_s``: CPU the caller spent receiving it (decoding
        the messages), added to the keyframe's intake time (``SessionStatus.intake_ms_*``)."""
        cpu0 = time.thread_time()
        prepared: TrainingKeyframe | None = None
        if self.device.type == "cpu":
            try:
                prepared = self._prepare(kf)
            except DataError as err:
                self._event("bad_keyframe", f"keyframe {kf.stamp_ns} refused: {err}")
                refused: Future[int | None] = Future()
                refused.set_result(None)
                return refused
        spent = received_cpu_s + time.thread_time() - cpu0
        cmd: Command[int | None] = Command("insert", lambda: self._insert(kf, prepared, spent))
        with self._condition:
            self._check_open()
            if self.free_running and self._pending_inserts >= self.insert_queue:
                oldest = self._drop_queued(lambda c: c.name == "insert")
                if oldest is not None:
                    self._pending_inserts -= 1
                    oldest.future.set_result(None)
                self._event("keyframe_overload", "mapper cannot keep up: a keyframe was dropped from its full "
                                                 "insert queue")
            self._append(cmd)
            self._pending_inserts += 1
        return cmd.future

    def update_poses(self, poses: Mapping[int, np.ndarray]) -> Future[int]:
        """Replace keyframe poses ({stamp_ns: T_wc [4, 4]}, e.g. bundle adjustment); the Gaussians
        stay. The future gives how many keyframes were updated (unknown and dropped ones are not)."""
        return self.submit("update_poses", lambda: self._keys.update_poses(dict(poses)))

    def retire_keyframes(self, stamps: list[int]) -> Future[tuple[int, int]]:
        """Keyframes the tracker culled (by stamp): out of training, their Gaussians handed on to the
        nearest kept keyframe (``GaussianMapper.retire_keyframes``). The future gives (retired,
        Gaussians handed on); unknown stamps are ignored."""
        return self.submit("retire", lambda: self._keys.retire(list(stamps)))

    def correct_keyframes(self, poses: Mapping[int, np.ndarray]) -> Future[tuple[int, int]]:
        """Rigidly move keyframes ({stamp_ns: corrected T_wc}) and the Gaussians anchored to them,
        then train them with priority (``GaussianMapper.correct_keyframes``). The future gives
        (keyframes corrected, Gaussians moved)."""
        return self.submit("correct", lambda: self._keys.correct(dict(poses)))

    def set_training(self, on: bool) -> Future[bool]:
        """Pause (False) or resume the free-running training between commands (a managed node's
        deactivate / activate); keyframes, deltas, renders and saves go on. Sessions of an acknowledged replay train
        by command only and are unchanged. The future gives whether it trains now."""
        def run() -> bool:
            self._training = bool(on) and self.free_running and not self._finished
            return self._training
        return self.submit("set_training", run)

    def train(self, iterations: int) -> Future[StepStats | None]:
        """Run ``iterations`` training steps now (nothing before ``ready``); the future gives the
        last step's stats. Acknowledged replays call this once per frame."""
        return self.submit("train", lambda: self._train(int(iterations)))

    def delta(self, max_rows: int | None, exact: bool = False,
              publish: Callable[[np.ndarray], None] | None = None) -> Future[DeltaBatch]:
        """The next map delta for the receiver: at most ``max_rows`` rows over the tolerance, or
        with ``exact`` every difference at tolerance 0 (repeated until nothing differs).

        The worker cuts a snapshot of the map; the outbox thread diffs it and calls
        ``publish(rows)`` for each message, in the order the snapshots were cut: messages leave in
        sequence order whichever threads asked for them."""
        return self._to_outbox("delta", max_rows, exact, publish)

    def snapshot_message(self, publish: Callable[[np.ndarray], None] | None = None
                         ) -> Future[tuple[np.ndarray, int, int]]:
        """The whole map as the next snapshot message (rows, Gaussian count, its seq); ``publish``
        as for ``delta``."""
        return self._to_outbox("snapshot", None, False, publish)

    def _to_outbox(self, kind: str, max_rows: int | None, exact: bool,
                   publish: Callable[[np.ndarray], None] | None) -> Future[Any]:
        out: Future[Any] = Future()

        def cut() -> None:  # on the worker: the snapshot is the only part that reads the map
            _forward(self._outbox.send(_OutboxJob(kind, self._mapper.snapshot(), max_rows, exact, publish)), out)

        _forward(self.submit(kind, cut), out, errors_only=True)  # a failed cut (or a dead worker) fails ``out``
        return out

    def snapshot(self) -> Future[GaussianRecords]:
        """The whole map as records (host copies)."""
        return self.submit("records", self._mapper.snapshot)

    def render(self, T_wc: np.ndarray, camera: PinholeCamera | None = None,
               publish: Callable[[RenderedView], None] | None = None) -> Future[RenderedView | None]:
        """Render the map from camera-to-world ``T_wc`` [4, 4] with ``camera`` (default: the
        prepared camera of the first keyframe). None before a keyframe or with an empty map.
        ``publish(view)`` is called on the worker when there is a view."""
        T = np.asarray(T_wc, dtype=np.float64)
        return self.submit("render", lambda: self._render(T, camera, publish))

    def state_dict(self, only_if_changed: bool = False) -> Future[MapperCheckpoint | None]:
        """Everything needed to resume (the mapper's state plus the keyframe-stamp table in
        ``extra["keyframe_stamps"]``), or None when ``only_if_changed`` and nothing changed since
        the last capture."""
        return self.submit("state_dict", lambda: self._state_dict(only_if_changed))

    def interrupt(self) -> None:
        """From any thread: a finish in progress (or to come) stops after the step it is in, so a
        node that is shutting down saves the map as trained so far within its stop deadline
        instead of waiting out the final iterations (minutes on a busy CPU)."""
        self._interrupted.set()

    def finish(self, final_iterations: int = 0, densify: bool = True,
               budget_s: float = 0.0, total_iterations: int = 0) -> Future[FinishResult]:
        """Run what is queued, stop free-running training, run ``final_iterations`` (once, on the
        keyframes there are, fewer than ``min_keyframes`` too; with ``densify=False`` they only
        refine, so the map does not grow at the end), and
        refuse keyframes from then on. Deltas, renders and state stay available.

        ``budget_s`` > 0 ends the final iterations once they have taken that long (checked after
        each, so at least one runs): a robot that must hand its map over by a deadline trades the
        last polish for time. ``total_iterations`` > 0 runs more final iterations while the map has
        trained fewer in all: a live run on a slow machine, which trained little while the camera
        moved, still gets the training an acknowledged replay's map had."""
        return self.submit("finish", lambda: self._finish(int(final_iterations), bool(densify), float(budget_s),
                                                          int(total_iterations)))

    def call(self, fn: Callable[[GaussianMapper], T]) -> Future[T]:
        """Run ``fn(mapper)`` on the worker (tests, benchmarks and tools that need the engine);
        it must not keep references to the mapper's tensors."""
        return self.submit("call", lambda: fn(self._mapper))

    def save_state(self, write: Callable[[MapperCheckpoint], T], only_if_changed: bool = False) -> Future[T | None]:
        """Capture the state (``state_dict``) and ``write(state)`` it, both on the worker: saves
        from several threads (a timer, a finish service) land in command order, so an older
        state never overwrites a newer one. None when ``only_if_changed`` and nothing changed."""
        def run() -> T | None:
            ckpt = self._state_dict(only_if_changed)
            return None if ckpt is None else write(ckpt)
        return self.submit("save_state", run)

    def close(self, timeout_s: float = 30.0, drain: bool = False) -> bool:
        """Stop the worker after the command or step in progress (queued commands fail with
        SessionError), then the outbox after sending every snapshot the worker cut; a cut that
        comes later (the worker outlived ``timeout_s``) fails its future. Idempotent."""
        stopped = super().close(timeout_s, drain)
        return self._outbox.close(timeout_s, drain=True) and stopped

    # ------------------------------------------------------------------- worker
    def _take(self, cmd: Command[Any]) -> None:
        if cmd.name == "insert":
            self._pending_inserts -= 1

    def _after_command(self, cmd: Command[Any]) -> None:
        self._publish_status()

    def _has_background(self) -> bool:
        return self._training and not self._finished

    def _background(self) -> float:
        # Live, training starts at live_min_keyframes (1): the map is for use in flight. Acknowledged
        # replays keep min_keyframes (their train commands), so they reproduce the offline schedule.
        st = self._mapper.step(min_keyframes=self.cfg.live_min_keyframes)
        if st is None:
            return _IDLE_WAIT_S
        self._after_step(st)
        return 0.0

    def _on_background_error(self, err: Exception) -> float:
        self._event("training_step", f"training step failed: {type(err).__name__}: {err}")
        return BACKGROUND_ERROR_PAUSE_S

    def _after_step(self, st: StepStats) -> None:
        self._intake.trained(st.kf_id)
        self._tally.step(st)
        self._publish_status()

    def _publish_status(self) -> None:
        self._status = self._tally.status(
            self._mapper, keyframes=len(self._keys.ids), keyframe_timing=self._intake.summary(),
            iterations_final=self._iterations_final, insert_queue=self._pending_inserts,
            finished=self._finished, render_camera=self._render_camera)

    def _event(self, kind: str, message: str) -> None:
        self._events.put(SessionEvent(kind, message))

    # --------------------------------------------------------- command bodies
    def _prepare(self, kf: KeyframeInput) -> TrainingKeyframe:
        return prepare_keyframe(self.cfg, self.device, -1, kf.stamp_ns, kf.T_wc, kf.rgb, kf.depth, kf.camera,
                                kf.depth_scale)

    def _insert(self, kf: KeyframeInput, prepared: TrainingKeyframe | None, spent_cpu_s: float) -> int | None:
        if self._finished:
            return None
        if kf.stamp_ns in self._keys.ids:
            self._counters.duplicate_keyframes += 1
            return None
        kf_id = len(self._keys.ids)
        t0, cpu0 = time.perf_counter(), time.thread_time()
        try:
            if prepared is None:  # on a GPU: uploaded and prepared here, between two steps
                with self._mapper.peaks.work("keyframe upload"):
                    prepared = self._prepare(kf)
            # Free-running, the budget is enforced by the next training step: an insertion that
            # must keep up with the tracker pays ~35 ms instead of ~180 ms on a 60k map (CPU).
            added = self._mapper.add_prepared_keyframe(replace(prepared, kf_id=kf_id), kf.points_w, kf.colors,
                                                       enforce_budget=not self.free_running)
        except DataError as err:
            self._event("bad_keyframe", f"keyframe {kf.stamp_ns} refused: {err}")
            return None
        self._keys.ids[kf.stamp_ns] = kf_id
        if self._render_camera is None:
            self._render_camera = view_preparation(kf.camera, self.cfg.resolution_scale).camera
        self._counters.keyframes += 1
        self._counters.seeded_gaussians += added
        self._counters.insert_ms_total += round(1e3 * (time.perf_counter() - t0))
        self._intake.inserted(kf_id, kf.decided_ns, 1e3 * (spent_cpu_s + time.thread_time() - cpu0))
        return added

    def _train(self, iterations: int) -> StepStats | None:
        t0 = time.perf_counter()
        last = None
        for _ in range(iterations):
            st = self._mapper.step()
            if st is None:
                break
            self._after_step(st)
            last = st
        # An acknowledged frame's training time: train_ms_total / train_commands.
        self._counters.train_commands += 1
        self._counters.train_ms_total += round(1e3 * (time.perf_counter() - t0))
        return last

    def _render(self, T_wc: np.ndarray, camera: PinholeCamera | None,
                publish: Callable[[RenderedView], None] | None) -> RenderedView | None:
        cam = camera if camera is not None else self._render_camera
        if cam is None or len(self._mapper.gmap) == 0:
            return None
        out = self._mapper.render(T_wc, cam)
        rgb = render_rgb8(out.color)
        view = RenderedView(np.ascontiguousarray(rgb), out.depth.cpu().numpy().astype(np.float32), cam)
        if publish is not None:
            publish(view)
        self._counters.renders += 1
        return view

    def _state_dict(self, only_if_changed: bool) -> MapperCheckpoint | None:
        version = (self._mapper.iteration, len(self._keys.ids))
        if only_if_changed and version == self._captured:
            return None
        ckpt = self._mapper.state_dict(self._keys.table())
        self._captured = version
        return ckpt

    def _load(self, ckpt: MapperCheckpoint) -> None:
        """Before the worker starts: the mapper's state and the stamp table."""
        self._keys.load(ckpt.extra)
        self._mapper.load_state_dict(ckpt)
        if ckpt.keyframes:
            self._render_camera = ckpt.keyframes[-1].camera  # prepared: undistorted and scaled
        self._captured = (self._mapper.iteration, len(self._keys.ids))

    def _finish(self, final_iterations: int, densify: bool, budget_s: float = 0.0,
                total_iterations: int = 0) -> FinishResult:
        t0 = time.perf_counter()
        ran = 0
        if not self._finished:
            self._training = False
            self._finished = True
            final_iterations = max(final_iterations, total_iterations - self._mapper.iteration)
            for _ in range(final_iterations):  # on whatever keyframes there are, even fewer than min_keyframes
                if self._interrupted.is_set():
                    break
                st = self._mapper.step(densify=densify, final=True)
                if st is None:
                    break
                self._iterations_final += 1
                self._after_step(st)
                ran += 1
                if budget_s > 0 and time.perf_counter() - t0 >= budget_s:
                    break
        return FinishResult(self._epoch, len(self._mapper.gmap), ran,
                            time.perf_counter() - t0)
