"""The mapper's side of the replay service (core/runtime/replay.py: FrameAcknowledger), without ROS: the training
futures complete on this thread and the hand-over runs what it gets at once, in order."""
from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future

from memgs_ros.core.runtime.replay import FrameAcknowledger


class _Mapper:
    """The node's side: each ``train()`` a future the test resolves, acknowledgements recorded."""

    def __init__(self, window: int) -> None:
        self.trains: list[Future] = []
        self.acked: list[int] = []
        self.ack_ms: list[float] = []
        self.handed: list[Callable[[], None]] = []
        self.now = 0.0
        self.acks = FrameAcknowledger(window, self.train, self.handed.append, self.acked.append,
                                         self.ack_ms.append, clock=lambda: self.now)

    def train(self) -> Future:
        f: Future = Future()
        self.trains.append(f)
        return f

    def run_handed(self) -> None:
        """The executor's thread: what the acknowledger handed over, in order."""
        while self.handed:
            self.handed.pop(0)()


def test_a_frame_is_acknowledged_once_its_training_is_within_the_window() -> None:
    m = _Mapper(window=0)
    m.acks.processed(1, keyframe=False, bundle_complete=False)
    assert len(m.trains) == 1 and m.acked == []  # training queued at once; nothing acknowledged yet
    m.run_handed()
    assert m.acked == []  # window 0: the frame's own training must finish
    m.now = 0.25
    m.trains[0].set_result(None)  # on the session's worker: its completion is handed over
    assert m.acked == []
    m.run_handed()
    assert m.acked == [1] and m.ack_ms == [250.0]


def test_window_one_acknowledges_while_the_frame_trains() -> None:
    m = _Mapper(window=1)
    m.acks.processed(1, keyframe=False, bundle_complete=False)
    m.run_handed()
    assert m.acked == [1]  # the tracker takes the next frame while the mapper trains this one
    m.acks.processed(2, keyframe=False, bundle_complete=False)
    m.run_handed()
    assert m.acked == [1]  # two frames' training unfinished: frame 2 waits
    m.trains[0].set_result(None)
    m.run_handed()
    assert m.acked == [1, 2]


def test_a_keyframe_frame_trains_after_its_bundle_is_complete() -> None:
    m = _Mapper(window=1)
    m.acks.processed(5, keyframe=True, bundle_complete=False)
    assert m.trains == [] and m.acks.awaiting == {5}  # its insertion must be queued first
    m.acks.bundle_complete(7)  # another keyframe's bundle: nothing waited for it
    assert m.trains == []
    m.now = 0.5
    m.acks.bundle_complete(5)
    assert len(m.trains) == 1 and m.acks.awaiting == frozenset()
    m.run_handed()
    assert m.acked == [5] and m.ack_ms == [500.0]  # counted from the tracker's word on the frame
    m.acks.bundle_complete(5)  # the same bundle again (a replay): no second training
    assert len(m.trains) == 1


def test_a_keyframe_whose_bundle_came_first_trains_at_once() -> None:
    m = _Mapper(window=0)
    m.acks.processed(5, keyframe=True, bundle_complete=True)
    assert len(m.trains) == 1


def test_a_failed_training_still_acknowledges_the_frame() -> None:
    m = _Mapper(window=0)
    m.acks.processed(1, keyframe=False, bundle_complete=False)
    m.trains[0].set_exception(RuntimeError("step failed"))  # reported elsewhere; the replay goes on
    m.run_handed()
    assert m.acked == [1]


def test_frames_are_acknowledged_in_order_when_training_finishes_late() -> None:
    m = _Mapper(window=0)
    for stamp in (1, 2, 3):
        m.acks.processed(stamp, keyframe=False, bundle_complete=False)
    m.run_handed()
    for f in m.trains:
        f.set_result(None)
    m.run_handed()
    assert m.acked == [1, 2, 3] and len(m.ack_ms) == 3


def test_a_frame_trains_after_the_pose_messages_sent_with_it_whichever_comes_first() -> None:
    """The tracker names the pose messages it sent with a frame ("refined", "loop", "culled": topics
    of their own, no order across them); the frame's training is queued only once each is in, so
    the session's commands keep one order (an acknowledged replay's map the same every run)."""
    m = _Mapper(window=0)
    m.acks.processed(1, keyframe=False, bundle_complete=False, parts=frozenset({"refined", "loop"}))
    m.run_handed()
    assert m.trains == [] and m.acks.awaiting == {1}  # the word came first: it waits
    m.acks.part_arrived(1, "refined")
    assert m.trains == []
    m.acks.part_arrived(1, "loop")
    m.run_handed()
    assert len(m.trains) == 1 and m.acks.awaiting == frozenset()
    m.trains[0].set_result(None)
    m.run_handed()
    assert m.acked == [1]
    # The usual order: the part first, then the word; the frame trains at once.
    m.acks.part_arrived(2, "culled")
    assert m.trains[1:] == []
    m.acks.processed(2, keyframe=False, bundle_complete=False, parts=frozenset({"culled"}))
    m.run_handed()
    assert len(m.trains) == 2
    # A keyframe waits for its bundle and its parts alike.
    m.acks.processed(3, keyframe=True, bundle_complete=False, parts=frozenset({"refined"}))
    m.acks.bundle_complete(3)
    assert len(m.trains) == 2 and m.acks.awaiting == {3}
    m.acks.part_arrived(3, "refined")
    m.run_handed()
    assert len(m.trains) == 3 and m.acks.awaiting == frozenset()


def test_a_part_that_never_comes_holds_its_frame_no_longer_than_the_wait() -> None:
    from memgs_ros.core.runtime.replay import PART_WAIT_S

    m = _Mapper(window=0)
    m.acks.processed(1, keyframe=False, bundle_complete=False, parts=frozenset({"refined"}))
    m.now += PART_WAIT_S + 0.1
    m.acks.processed(2, keyframe=False, bundle_complete=False)
    m.run_handed()
    assert len(m.trains) == 2 and m.acks.awaiting == frozenset()  # 1 given up on, then 2


def test_the_last_frame_waits_no_longer_than_the_wait_without_another_announcement() -> None:
    """No later frame's word comes to end the wait: the node's timer does (``expire_parts``)."""
    from memgs_ros.core.runtime.replay import PART_WAIT_S

    m = _Mapper(window=0)
    m.acks.processed(1, keyframe=False, bundle_complete=False, parts=frozenset({"loop"}))
    m.acks.expire_parts()
    assert len(m.trains) == 0 and m.acks.awaiting == {1}  # not yet
    m.now += PART_WAIT_S + 0.1
    m.acks.expire_parts()
    m.run_handed()
    assert len(m.trains) == 1 and m.acks.awaiting == frozenset()
