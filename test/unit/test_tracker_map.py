"""The tracker's map saved and loaded (core/tracking/map_io.py, frontend/map_session.py): a second
session relocalises in the first one's world, maps on or only localises, and a bad file is refused."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking import TrackerConfig, TrackingState, make_tracker
from memgs_ros.core.tracking.map_io import read_tracker_map, write_tracker_map
from memgs_ros.errors import DataError
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(generate_frames(SyntheticSpec(width=320, height=240, n_frames=60, seed=0, supersample=1)))


@pytest.fixture(scope="module")
def saved(frames: list[Frame], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list]:
    """Session 1: frames 0-39 tracked, the map written; returns (file, session 1's results)."""
    path = tmp_path_factory.mktemp("tmap") / "tracker.npz"
    with make_tracker(TrackerConfig(ba_threaded=False), frames[0].camera) as t:
        results = [t.track(f) for f in frames[:40]]
        t.wait_for_loop_closing()
        write_tracker_map(t.export_map({"frames": 40}), path)
        assert t.map_stats() is not None
    return path, results


def _position_error_m(T_wc: np.ndarray, frame: Frame, anchor: np.ndarray) -> float:
    return float(np.linalg.norm((anchor @ T_wc)[:3, 3] - frame.T_wc_gt[:3, 3]))


def test_the_file_holds_the_map(saved: tuple[Path, list]) -> None:
    path, _ = saved
    m = read_tracker_map(path)
    assert m.n_keyframes >= 2 and m.header["points"] > 200 and m.header["frames"] == 40
    assert len(m.arrays["bow_kf"]) == m.n_keyframes  # the place-recognition vectors are kept
    assert int(m.arrays["kf_point_ids"].max()) == m.header["points"] - 1  # renumbered, no bad points


@pytest.mark.parametrize("localize", [False, True])
def test_a_second_session_relocalises_in_the_first_ones_world(frames: list[Frame], saved: tuple[Path, list],
                                                              localize: bool) -> None:
    path, first = saved
    anchor = frames[0].T_wc_gt @ invert_pose(first[0].T_wc)  # session 1's world -> ground truth
    m = read_tracker_map(path)
    with make_tracker(TrackerConfig(ba_threaded=False), frames[0].camera) as t:
        t.localize_only = localize
        t.load_map(m)
        results = [t.track(f) for f in frames[25:60]]  # overlaps session 1, then goes on past it
        posed = [(r, f) for r, f in zip(results, frames[25:60]) if r.T_wc is not None]
        assert 0 <= t.relocalized_after <= 2 and t.frames_relocalizing == t.relocalized_after
        assert t.stamps_before_map  # session 1's own frames again: flagged (stamps key the keyframes)
        assert results[t.relocalized_after].state == TrackingState.OK
        # No new world: the frames both sessions tracked get the same place in it (within ~2 cm),
        # and the rest no further from the ground truth than session 1's own drift allows.
        assert len(posed) >= len(results) - 2
        same = [np.linalg.norm(r.T_wc[:3, 3] - first[25 + i].T_wc[:3, 3]) for i, r in enumerate(results[:15])
                if r.T_wc is not None]
        assert np.median(same) < 0.02, np.round(same, 3)  # this 320x240 sequence tracks to ~1 cm
        drift = max(_position_error_m(r.T_wc, f, anchor) for r, f in zip(first, frames[:40]))
        err = [_position_error_m(r.T_wc, f, anchor) for r, f in posed]
        assert max(err) < drift + 0.02, (np.round(err, 3), drift)
        new_kfs = sum(r.keyframe is not None for r in results)
        stats = t.map_stats()
        assert stats is not None
        if localize:
            assert new_kfs == 0 and len(stats.keyframe_ids) == m.n_keyframes
        else:
            assert new_kfs >= 1 and max(stats.keyframe_ids) >= m.header["next_keyframe_id"]


def test_a_tracker_that_cannot_relocalise_gives_no_pose_and_starts_no_world(frames: list[Frame],
                                                                           saved: tuple[Path, list]) -> None:
    m = read_tracker_map(saved[0])
    rng = np.random.default_rng(0)
    noise = [Frame(f.stamp_ns, rng.integers(0, 255, f.rgb.shape, np.uint8), f.depth_m, f.camera) for f in frames[:5]]
    with make_tracker(TrackerConfig(ba_threaded=False, new_segment_after_lost_frames=1), frames[0].camera) as t:
        t.load_map(m)
        results = [t.track(f) for f in noise]
        assert all(r.T_wc is None and r.keyframe is None for r in results)
        assert t.frames_relocalizing == 5 and t.relocalized_after == -1 and t.segment_id == m.header["segment_id"]


def test_another_camera_or_a_damaged_file_is_refused(frames: list[Frame], saved: tuple[Path, list],
                                                     tmp_path: Path) -> None:
    m = read_tracker_map(saved[0])
    cam = frames[0].camera
    other = type(cam)(cam.width, cam.height, cam.fx * 1.2, cam.fy * 1.2, cam.cx, cam.cy)
    with make_tracker(TrackerConfig(ba_threaded=False), other) as t, pytest.raises(DataError, match="camera"):
        t.load_map(m)
    raw = saved[0].read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match="not a readable tracker map"):
        read_tracker_map(cut)
    bad = dict(m.arrays)
    bad["kf_point_ids"] = bad["kf_point_ids"] + 10**6
    write_tracker_map(type(m)(m.header, bad), tmp_path / "bad.npz")
    with pytest.raises(DataError, match="past the store"):
        read_tracker_map(tmp_path / "bad.npz")
