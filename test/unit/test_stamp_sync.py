from __future__ import annotations

import pytest

from memgs_ros.ros.stamp_sync import NearestPairer, RgbdPairing, StampBundler


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


def _pairing(warn_s: float = 5.0) -> tuple[RgbdPairing, list[tuple[int, str, str]], list[int], list[str]]:
    pairs: list[tuple[int, str, str]] = []
    unpaired: list[int] = []
    problems: list[str] = []
    p = RgbdPairing(20, warn_s, ("/cam/color", "/cam/depth", 0.02), pairs.append, unpaired.append, problems.append)
    return p, pairs, unpaired, problems


def test_rgbd_pairing_hands_over_pairs_and_counts_the_colour_it_drops() -> None:
    p, pairs, unpaired, problems = _pairing()
    p.color(100, "c100", 0.0)
    p.color(133, "c133", 0.03)
    p.depth(130, "d130")
    assert pairs == [(133, "c133", "d130")]
    assert sum(unpaired) == 1 and problems == []  # c100 can never pair in order


def test_rgbd_pairing_says_why_colour_finds_no_depth() -> None:
    p, pairs, unpaired, problems = _pairing(warn_s=5.0)
    for k in range(7):  # colour alone for 6 s: no depth topic at all
        p.color(10**9 * k, f"c{k}", float(k))
    assert pairs == [] and len(problems) == 1
    assert "no depth on /cam/depth" in problems[0] and "align_depth.enable" in problems[0]
    p.depth(10**9 * 20, "d20")  # depth arrives, but never near the colour's stamps
    for k in range(7, 13):
        p.color(10**9 * k, f"c{k}", float(k))
    assert len(problems) == 2 and "within 20 ms of colour" in problems[1]
    assert sum(unpaired) > 0
