"""The bag player's rules without ROS: the frame feed (loops, skips, max_frames) and the pacing
(start gate, lockstep acknowledgement, real-time clock)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.runtime.replay import AckWait, RealTimeClock, StartGate
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.replay import ReplayFeed, frames_total, open_frames

CAM = PinholeCamera(8, 6, 10.0, 10.0, 3.5, 2.5)


def _frames(n: int, period_ns: int = 100, start_ns: int = 1000) -> list[Frame]:
    return [Frame(stamp_ns=start_ns + i * period_ns, rgb=np.zeros((6, 8, 3), np.uint8), depth_m=None, camera=CAM)
            for i in range(n)]


def _drain(feed: ReplayFeed) -> list[int]:
    out = []
    while (item := feed.next()) is not None:
        out.append(item[1])
    return out


def test_feed_loops_with_increasing_stamps_and_stops_at_max_frames() -> None:
    feed = ReplayFeed(_frames(3), loop=True, max_frames=7)
    # Each pass shifted by its span (200) plus one frame period (100).
    assert _drain(feed) == [1000, 1100, 1200, 1300, 1400, 1500, 1600]
    assert _drain(ReplayFeed(_frames(3))) == [1000, 1100, 1200]
    assert _drain(ReplayFeed(_frames(1), loop=True, max_frames=3)) == [1000, 1000 + 33_333_333, 1000 + 66_666_666]


def test_feed_skips_and_counts_bad_frames_or_refuses_them_with_strict() -> None:
    frames = _frames(5)
    bad = [frames[0], frames[1], replace(frames[0], stamp_ns=900), frames[2],
           replace(frames[3], camera=replace(CAM, fx=20.0)), frames[4]]
    feed = ReplayFeed(bad)
    assert _drain(feed) == [1000, 1100, 1200, 1400]
    assert feed.skipped() == {"stamp_backwards": 1, "camera_changed": 1}
    strict = ReplayFeed(bad, strict=True)
    assert _drain_until_error(strict) == [1000, 1100]


def _drain_until_error(feed: ReplayFeed) -> list[int]:
    out: list[int] = []
    with pytest.raises(DataError, match="stamp_backwards"):
        while (item := feed.next()) is not None:
            out.append(item[1])
    return out


def test_frames_total_and_open_frames() -> None:
    assert frames_total(_frames(5), 0) == 5 and frames_total(_frames(5), 3) == 3
    assert frames_total(iter(_frames(5)), 4) == 4  # no length: the cap, or 0
    with pytest.raises(ConfigError, match="parameter 'source' is empty"):
        open_frames("", None, strict=False)
    assert len(list(open_frames("synthetic:w=32,h=24,n=3", None, strict=False))) == 3


def test_start_gate_waits_for_steady_readers_or_the_start_delay() -> None:
    gate = StartGate(settle_s=0.5, start_delay_s=10.0, created_s=0.0, acker="a publisher on 'ack'")
    assert gate.ready(0.1, (1, 1, 1, 1), True, []) == (False, [])  # counts just changed
    assert gate.ready(0.4, (1, 1, 1, 1), True, []) == (False, [])
    assert gate.ready(0.5, (1, 2, 1, 1), True, []) == (False, [])  # a depth reader arrived: settle again
    assert gate.ready(1.0, (1, 2, 1, 1), True, []) == (True, [])
    late = StartGate(settle_s=0.5, start_delay_s=2.0, created_s=0.0, acker="a publisher on 'ack'")
    assert late.ready(1.0, (0, 0, 0, 0), False, ["tracker's reader"]) == (False, [])
    assert late.ready(2.0, (0, 0, 0, 0), False, ["tracker's reader"]) == (
        True, ["a color subscriber", "a publisher on 'ack'", "tracker's reader"])


def test_ack_wait_and_real_time_clock() -> None:
    acks = AckWait(timeout_s=1.0)
    acks.sent(5, now_s=10.0)
    assert acks.ack(4, 10.2) is None and acks.awaiting_ns == 5  # not the frame awaited
    assert acks.ack(5, 10.25) == pytest.approx(0.25) and acks.awaiting_ns is None
    acks.sent(6, now_s=20.0)
    assert acks.expire(21.0) is None and acks.expire(21.5) == 6 and acks.timeouts == 1
    assert acks.awaiting_ns is None and acks.expire(30.0) is None
    clock = RealTimeClock(rate=2.0)
    clock.start(100.0, stamp0_ns=10**9)
    assert clock.due(3 * 10**9) == pytest.approx(101.0)  # 2 s of stamps at twice real time
