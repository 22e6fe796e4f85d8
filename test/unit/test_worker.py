"""The command worker (core/runtime/worker.py) and the mapping session's hazards it removes: no future
ever hangs, whatever a command, a training step or the worker itself does.

Every wait here is bounded: on the code before the worker base these tests failed by timing
out where a future never resolved."""
from __future__ import annotations

import threading
import time
from concurrent.futures import Future

import numpy as np
import pytest
from test_session import _cfg, _kf, frames  # noqa: F401 - frames is a fixture

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.mapper_service.session import MappingSession, SessionError
from memgs_ros.core.mapping.mapper import GaussianMapper
from memgs_ros.core.runtime.worker import CommandWorker, WorkerStopped

WAIT_S = 20.0


class _Counter(CommandWorker):
    """A worker whose background work counts, and fails when told to."""

    def __init__(self) -> None:
        super().__init__("counter")
        self.count = 0
        self.fail_background: Exception | None = None
        self.background_errors: list[Exception] = []
        self.running = True
        self.start()

    def _has_background(self) -> bool:
        return self.running

    def _background(self) -> float:
        if self.fail_background is not None:
            raise self.fail_background
        self.count += 1
        return 0.001

    def _on_background_error(self, err: Exception) -> float:
        self.background_errors.append(err)
        return 0.01


def test_command_errors_reach_their_future_and_the_worker_goes_on() -> None:
    w = _Counter()
    try:
        bad = w.submit("bad", lambda: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            bad.result(WAIT_S)
        assert w.submit("ok", lambda: 42).result(WAIT_S) == 42 and w.alive
    finally:
        w.close()


def test_background_errors_go_to_the_hook_and_commands_still_run() -> None:
    w = _Counter()
    try:
        w.fail_background = ValueError("a step failed")
        deadline = time.monotonic() + WAIT_S
        while not w.background_errors and time.monotonic() < deadline:
            time.sleep(0.01)
        assert isinstance(w.background_errors[0], ValueError)
        assert w.submit("read", lambda: "still here").result(WAIT_S) == "still here"
        w.fail_background = None
        n = w.submit("count", lambda: w.count).result(WAIT_S)
        deadline = time.monotonic() + WAIT_S
        while w.submit("count", lambda: w.count).result(WAIT_S) <= n and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.alive
    finally:
        w.close()


def test_a_dying_worker_fails_every_pending_future_and_refuses_new_ones() -> None:
    class Fragile(_Counter):
        def _after_command(self, cmd) -> None:  # noqa: ANN001
            if cmd.name == "poison":
                raise RuntimeError("bug in a hook")

    w = Fragile()
    gate = threading.Event()
    blocker = w.submit("block", lambda: gate.wait(WAIT_S))
    poison = w.submit("poison", lambda: None)
    queued = [w.submit(f"q{i}", lambda: None) for i in range(3)]
    gate.set()
    assert blocker.result(WAIT_S) is True
    assert poison.result(WAIT_S) is None  # the command itself ran; the hook after it killed the loop
    for f in queued:
        with pytest.raises(WorkerStopped, match="died: RuntimeError: bug in a hook"):
            f.result(WAIT_S)
    assert not w.alive and isinstance(w.death, RuntimeError)
    with pytest.raises(WorkerStopped, match="died"):
        w.submit("late", lambda: None)


def test_close_fails_queued_commands_or_drains_them() -> None:
    for drain in (False, True):
        w = _Counter()
        w.running = False
        gate = threading.Event()
        w.submit("block", lambda: gate.wait(WAIT_S))
        queued = [w.submit(f"q{i}", lambda i=i: i) for i in range(3)]
        closer = threading.Thread(target=w.close, kwargs={"drain": drain})
        closer.start()
        deadline = time.monotonic() + WAIT_S
        while w.alive and time.monotonic() < deadline:  # until close() has shut the queue
            time.sleep(0.005)
        gate.set()
        closer.join(WAIT_S)
        if drain:
            assert [f.result(WAIT_S) for f in queued] == [0, 1, 2]
        else:
            for f in queued:
                with pytest.raises(WorkerStopped, match="closed"):
                    f.result(WAIT_S)
        assert not w.alive
        with pytest.raises(WorkerStopped, match="closed"):
            w.submit("late", lambda: None)


def test_close_with_a_stuck_command_fails_what_is_queued_behind_it() -> None:
    w = _Counter()
    w.running = False
    gate = threading.Event()
    w.submit("stuck", lambda: gate.wait(WAIT_S))
    behind = w.submit("behind", lambda: None)
    assert w.close(timeout_s=0.1, drain=True) is False  # the stuck command outlived the timeout
    with pytest.raises(WorkerStopped):
        behind.result(WAIT_S)
    gate.set()


# ------------------------------------------------------------------ the mapping session's hazards


def test_a_value_error_in_a_free_running_step_is_an_event_not_a_dead_worker(
        frames: list[Frame], monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: the worker caught only DataError/RuntimeError around a free step, so a ValueError
    (e.g. from rasterize) ended the thread silently and every later future hung."""
    s = MappingSession(_cfg(), free_running=True)
    try:
        for i, f in enumerate(frames[:3]):
            s.insert_keyframe(_kf(f, 100 + i)).result(WAIT_S)
        real_step = GaussianMapper.step
        calls = {"n": 0}

        def flaky(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
            calls["n"] += 1
            if calls["n"] <= 2:
                raise ValueError("rasterize: bad input")
            return real_step(self, *a, **k)

        monkeypatch.setattr(GaussianMapper, "step", flaky)
        deadline = time.monotonic() + WAIT_S
        events = []
        while time.monotonic() < deadline and not any(e.kind == "training_step" for e in events):
            events += s.poll_events()
            time.sleep(0.02)
        assert any("ValueError" in e.message for e in events if e.kind == "training_step"), events
        assert s.snapshot().result(WAIT_S) is not None
        assert s.status.alive
    finally:
        s.close()


def test_a_dead_session_fails_the_lockstep_wait_and_the_outbox_futures(
        frames: list[Frame], monkeypatch: pytest.MonkeyPatch) -> None:
    """The lockstep wait in nodes/mapper/node.py (train(...).result()) and the outbox futures resolve
    with SessionError when the worker dies, instead of blocking the node forever."""
    s = MappingSession(_cfg(), free_running=False)
    try:
        for i, f in enumerate(frames[:3]):
            s.insert_keyframe(_kf(f, 100 + i)).result(WAIT_S)
        gate = threading.Event()
        s.call(lambda m: gate.wait(WAIT_S))
        train = s.train(2)
        delta = s.delta(100)

        def broken(*_: object) -> None:
            raise RuntimeError("status bug")

        monkeypatch.setattr(s, "_publish_status", broken)
        gate.set()
        with pytest.raises(SessionError, match="died"):
            train.result(WAIT_S)
        with pytest.raises(SessionError):
            delta.result(WAIT_S)
        assert not s.status.alive
        with pytest.raises(SessionError):
            s.train(1)
    finally:
        s.close(timeout_s=5)


def test_close_fails_outbox_futures_and_a_cut_after_a_timed_out_join(
        frames: list[Frame], monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: close() never failed outbox futures, and a snapshot the worker cut after close's
    join timed out went into a queue nobody read: its future hung."""
    s = MappingSession(_cfg(), free_running=False)
    for i, f in enumerate(frames[:3]):
        s.insert_keyframe(_kf(f, 100 + i)).result(WAIT_S)
    real = GaussianMapper.snapshot
    inside = threading.Event()

    def slow(self):  # noqa: ANN001, ANN202
        inside.set()
        time.sleep(0.5)  # the cut outlasts close's join below (not a wait for a state)
        return real(self)

    monkeypatch.setattr(GaussianMapper, "snapshot", slow)
    cut_late = s.delta(100)  # the worker is inside this cut when close gives up waiting
    assert inside.wait(WAIT_S)
    queued = s.delta(100)
    s.close(timeout_s=0.05)
    for f in (cut_late, queued):
        with pytest.raises(SessionError):
            f.result(WAIT_S)


def test_saves_land_in_command_order(frames: list[Frame]) -> None:
    """Before: the node captured a state on the worker and wrote it on its own thread, so a slow
    periodic save could land after the final one and overwrite it."""
    s = MappingSession(_cfg(), free_running=False)
    try:
        for i, f in enumerate(frames[:3]):
            s.insert_keyframe(_kf(f, 100 + i)).result(WAIT_S)
        written: list[int] = []

        def slow_write(ck) -> int:  # noqa: ANN001
            time.sleep(0.3)
            written.append(ck.iteration)
            return ck.iteration

        older: Future = s.save_state(slow_write)
        s.train(3)
        final = s.save_state(lambda ck: written.append(ck.iteration) or ck.iteration)
        assert older.result(WAIT_S) == 0 and final.result(WAIT_S) == 3
        assert written == [0, 3]
    finally:
        s.close()


def test_keyframes_are_prepared_without_touching_the_mapper(frames: list[Frame],
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Preparing a keyframe on the caller's thread used the mapper object the worker owns; it is
    a pure function of the config now."""
    def owned(*_: object, **__: object) -> None:
        raise AssertionError("the caller's thread reached into the worker's mapper")

    monkeypatch.setattr(GaussianMapper, "prepare_keyframe", owned)
    s = MappingSession(_cfg(), free_running=False)
    try:
        assert s.insert_keyframe(_kf(frames[0], 100)).result(WAIT_S) > 0
        assert np.isfinite(s.status.keyframes)
    finally:
        s.close()


def test_a_worker_thread_runs_at_its_own_niceness() -> None:
    """A background actor (the tracking back-end) lowers its own thread's priority only: the
    thread that created it keeps its own, so the frame path is not slowed."""
    import os

    class _Niced(CommandWorker):
        def __init__(self) -> None:
            super().__init__("niced", niceness=6)
            self.start()

    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    w = _Niced()
    try:
        theirs = w.submit("priority", lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())).result(10)
    finally:
        w.close()
    assert theirs == max(mine, 6)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == mine
