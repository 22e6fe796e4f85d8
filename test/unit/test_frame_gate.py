"""The tracker's frame gating as ROS-free services: stamp rules, a live camera's gate, the camera
source and the frames that wait for it, the kernels' warm-up thread."""
from __future__ import annotations

import threading

import pytest

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.runtime.warm import WarmUpThread
from memgs_ros.core.tracking.frame_gate import CameraSource, CameraWait, LiveGate, StampRules
from memgs_ros.errors import DataError

S = 1_000_000_000


def test_stamp_rules_take_forward_stamps_and_refuse_duplicates_late_and_future_ones() -> None:
    rules = StampRules(jump_back_ns=2 * S, max_ahead_ns=10 * S)
    now = 100 * S
    assert rules.check(50 * S, now).take and rules.check(50 * S, now).problem is None
    rules.took(50 * S)
    dup = rules.check(50 * S, now)
    assert not dup.take and dup.problem == "stamp_duplicate"
    late = rules.check(49 * S, now)
    assert not late.take and late.problem == "stamp_order" and "1000.0 ms before" in late.message
    future = rules.check(200 * S, now)
    assert not future.take and future.problem == "stamp_future"
    assert rules.check(200 * S, 0).take  # a clock that does not run judges no stamp as future
    reset = rules.check(10 * S, now)  # more than jump_back before: a bag loop / clock reset
    assert reset.take and reset.problem == "time_jump_back"
    rules.took(10 * S)
    assert rules.check(11 * S, now).take and rules.check(11 * S, now).problem is None


def test_stamp_rules_do_not_move_for_a_frame_that_was_not_taken() -> None:
    rules = StampRules(jump_back_ns=S, max_ahead_ns=0)
    rules.took(5 * S)
    assert rules.check(6 * S, 0).take  # judged, but refused later (an unreadable image): not took()
    assert rules.check(6 * S, 0).take and rules.last_ns == 5 * S


def test_live_gate_counts_lost_frames_and_refuses_warming_and_stale_ones() -> None:
    gate = LiveGate(max_age_ns=100_000_000)  # 0.1 s
    assert gate.admit(1, 1_000, 5_000, warm=False) == ("warming", 0)
    assert gate.admit(4, 2_000, 6_000, warm=True) == (None, 2)  # 2 and 3 never arrived
    assert gate.admit(5, 3_000, 7_000, warm=True) == (None, 0)
    # waited 0.2 s longer than the least wait seen (4 us): stale, whatever the clocks' offset
    assert gate.admit(6, 4_000, 8_000 + 200_000_000, warm=True) == ("stale", 0)
    assert gate.admit(2, 0, 9_000, warm=True) == (None, 0)  # a restarted publisher; no stamp: taken


def test_a_lockstep_gate_takes_every_frame() -> None:
    gate = LiveGate(max_age_ns=0)
    assert gate.admit(1, 1, 10**12, warm=False) == (None, 0)
    assert gate.admit(3, 1, 10**12, warm=False) == (None, 1)


def test_camera_wait_keeps_the_newest_and_hands_back_the_one_it_drops() -> None:
    wait: CameraWait[int] = CameraWait(2)
    assert wait.add(1) is None and wait.add(2) is None
    assert wait.add(3) == 1 and len(wait) == 2
    assert wait.drain() == [2, 3] and len(wait) == 0


CAM = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def test_camera_from_the_first_camera_info_releases_the_waiting_frames() -> None:
    src: CameraSource[str] = CameraSource(None, wait=2)
    assert src.for_frame("a", 640, 480) == (False, None)
    assert src.for_frame("b", 640, 480) == (False, None)
    assert src.for_frame("c", 640, 480) == (False, "a")
    verdict = src.info(CAM)
    assert verdict.kind == "set" and verdict.released == ["b", "c"] and src.camera == CAM
    assert src.for_frame("d", 640, 480) == (True, None)
    assert src.info(CAM).kind == ""
    assert src.info(PinholeCamera(640, 480, 600.0, 600.0, 320.0, 240.0)).kind == "changed"
    assert src.camera == CAM  # the first is kept


def test_a_configured_calibration_is_fitted_to_the_first_frame_and_compared_once() -> None:
    src: CameraSource[str] = CameraSource(CAM)
    assert src.for_frame("a", 320, 240) == (True, None)
    assert src.camera is not None and (src.camera.width, src.camera.fx) == (320, 250.0)
    other = src.info(PinholeCamera(640, 480, 540.0, 500.0, 320.0, 240.0))
    assert other.kind == "differs" and other.differences
    assert src.info(PinholeCamera(640, 480, 540.0, 500.0, 320.0, 240.0)).kind == ""  # said once
    with pytest.raises(DataError):
        CameraSource(CAM).for_frame("wide", 640, 360)  # another aspect ratio


def test_warm_up_thread_reports_and_is_ready_after_a_failure_too() -> None:
    done: list[tuple[float, Exception | None]] = []
    release = threading.Event()
    warm = WarmUpThread(lambda: release.wait(10), lambda s, e: done.append((s, e)))
    assert not warm.wait(0.05)
    release.set()
    assert warm.wait(10) and done and done[0][1] is None

    def fail() -> None:
        raise RuntimeError("no compiler")

    failed: list[Exception | None] = []
    bad = WarmUpThread(fail, lambda _s, e: failed.append(e))
    assert bad.wait(10) and isinstance(failed[0], RuntimeError)
    bad.join(1.0)


def test_the_warm_up_leaves_the_heap_settled_for_the_frames() -> None:
    """What starting made is collected and then exempt from the collector's full passes, which
    walked every object the imports made (70-90 ms with the GIL held in a tracker)."""
    import gc

    class Cycle:
        def __init__(self) -> None:
            self.me = self

    kept: list[Cycle] = []

    def warm() -> None:
        kept.extend(Cycle() for _ in range(1000))  # alive: frozen
        for _ in range(1000):
            Cycle()  # garbage in cycles: collected before the freeze

    before = gc.get_freeze_count()
    try:
        warm_up = WarmUpThread(warm, lambda _s, _e: None)
        assert warm_up.wait(10)
        frozen = gc.get_freeze_count()
        assert frozen >= before + 1000
        assert not any(type(o) is Cycle for o in gc.get_objects())  # kept ones frozen, the rest freed
        assert len(kept) == 1000 and all(c.me is c for c in kept)
    finally:
        gc.unfreeze()  # the rest of the suite's collections as before
