"""The rolling shutter's direction checked on the frames (frontend/readout.py): a rolling-shutter
sequence of the synthetic room played forward then backward, as ``--repeat`` plays a recording,
is corrected the right way round on both passes; a forward one never flips."""
from __future__ import annotations

import numpy as np
import pytest

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import interpolate_poses
from memgs_ros.core.metrics.trajectory import ate
from memgs_ros.core.tracking import make_tracker
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.frontend.readout import ReadoutDirection
from memgs_ros.io.synthetic import SyntheticSpec, build_scene, render, trajectory

READOUT_S = 0.033  # a whole frame interval: the skew of a slow CMOS sensor
BANDS = 24  # poses a frame: 10 rows each at 240


def _rolling_shutter_frames(spec: SyntheticSpec) -> list[Frame]:
    """The spec's frames with row v exposed at stamp + (v - (H - 1) / 2) / H * READOUT_S (the tracker's
    model), rendered band by band at the ground-truth pose of the band's centre row."""
    stamps, poses = trajectory(spec)
    cam, scene = spec.camera, build_scene(spec.seed)
    rows = cam.height // BANDS
    frames = []
    for k in range(spec.n_frames):
        rgb = np.empty((cam.height, cam.width, 3), np.uint8)
        depth = np.empty((cam.height, cam.width), np.float32)
        for b in range(BANDS):
            v0 = b * rows
            s = (v0 + 0.5 * (rows - 1) - 0.5 * (cam.height - 1)) / cam.height * READOUT_S
            q = np.clip(stamps[k] + int(s * 1e9), stamps[0], stamps[-1])
            T_wc, _ = interpolate_poses(stamps, poses, np.array([q]))
            band = PinholeCamera(cam.width, rows, cam.fx, cam.fy, cam.cx, cam.cy - v0)
            rgb[v0:v0 + rows], depth[v0:v0 + rows] = render(scene, band, T_wc[0], spec.aa)
        frames.append(Frame(int(stamps[k]), rgb, depth, cam, poses[k].copy()))
    return frames


@pytest.fixture(scope="module")
def forward_back() -> tuple[list[Frame], int]:
    """120 frames forward, then the same frames backward and forward again on one clock (two turns).
    The camera turns at ~0.8 rad/s (skew up to 3.5 px) and moves slowly: the tracker corrects
    rotation only."""
    spec = SyntheticSpec(width=320, height=240, n_frames=120, path_rot=1.0, path_amp=0.3, supersample=1)
    fwd = _rolling_shutter_frames(spec)
    dt = fwd[1].stamp_ns - fwd[0].stamp_ns
    frames = list(fwd)
    for seq in (list(reversed(fwd[:-1])), fwd[1:]):
        frames += [Frame(frames[-1].stamp_ns + dt * (i + 1), f.rgb, f.depth_m, f.camera, f.T_wc_gt)
                   for i, f in enumerate(seq)]
    return frames, len(fwd)


def _track(frames: list[Frame], auto: bool) -> tuple[object, np.ndarray, list[int], list[int]]:
    """ATE result, stamps of the posed frames, frames where the direction flipped, frames posed the
    other way while the evidence built."""
    cfg = TrackerConfig(ba_threaded=False, rolling_shutter_readout_s=READOUT_S, rolling_shutter_auto_direction=auto)
    tracker = make_tracker(cfg, frames[0].camera)
    est, stamps, flips, held = [], [], [], []
    try:
        for k, f in enumerate(frames):
            before = tracker.readout.held_other
            res = tracker.track(f)
            if tracker.readout.flips > len(flips):
                flips.append(k)
            if tracker.readout.held_other > before:
                held.append(k)
            if res.T_wc is not None:
                est.append(res.T_wc)
                stamps.append(f.stamp_ns)
    finally:
        tracker.close()
    gt_st = np.array([f.stamp_ns for f in frames])
    gt = np.array([f.T_wc_gt for f in frames])
    r = ate(np.array(stamps), np.array(est), gt_st, gt)
    return r, np.array(stamps), flips, held


def test_a_backward_pass_is_corrected_the_other_way(forward_back: tuple[list[Frame], int]) -> None:
    frames, n_fwd = forward_back
    turn = 2 * n_fwd - 1  # the first frame of the second forward pass
    frames = frames[:turn]  # forward and back: one turn
    fixed, _, no_flips, never = _track(frames, auto=False)
    auto, stamps, flips, held = _track(frames, auto=True)
    assert no_flips == [] and never == []
    # Flipped once, soon after the turn, and never back; before the first flip every frame kept the
    # direction in use.
    assert len(flips) == 1 and n_fwd <= flips[0] <= n_fwd + 15, flips
    assert held == []
    back = stamps[auto.est_index] > frames[n_fwd].stamp_ns
    err_auto = float(np.sqrt(np.mean(auto.errors_m[back] ** 2)))
    back_f = stamps[fixed.est_index] > frames[n_fwd].stamp_ns
    err_fixed = float(np.sqrt(np.mean(fixed.errors_m[back_f] ** 2)))
    assert err_auto < 0.7 * err_fixed, (err_auto, err_fixed)


def test_after_a_first_turn_frames_before_the_next_flip_are_posed_the_other_way(
        forward_back: tuple[list[Frame], int]) -> None:
    """An input that turned once is a replay with turns: at its next turn, the frames that fit the
    other direction better while the evidence builds are posed that way, before the flip."""
    frames, n_fwd = forward_back
    turn = 2 * n_fwd - 1
    _, _, flips, held = _track(frames, auto=True)
    assert len(flips) == 2 and turn <= flips[1] <= turn + 15, flips
    assert held and all(flips[0] < k for k in held), (held, flips)
    assert any(turn <= k < flips[1] for k in held), (held, flips)


def test_a_forward_sequence_keeps_its_direction(forward_back: tuple[list[Frame], int]) -> None:
    frames, n_fwd = forward_back
    _, _, flips, held = _track(frames[:n_fwd], auto=True)
    assert flips == [] and held == []


def test_evidence_adds_up_only_for_the_other_direction() -> None:
    d = ReadoutDirection(0.02)
    assert d.readout_now_s == 0.02
    for _ in range(50):  # the direction in use clearly better, or the two alike: no flip
        assert not d.vote(0.6, 0.9) and not d.vote(0.8, 0.8 * np.exp(0.01))
    assert d.evidence == 0.0 and d.sign == 1
    flipped = [d.vote(0.9, 0.75) for _ in range(5)]  # log(0.9 / 0.75) - drift = 0.16 a frame
    assert flipped == [False, False, False, True, False] and d.readout_now_s == -0.02 and d.flips == 1
    assert not d.vote(float("nan"), 1.0) and not d.vote(0.0, 1.0)


def test_only_frames_turning_fast_enough_are_checked() -> None:
    fx = 500.0
    d = ReadoutDirection(0.02)
    assert not d.worth_checking(np.array([0.0, 0.2, 0.0]), fx)  # 1 px at the first and last rows
    fast = np.array([0.0, 0.4, 0.0])
    assert [d.worth_checking(fast, fx) for _ in range(4)] == [False, True, False, True]  # idle: every 2nd
    d.vote(0.9, 0.8)  # some evidence for the other way: every turning frame
    assert [d.worth_checking(fast, fx) for _ in range(3)] == [True, True, True]
    assert not ReadoutDirection(0.02, auto=False).worth_checking(np.array([0.0, 3.0, 0.0]), fx)
    assert not ReadoutDirection(0.0).worth_checking(np.array([0.0, 3.0, 0.0]), fx)
