"""Long flights as sources: a source played forward and back (``--repeat``) and the synthetic orbit
flown lap after lap, each with its ground truth on the one clock."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from memgs_ros.core.geometry.poses import interpolate_poses
from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.errors import ConfigError
from memgs_ros.io.repeat import RepeatedSource, pass_of
from memgs_ros.io.replay import Preloaded
from memgs_ros.io.sources import open_source
from memgs_ros.io.synthetic import generate_frames, parse_spec, trajectory, write_tum_folder

SPEC = "synthetic:w=48,h=36,n=7,seed=1"


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tum") / "room"
    write_tum_folder(generate_frames(parse_spec(SPEC)), path)
    return path


@pytest.mark.parametrize("kind", ["tum", "synthetic"])
def test_passes_run_forward_and_back_on_one_clock(folder: Path, kind: str) -> None:
    spec = str(folder) if kind == "tum" else SPEC
    once = list(open_source(spec))
    src = open_source(spec, repeat=4)
    frames = list(src)
    n = len(once)
    assert len(src) == len(frames) == n + 3 * (n - 1)  # each turning frame shown once
    stamps = np.array([f.stamp_ns for f in frames])
    assert np.all(np.diff(stamps) > 0)
    assert np.array_equal(stamps, src.frame_stamps())
    # The gaps between frames mirror at each turn: the camera goes back the way it came.
    gaps = np.diff([f.stamp_ns for f in once])
    assert np.array_equal(np.diff(stamps), np.concatenate([gaps, gaps[::-1], gaps, gaps[::-1]]))
    # Pass 1 shows the frames backward (same images, same ground-truth poses), pass 2 forward again.
    order = list(range(n)) + list(range(n - 2, -1, -1)) + list(range(1, n)) + list(range(n - 2, -1, -1))
    for f, k in zip(frames, order, strict=True):
        assert np.array_equal(f.rgb, once[k].rgb)
        assert np.allclose(f.T_wc_gt, once[k].T_wc_gt)
    assert pass_of(stamps, stamps[0], once[-1].stamp_ns, 4).tolist() == \
        [0] * n + [1] * (n - 1) + [2] * (n - 1) + [3] * (n - 2) + [3]


@pytest.mark.parametrize("kind", ["tum", "synthetic"])
def test_ground_truth_follows_every_pass(folder: Path, kind: str) -> None:
    spec = str(folder) if kind == "tum" else SPEC
    src = open_source(spec, repeat=5)
    gt_s, gt_T = src.ground_truth()
    assert np.all(np.diff(gt_s) > 0)
    frames = list(src)
    T, valid = interpolate_poses(gt_s, gt_T, np.array([f.stamp_ns for f in frames]))
    assert valid.all()
    for f, Tf in zip(frames, T, strict=True):
        assert np.allclose(f.T_wc_gt, Tf, atol=1e-9)


def test_a_folder_is_read_again_each_pass_and_a_generator_kept(folder: Path) -> None:
    """A TUM folder loads frame k alone (a camera's cost every pass); the synthetic room is kept."""
    src = open_source(str(folder), repeat=3)
    assert isinstance(src, RepeatedSource)
    frames = list(src)
    a, b = frames[0], frames[2 * 6]  # frame 0 in pass 0, and again at the end of pass 1
    assert a.rgb is not b.rgb and np.array_equal(a.rgb, b.rgb)
    syn = list(open_source(SPEC, repeat=3))
    assert syn[0].rgb is syn[12].rgb


def test_repeat_is_refused_where_it_cannot_work(folder: Path) -> None:
    with pytest.raises(ConfigError, match="repeat must be an integer >= 1"):
        open_source(SPEC, repeat=0)
    with pytest.raises(ConfigError, match="cannot be repeated: it does not know its frames' stamps"):
        RepeatedSource(list(open_source(SPEC)), 2)  # type: ignore[arg-type]


def test_preloaded_frames_repeat_without_a_second_copy(folder: Path) -> None:
    """The player preloads, then repeats: every pass shows the preloaded images themselves."""
    preloaded = Preloaded(open_source(str(folder), raw_depth=True), budget_mb=10)
    src = RepeatedSource(preloaded, 3)  # type: ignore[arg-type]
    frames = list(src)
    assert len(frames) == 3 * len(preloaded) - 2
    assert frames[len(preloaded)].rgb is preloaded.frames[-2].rgb
    assert np.array_equal([f.stamp_ns for f in frames], open_source(str(folder), repeat=3).frame_stamps())


def test_repeat_one_is_the_source(folder: Path) -> None:
    assert not isinstance(open_source(str(folder), repeat=1), RepeatedSource)


def test_raw_depth_is_the_png_as_stored(folder: Path) -> None:
    raw = list(open_source(str(folder), raw_depth=True))
    metres = list(open_source(str(folder)))
    assert isinstance(raw[0].depth_m, DepthUnits) and raw[0].depth_m.raw.dtype == np.uint16
    assert raw[0].depth_m.scale == 5000.0
    for r, m in zip(raw, metres, strict=True):
        got, want = r.depth_metres(), np.where(m.depth_m > 0, m.depth_m, np.nan)
        assert np.allclose(np.nan_to_num(got), np.nan_to_num(want))


def test_orbit_laps_are_one_closed_round_flown_again() -> None:
    spec = parse_spec("synthetic:w=48,h=36,path=orbit,n=12,laps=3")
    assert spec.total_frames == 36
    stamps, poses = trajectory(spec)
    assert len(stamps) == 36 and np.all(np.diff(stamps) > 0)
    assert np.allclose(poses[12:24], poses[:12]) and np.allclose(poses[24:], poses[:12])
    # Closed: the step from the last frame of a lap to the first of the next is an ordinary step.
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 1.5 * steps.min()
    frames = list(open_source(spec.to_string()))
    assert len(frames) == 36 and frames[13].rgb is frames[1].rgb  # a lap's images are rendered once
    assert [f.stamp_ns for f in frames] == stamps.tolist()
    assert len(open_source(spec.to_string(), max_frames=20)) == 20
    assert len(list(open_source(spec.to_string(), max_frames=20))) == 20
    # Preloading counts a lap's images once.
    assert Preloaded(open_source(spec.to_string()), budget_mb=100).nbytes == sum(
        f.rgb.nbytes + f.depth_m.nbytes for f in frames[:12])


def test_laps_spec_round_trip_and_errors() -> None:
    spec = parse_spec("synthetic:w=48,h=36,path=orbit,n=12,laps=3")
    assert parse_spec(spec.to_string()) == spec
    assert "laps" not in parse_spec("synthetic:n=5").to_string()
    with pytest.raises(ConfigError, match="laps must be in"):
        parse_spec("synthetic:laps=0")


def test_forward_only_passes_jump_back_to_the_start(folder: Path) -> None:
    """``repeat_forward``: every pass forward, a frame period after the last, ground truth with it
    (a rolling-shutter recording keeps its rows in the flight's order)."""
    once = list(open_source(str(folder)))
    src = open_source(str(folder), repeat=3, repeat_forward=True)
    frames = list(src)
    n = len(once)
    assert len(src) == len(frames) == 3 * n
    stamps = np.array([f.stamp_ns for f in frames])
    assert np.all(np.diff(stamps) > 0) and np.array_equal(stamps, src.frame_stamps())
    for p in range(3):
        for k in range(n):
            assert np.array_equal(frames[p * n + k].rgb, once[k].rgb)
    assert src.pass_of(stamps).tolist() == [0] * n + [1] * n + [2] * n
    gt_s, gt_T = src.ground_truth()
    T, valid = interpolate_poses(gt_s, gt_T, stamps)
    assert valid.all() and all(np.allclose(f.T_wc_gt, Tf, atol=1e-9) for f, Tf in zip(frames, T, strict=True))
