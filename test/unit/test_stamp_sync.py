from __future__ import annotations

import pytest

from memgs_ros.ros.stamp_sync import NearestPairer, StampBundler


def test_bundler_completes_in_any_order_and_bounds_pending() -> None:
    b = StampBundler({"color", "depth", "pose"}, max_pending=2)
    assert b.add("pose", 10, "p") is None
    assert b.add("color", 10, "c") is None
    assert b.add("depth", 10, "d") == {"pose": "p", "color": "c", "depth": "d"}
    for s in (20, 30, 40):
        b.add("color", s, s)
    assert b.pending == 2 and b.dropped == 1
    assert b.add("depth", 20, 0) is None  # 20 was dropped: this starts a new bundle
    with pytest.raises(KeyError, match="unknown bundle part"):
        b.add("keypoints", 10, None)


def test_pairer_nearest_within_tolerance() -> None:
    p: NearestPairer[str] = NearestPairer(max_dt_ns=20)
    assert p.add_a(100, "c100") is None
    assert p.add_a(133, "c133") is None
    assert p.add_b(130, "d130") == (133, "c133", "d130")
    assert p.dropped == 1  # c100 is older than the pair and can never match in order
    assert p.add_b(200, "d200") is None
    assert p.add_a(260, "c260") is None  # 60 apart: no pair


def test_exact_pairer() -> None:
    p: NearestPairer[int] = NearestPairer(max_dt_ns=0)
    assert p.add_b(5, 1) is None
    assert p.add_a(6, 2) is None
    assert p.add_a(5, 3) == (5, 3, 1)
