"""The mapper's start, checkpoint writes and reporting, without ROS (core/mapper_service/mapper_start.py,
checkpoint_saver.py, reporting.py, keyframe_decisions.py): real sessions on the CPU, a recording
stand-in for the node's stats."""
from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from memgs_ros.core.mapper_service.checkpoint_saver import CheckpointSaver
from memgs_ros.core.mapper_service.keyframe_decisions import DecisionTimes
from memgs_ros.core.mapper_service.mapper_start import MapperStart, SessionOptions, start_mapper
from memgs_ros.core.mapper_service.reporting import IterationRate, report_failure
from memgs_ros.core.mapper_service.session import MappingSession
from memgs_ros.core.mapping.checkpoint import CheckpointFile
from memgs_ros.core.mapping.config import MappingConfig
from memgs_ros.core.merge.config import MergeConfig
from memgs_ros.core.runtime.replay import Pacing
from memgs_ros.core.runtime.stat_fields import Stat
from memgs_ros.core.runtime.worker import WorkerStopped
from memgs_ros.errors import ConfigError, DataError


class _Posts:
    """What a service posted, in order (the node's NodeStats applies the same later)."""

    def __init__(self) -> None:
        self.posted: list[tuple[str, str, object]] = []

    def post_add(self, stat: Stat[int], n: int = 1) -> None:
        self.posted.append(("count", stat.key, n))

    def post_set(self, stat: Stat[Any], value: object) -> None:
        self.posted.append(("gauge", stat.key, value))

    def post_problem(self, kind: str, message: str) -> None:
        self.posted.append(("problem", kind, message))

    def names(self, op: str) -> list[str]:
        return [name for o, name, _ in self.posted if o == op]


@pytest.fixture
def started() -> Iterator[list[MapperStart]]:
    """Starts made by a test; their sessions closed after it."""
    out: list[MapperStart] = []
    yield out
    for s in out:
        s.session.close(30.0)


def _start(started: list[MapperStart], **opts: object) -> MapperStart:
    s = start_mapper(MappingConfig(), MergeConfig(), "cpu", SessionOptions(**opts))  # type: ignore[arg-type]
    started.append(s)
    return s


def _saved_state(path: Path) -> None:
    """A checkpoint of an empty session at ``path``."""
    session = MappingSession(MappingConfig(), "cpu")
    try:
        CheckpointFile(path).write(session.state_dict().result(30))
    finally:
        session.close(30.0)


def test_a_mapper_without_a_checkpoint_starts_an_empty_free_running_session(started: list[MapperStart]) -> None:
    s = _start(started)
    assert (s.device, s.checkpoint, s.resumed, s.set_aside) == ("cpu", None, None, None)
    assert s.session.free_running and s.session.status.gaussians == 0 and s.raster.backend


def test_a_lockstep_mapper_resumes_from_its_checkpoint(tmp_path: Path, started: list[MapperStart]) -> None:
    path = tmp_path / "ck.npz"
    _saved_state(path)
    s = _start(started, pacing=Pacing.LOCKSTEP, checkpoint_path=str(path))
    assert s.resumed is not None and s.set_aside is None and s.checkpoint == CheckpointFile(path)
    assert not s.session.free_running
    ignored = _start(started, checkpoint_path=str(path), resume=False)  # the file stays, to be overwritten
    assert ignored.resumed is None and ignored.checkpoint is not None and path.exists()


def test_an_unreadable_checkpoint_is_set_aside_and_the_map_starts_empty(tmp_path: Path,
                                                                        started: list[MapperStart]) -> None:
    path = tmp_path / "ck.npz"
    path.write_bytes(b"not a checkpoint")
    s = _start(started, checkpoint_path=str(path))
    assert s.resumed is None and s.set_aside is not None and s.set_aside.startswith("cannot resume")
    assert not path.exists() and len(list(tmp_path.glob("ck.npz.unreadable-*"))) == 1


def test_a_checkpoint_the_session_refuses_is_set_aside(tmp_path: Path, started: list[MapperStart]) -> None:
    path = tmp_path / "ck.npz"
    session = MappingSession(MappingConfig(), "cpu")
    try:
        state = session.state_dict().result(30)
    finally:
        session.close(30.0)
    CheckpointFile(path).write(replace(state, extra={"keyframe_stamps": "not a table"}))  # readable, not takeable
    s = _start(started, checkpoint_path=str(path))
    assert s.resumed is None and s.set_aside is not None and "keyframe_stamps" in s.set_aside
    assert not path.exists()


def test_a_device_torch_does_not_know_is_refused_before_any_session() -> None:
    with pytest.raises(ConfigError, match="not a torch device"):
        start_mapper(MappingConfig(), MergeConfig(), "tpu:0", SessionOptions())


def test_checkpoint_writes_are_counted_and_skipped_when_nothing_changed(tmp_path: Path) -> None:
    session, posts = MappingSession(MappingConfig(), "cpu"), _Posts()
    try:
        assert CheckpointSaver(session, None, posts).save().result(30) is None  # no file: nothing to do
        saver = CheckpointSaver(session, CheckpointFile(tmp_path / "ck.npz"), posts)
        assert saver.save().result(30) == tmp_path / "ck.npz"
        assert posts.names("count") == ["checkpoints"]
        assert posts.names("gauge") == ["checkpoint_gaussians", "checkpoint_ms"]
        assert saver.save().result(30) is None  # unchanged since
        assert saver.save(force=True).result(30) == tmp_path / "ck.npz"
        assert saver.save_within(30.0) is None
        assert posts.names("problem") == []
    finally:
        session.close(30.0)


def test_a_failed_checkpoint_write_is_a_problem_not_an_exception_at_exit(tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("")  # the checkpoint's folder cannot be made
    session, posts = MappingSession(MappingConfig(), "cpu"), _Posts()
    saver = CheckpointSaver(session, CheckpointFile(tmp_path / "a_file" / "ck.npz"), posts)
    try:
        assert saver.save_within(30.0) is None  # the shutdown's save: the error is counted, not raised
        assert posts.names("problem") == ["checkpoint_failed"]
        with pytest.raises(OSError):
            saver.save(force=True).result(30)  # the future carries the error to a caller that waits
        assert posts.names("problem") == ["checkpoint_failed"] * 2
    finally:
        session.close(30.0)
    assert saver.save().result(0) is None  # the worker stopped: counted, resolved
    assert posts.names("problem") == ["checkpoint_failed"] * 3


def _finished(value: object = None, error: BaseException | None = None) -> Future:
    f: Future = Future()
    if error is None:
        f.set_result(value)
    else:
        f.set_exception(error)
    return f


def test_only_real_failures_of_unanswered_commands_are_reported() -> None:
    posts = _Posts()
    done = report_failure(posts, "update_poses")
    done(_finished(3))
    cancelled: Future = Future()
    cancelled.cancel()
    done(cancelled)
    done(_finished(error=WorkerStopped("closed")))  # the node is shutting down
    assert posts.posted == []
    done(_finished(error=DataError("keyframe 3 refused")))
    assert posts.posted == [("problem", "command_failed", "update_poses failed: DataError: keyframe 3 refused")]


def test_the_iteration_rate_is_measured_between_readings() -> None:
    rate = IterationRate(10.0)
    assert rate.update(11.0, 100) is None  # no earlier reading of the iteration
    assert rate.update(13.0, 150) == 25.0
    assert rate.update(13.0, 160) is None  # no time passed
    assert rate.update(14.0, 170) == 10.0


def test_decision_times_are_taken_once_and_bounded() -> None:
    d = DecisionTimes(limit=4, keep=2)
    d.decided(1, 111)
    assert d.take(1) == 111 and d.take(1) == 0  # taken once; 0: unknown
    for stamp in range(10, 16):
        d.decided(stamp, stamp * 10)
    assert d.take(99) == 0 and len(d) == 2  # bundles that never completed: the newest two stay
    assert d.take(15) == 150 and d.take(14) == 140
