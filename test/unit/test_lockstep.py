"""The replay service's acknowledgement window (core/runtime/replay.py: AckWindow)."""
from __future__ import annotations

from concurrent.futures import Future

import pytest

from memgs_ros.core.runtime.replay import AckWindow


def _done(f: Future) -> None:
    f.set_result(None)


def test_window_zero_acknowledges_a_frame_after_its_own_training() -> None:
    acks = AckWindow(0)
    f1: Future = Future()
    acks.submitted(1, f1)
    assert acks.due() == []
    _done(f1)
    assert acks.due() == [1] and acks.due() == []


def test_window_one_acknowledges_at_once_while_only_the_frame_itself_trains() -> None:
    acks = AckWindow(1)
    f1, f2, f3 = Future(), Future(), Future()
    acks.submitted(1, f1)
    assert acks.due() == [1]  # the tracker may take frame 2 while frame 1 trains
    acks.submitted(2, f2)
    assert acks.due() == []  # frames 1 and 2 both unfinished: one too many
    _done(f1)
    assert acks.due() == [2]
    _done(f2)
    acks.submitted(3, f3)
    assert acks.due() == [3] and acks.waiting == 0


def test_a_failed_training_still_lets_the_replay_go_on_in_order() -> None:
    acks = AckWindow(0)
    f1, f2 = Future(), Future()
    acks.submitted(1, f1)
    acks.submitted(2, f2)
    _done(f2)
    assert acks.due() == []  # frame 1 first
    f1.set_exception(RuntimeError("step failed"))
    assert acks.due() == [1, 2]


def test_a_negative_window_is_refused() -> None:
    with pytest.raises(ValueError):
        AckWindow(-1)
