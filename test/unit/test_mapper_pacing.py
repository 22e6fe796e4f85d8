"""The mapper's periodic deltas and live view (core/mapper_service/output_pacing.py), without ROS."""
from __future__ import annotations

from concurrent.futures import Future

from memgs_ros.core.mapper_service.output_pacing import DeltaPacer, LiveView, delta_rows
from memgs_ros.core.mapper_service.session_records import SessionStatus


def test_delta_rows_split_the_link_budget_over_the_delta_rate() -> None:
    assert delta_rows(500.0, 1.0, 100) == 5000
    assert delta_rows(500.0, 5.0, 100) == 1000
    assert delta_rows(1.0, 100.0, 1000) == 1  # never zero: a delta always moves the map on


class _Link:
    def __init__(self) -> None:
        self.sent: list[tuple[int, Future]] = []
        self.acked = True
        self.waits = 0
        self.pacer = DeltaPacer(7, self.send, lambda: self.acked, self.wait)

    def send(self, rows: int) -> Future:
        f: Future = Future()
        self.sent.append((rows, f))
        return f

    def wait(self) -> None:
        self.waits += 1


def test_one_periodic_delta_at_a_time() -> None:
    link = _Link()
    first = link.pacer.tick()
    assert link.sent == [(7, first)]
    assert link.pacer.tick() is first and len(link.sent) == 1  # still in flight: the tick waits for nothing
    first.set_result(None)
    second = link.pacer.tick()
    assert second is not first and len(link.sent) == 2


def test_a_lagging_receiver_skips_the_tick_and_is_counted() -> None:
    link = _Link()
    first = link.pacer.tick()
    first.set_result(None)
    link.acked = False
    assert link.pacer.tick() is first and link.waits == 1 and len(link.sent) == 1
    link.acked = True
    assert link.pacer.tick() is not first and link.waits == 1


def test_no_periodic_delta_once_the_finish_began() -> None:
    link = _Link()
    assert link.pacer.tick() is not None
    link.sent[0][1].set_result(None)
    link.pacer.finishing = True
    link.acked = False  # not even asked: the final flush will carry everything
    assert link.pacer.tick() is link.sent[0][1] and link.waits == 0 and len(link.sent) == 1


def test_the_live_view_renders_a_changed_pose_or_map_once() -> None:
    view = LiveView()
    st = SessionStatus(iteration=3, gaussians=100, keyframes=1)
    assert view.due(1, st)
    render: Future = Future()
    view.started(render)
    assert not view.due(2, st)  # the last render still waits: skip the tick
    render.set_result(None)
    assert not view.due(1, st)  # the same view of the same map: nothing new to send
    assert view.due(2, st)  # a new pose
    view.started(done := Future())
    done.set_result(None)
    assert not view.due(2, st)
    assert view.due(2, SessionStatus(iteration=4, gaussians=100, keyframes=1))  # the map trained
