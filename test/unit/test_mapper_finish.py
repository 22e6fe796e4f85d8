"""The mapper's finish sequence (core/mapper_service/finish.py), without ROS: asyncio stands in for the
node's executor, plain futures for the session's."""
from __future__ import annotations

import asyncio
from concurrent.futures import Future
from types import SimpleNamespace
from typing import Any

import pytest

from memgs_ros.core.mapper_service.finish import FinalPlan, FinishSteps, finish_map
from memgs_ros.core.mapper_service.session_records import FinishResult
from memgs_ros.core.map_io.answers import MapAnswer
from memgs_ros.core.runtime.worker import WorkerStopped
from memgs_ros.errors import DataError


def _resolved(value: Any) -> Future:
    f: Future = Future()
    f.set_result(value)
    return f


class _Node:
    """The node's side of the finish: records what was called, in order."""

    def __init__(self, acked_after: int = 0, save_error: BaseException | None = None) -> None:
        self.calls: list[str] = []
        self.logged: list[str] = []
        self.sleeps = 0
        self._acked_after = acked_after
        self._save_error = save_error
        self.session = SimpleNamespace(finish=self.finish, status=SimpleNamespace(gaussians=1234))
        self.now = 0.0

    def finish(self, *plan: Any) -> Future:
        self.calls.append(f"finish{plan}")
        return _resolved(FinishResult(epoch=77, gaussians=1234, final_iterations=5, seconds=1.25))

    def flush(self) -> Future:
        self.calls.append("flush")
        return _resolved(None)

    def snapshot(self) -> Future:
        self.calls.append("snapshot")
        return _resolved((None, 1234, 9))

    def save(self) -> Future:
        self.calls.append("save")
        f: Future = Future()
        if self._save_error is None:
            f.set_result(None)
        else:
            f.set_exception(self._save_error)
        return f

    def acked(self) -> bool:
        return self.sleeps >= self._acked_after

    async def sleep(self, seconds: float) -> None:
        self.sleeps += 1
        self.now += seconds

    def steps(self) -> FinishSteps:
        return FinishSteps(self.flush, self.snapshot, self.save, self.acked, asyncio.wrap_future, self.sleep,
                           self.logged.append)

    def run(self, plan: FinalPlan, timeout_s: float = 10.0) -> str:
        return asyncio.run(finish_map(self.session, plan, self.steps(), timeout_s, clock=lambda: self.now))


def test_finish_runs_its_steps_in_order_and_names_the_closing_snapshot() -> None:
    node = _Node()
    answer = node.run(FinalPlan(iterations=5, densify=False, budget_s=2.0, total_iterations=100))
    assert node.calls == ["finish(5, False, 2.0, 100)", "flush", "snapshot", "save"]
    assert MapAnswer.parse(answer) == MapAnswer(9, 1234, 77)
    assert node.logged == ["final 5 iterations in 1.2 s"]


def test_the_snapshot_waits_for_the_flush_to_be_acknowledged() -> None:
    node = _Node(acked_after=3)
    node.run(FinalPlan())
    assert node.sleeps == 3 and node.calls[-2:] == ["snapshot", "save"]


def test_a_receiver_that_never_acknowledges_delays_the_snapshot_at_most_the_timeout() -> None:
    node = _Node(acked_after=10**9)
    node.run(FinalPlan(), timeout_s=1.0)
    assert node.sleeps == pytest.approx(50, abs=1) and "snapshot" in node.calls  # 20 ms steps


@pytest.mark.parametrize("error", [OSError("disk full"), DataError("bad state"), WorkerStopped("closed")])
def test_a_failed_last_checkpoint_does_not_fail_the_finish(error: BaseException) -> None:
    assert MapAnswer.parse(_Node(save_error=error).run(FinalPlan())) == MapAnswer(9, 1234, 77)


def test_an_unexpected_error_of_the_last_checkpoint_fails_the_finish() -> None:
    with pytest.raises(RuntimeError, match="bug"):
        _Node(save_error=RuntimeError("bug")).run(FinalPlan())
