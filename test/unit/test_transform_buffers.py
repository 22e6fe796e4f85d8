"""A robot's transforms without ROS (core/geometry/transform_buffers.py): odometry read at a stamp,
static frames chained."""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry.transform_buffers import PoseWindow, StaticFrames


def _T(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_a_pose_window_interpolates_takes_the_nearest_within_tolerance_and_never_extrapolates() -> None:
    w = PoseWindow(window=3, max_gap_s=0.5)
    for stamp, x in ((1_000_000_000, 0.0), (1_100_000_000, 1.0), (1_100_000_000, 7.0)):  # a repeated stamp: ignored
        w.add(stamp, _T(x))
    assert list(w.stamps) == [1_000_000_000, 1_100_000_000]
    assert np.allclose(w.at(1_050_000_000, 0)[:3, 3], [0.5, 0, 0])
    assert np.allclose(w.at(1_120_000_000, 30_000_000)[:3, 3], [1, 0, 0])
    assert w.at(1_200_000_000, 30_000_000) is None
    w.add(2_000_000_000, _T(5.0))  # 0.9 s after the last: not interpolated across
    assert w.at(1_500_000_000, 10_000_000) is None
    w.add(500_000_000, _T(3.0))  # time went back (a looped bag): the window starts over
    assert list(w.stamps) == [500_000_000] and w.at(1_050_000_000, 10_000_000) is None


def test_static_frames_chain_from_child_to_parent() -> None:
    f = StaticFrames()
    f.set("base_link", "camera_link", _T(0.1))
    f.set("camera_link", "camera_optical", _T(0.02))
    assert np.allclose(f.lookup("base_link", "camera_optical")[:3, 3], [0.12, 0, 0])
    assert f.lookup("base_link", "nowhere") is None
    f.set("camera_optical", "camera_link", _T(0.0))  # a cycle ends the walk
    assert f.lookup("map", "camera_optical") is None
