"""The mapper's checkpoint writes, without ROS: the session's state captured and written on its
worker (so saves from a timer, the finish service and the shutdown land in command order and an
older state never overwrites a newer one), what they cost in the stats, and their failures."""
from __future__ import annotations

import time
from concurrent.futures import Future
from pathlib import Path
from typing import TypeVar

from memgs_ros.core.mapper_service.reporting import StatsPoster
from memgs_ros.core.mapper_service.session import MappingSession
from memgs_ros.core.mapping.checkpoint import CheckpointFile, MapperCheckpoint
from memgs_ros.core.runtime.telemetry_fields import MapperFields
from memgs_ros.core.runtime.worker import WorkerStopped
from memgs_ros.errors import DataError

__all__ = ["CheckpointSaver"]

T = TypeVar("T")


def _resolved(value: T) -> Future[T]:
    f: Future[T] = Future()
    f.set_result(value)
    return f


class CheckpointSaver:
    """Writes ``session``'s state to ``file`` (None: this mapper keeps no checkpoint), counted in
    ``posts`` (``checkpoints``, ``checkpoint_gaussians``, ``checkpoint_ms``;
    ``problem.checkpoint_failed``)."""

    def __init__(self, session: MappingSession, file: CheckpointFile | None, posts: StatsPoster) -> None:
        self.session, self.file, self._posts = session, file, posts

    def save(self, force: bool = False) -> Future[Path | None]:
        """Write the state atomically when it changed since the last write (``force``: anyway).
        The future gives the path, or None (unchanged, no checkpoint file, or failed: counted)."""
        ckpt = self.file
        if ckpt is None:
            return _resolved(None)
        posts, t0 = self._posts, time.perf_counter()

        def write(state: MapperCheckpoint) -> Path:  # on the session's worker
            ckpt.write(state)
            posts.post_add(MapperFields.checkpoints)
            posts.post_set(MapperFields.checkpoint_gaussians, len(state.gaussians))
            posts.post_set(MapperFields.checkpoint_ms, round((time.perf_counter() - t0) * 1e3, 1))
            return ckpt.path

        def failed(f: Future[Path | None]) -> None:
            err = None if f.cancelled() else f.exception()
            if err is not None:
                posts.post_problem("checkpoint_failed", f"could not write checkpoint {ckpt.path}: {err}")

        try:
            saved = self.session.save_state(write, only_if_changed=not force)
        except WorkerStopped as err:
            posts.post_problem("checkpoint_failed", f"could not write checkpoint {ckpt.path}: {err}")
            return _resolved(None)
        saved.add_done_callback(failed)
        return saved

    def save_within(self, timeout_s: float) -> Path | None:
        """``save()`` and wait at most ``timeout_s`` for it (a node's stop has a deadline): the
        path, or None (unchanged, none, or failed: counted). TimeoutError when it took longer."""
        try:
            return self.save().result(timeout=timeout_s)
        except TimeoutError:  # an OSError: told apart first
            raise
        except (OSError, DataError, WorkerStopped):  # counted by save
            return None
