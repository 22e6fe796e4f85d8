"""Compiled tracking kernels against their plain twins, and the rolling-shutter correction."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from kernel_support import BF, K, needs_numba
from scipy.spatial.transform import Rotation

from memgs_ros.core.tracking import TrackerConfig
from memgs_ros.core.tracking.backend.bundle_adjustment import (
    _optimize_pose,
    _orthonormalized_svd,
    apply_left_update,
    optimize_pose,
    orthonormalized,
)
from memgs_ros.core.tracking.features.features import (
    FrameFeatures,
    _match_by_projection,
    match_by_projection,
    unroll_rolling_shutter,
)
from memgs_ros.errors import ConfigError


def _features(rng: np.random.Generator, m: int) -> FrameFeatures:
    # Keypoints a little beyond the image too: undistortion pushes corner keypoints outside.
    uv = np.column_stack([rng.uniform(-15.0, 655.0, m), rng.uniform(-15.0, 495.0, m)])
    desc = rng.integers(0, 256, (m, 32), dtype=np.uint8)
    return FrameFeatures(uv.astype(np.float32), uv, rng.integers(0, 8, m), desc, np.full(m, np.nan))


def _map_points(rng: np.random.Generator, feats: FrameFeatures, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Projections near keypoints with descriptors a few bits off theirs (plus pure noise when M = 0)."""
    if len(feats) == 0:
        return rng.uniform(0.0, 480.0, (p, 2)), rng.integers(0, 256, (p, 32), dtype=np.uint8)
    src = rng.integers(0, len(feats), p)
    flips = [rng.integers(0, 256, (p, 32), dtype=np.uint8) for _ in range(3)]
    return feats.uv[src] + rng.normal(0.0, 3.0, (p, 2)), feats.desc[src] ^ (flips[0] & flips[1] & flips[2])


@pytest.mark.parametrize("m,p", [(0, 50), (50, 0), (1, 1), (300, 200), (1000, 1500)])
def test_match_by_projection_matches_reference(m: int, p: int) -> None:
    needs_numba()
    rng = np.random.default_rng(m + 7 * p)
    feats = _features(rng, m)
    proj, desc = _map_points(rng, feats, p)
    for radius, available, k in [(rng.uniform(2.0, 40.0, p), None, 12),
                                 (15.0, rng.random(m) > 0.2, 12),
                                 (rng.uniform(2.0, 160.0, p), None, 3)]:
        fast = match_by_projection(proj, desc, feats, radius, 80, 0.85, available=available, max_candidates=k)
        ref = _match_by_projection(proj, desc, feats, radius, 80, 0.85, available=available, max_candidates=k)
        for a, b in zip(fast, ref, strict=True):
            assert a.dtype == np.int64 and np.array_equal(a, b)
    if m >= 300:
        assert len(fast[0]) > 0.3 * min(m, p)  # the case exercises real matches


def test_match_by_projection_breaks_ties_as_the_reference() -> None:
    """Keypoints at one position (a corner found at two octaves) tie in distance: the kernel's
    early-stopping ring scan still keeps the reference's nearest candidates and order. (At
    max_candidates of 1-4 the reference's k-d tree cuts a tie its own way; the kernel keeps the
    one a row-major scan of the window meets first, as before the ring scan.)"""
    needs_numba()
    rng = np.random.default_rng(3)
    for _ in range(60):
        feats = _features(rng, 400)
        uv = np.round(feats.uv, 1)
        uv[rng.integers(0, 400, 130)] = uv[rng.integers(0, 400, 130)]  # shared positions
        feats = FrameFeatures(uv.astype(np.float32), uv, feats.octave, feats.desc, feats.depth_m)
        proj, desc = _map_points(rng, feats, 300)
        proj = np.clip(np.round(proj, 1), 0.0, 639.0)
        radius = rng.uniform(2.0, 60.0, 300)
        fast = match_by_projection(proj, desc, feats, radius, 80, 0.9)
        ref = _match_by_projection(proj, desc, feats, radius, 80, 0.9)
        for a, b in zip(fast, ref, strict=True):
            assert np.array_equal(a, b)


@pytest.mark.parametrize("k", [12, 3])
def test_match_by_projection_in_crowded_tight_windows(k: int) -> None:
    """Tight radii among crowded keypoints (a textured patch: more within reach than ``k``): the
    windows read whole, cut to the k nearest, give the reference's matches. (Distances that tie
    at the cut are left to the test above: the reference's k-d tree cuts those its own way.)"""
    needs_numba()
    rng = np.random.default_rng(11 + k)
    for _ in range(30):
        uv = rng.uniform(200.0, 260.0, (600, 2))
        feats = FrameFeatures(uv.astype(np.float32), uv, rng.integers(0, 8, 600),
                              rng.integers(0, 256, (600, 32), dtype=np.uint8), np.full(600, np.nan))
        proj, desc = _map_points(rng, feats, 400)
        radius = rng.uniform(1.5, 6.0, 400)
        fast = match_by_projection(proj, desc, feats, radius, 80, 0.9, max_candidates=k)
        ref = _match_by_projection(proj, desc, feats, radius, 80, 0.9, max_candidates=k)
        for a, b in zip(fast, ref, strict=True):
            assert np.array_equal(a, b)
        assert len(fast[0]) > 50  # real matches


def _pose_problem(rng: np.random.Generator, n: int) -> tuple:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.1, 3)).as_matrix()
    T[:3, 3] = rng.normal(0.0, 0.1, 3)
    p_c = np.column_stack([rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(0.8, 4.0, n)])
    p_w = (p_c - T[:3, 3]) @ T[:3, :3]  # R^T (p_c - t)
    uv = p_c[:, :2] / p_c[:, 2:] * 500.0 + [320.0, 240.0] + rng.normal(0.0, 0.5, (n, 2))
    uv[: n // 10] += rng.uniform(10.0, 40.0, (n // 10, 2))  # gross outliers
    depth = p_c[:, 2] + rng.normal(0.0, 0.01, n)
    depth[rng.random(n) < 0.3] = np.nan
    inv_sigma = 1.2 ** -rng.integers(0, 8, n).astype(np.float64)
    T0 = apply_left_update(T, rng.normal(0.0, 0.02, 6))
    return T, T0, p_w, uv, depth, inv_sigma


@pytest.mark.parametrize("n,rounds,chi2_scale", [(4, 4, 1.0), (12, 1, 1.0), (200, 4, 1.0), (500, 3, 2.0),
                                                 (500, 2, 0.5)])
def test_optimize_pose_matches_reference(n: int, rounds: int, chi2_scale: float) -> None:
    needs_numba()
    rng = np.random.default_rng(n + rounds)
    T, T0, p_w, uv, depth, inv_sigma = _pose_problem(rng, n)
    fast_T, fast_inl = optimize_pose(T0, p_w, uv, depth, inv_sigma, K, BF, chi2_scale=chi2_scale, rounds=rounds)
    ref_T, ref_inl = _optimize_pose(T0, p_w, uv, depth, inv_sigma, K, BF, chi2_scale=chi2_scale, rounds=rounds)
    assert np.allclose(fast_T, ref_T, atol=1e-9, rtol=0.0)
    assert np.array_equal(fast_inl, ref_inl)
    if n >= 200:
        assert np.linalg.norm(fast_T[:3, 3] - T[:3, 3]) < 0.01
        assert not fast_inl[: n // 10].any()


def test_optimize_pose_degenerate_inputs_match_reference() -> None:
    needs_numba()
    rng = np.random.default_rng(3)
    _, T0, p_w, uv, depth, inv_sigma = _pose_problem(rng, 50)
    p_w[:] = p_w[0]  # every observation of one point: rank-deficient normal equations
    fast = optimize_pose(T0, p_w, uv, depth, inv_sigma, K, BF)
    ref = _optimize_pose(T0, p_w, uv, depth, inv_sigma, K, BF)
    assert np.isfinite(fast[0]).all() and fast[0].shape == (4, 4)
    assert fast[1].shape == ref[1].shape == (50,)
    few = optimize_pose(T0, p_w[:3], uv[:3], depth[:3], inv_sigma[:3], K, BF)
    assert np.array_equal(few[0], T0) and not few[1].any()


def test_disabled_numba_falls_back_to_the_plain_path() -> None:
    """MEMGS_DISABLE_NUMBA=1: no kernel is compiled or called; pose optimisation runs its plain twin
    and OpenCV's ORB describes the extractor's keypoints."""
    code = ("import cv2, numpy as np\n"
            "from memgs_ros.core.tracking import TrackerConfig, _compiled\n"
            "from memgs_ros.core.tracking.backend import bundle_adjustment as ba\n"
            "from memgs_ros.core.tracking.features import orb\n"
            "from memgs_ros.core.tracking.features.features import OrbExtractor\n"
            "from memgs_ros.io.synthetic import generate_frames, parse_spec\n"
            "assert not _compiled.numba_available() and not orb.compiled_orb_available()\n"
            "ex = OrbExtractor(TrackerConfig(n_features=300))\n"
            "assert ex._tests is None\n"
            "f = next(iter(generate_frames(parse_spec('synthetic:w=320,h=240,n=1'))))\n"
            "feats = ex.extract(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY), f.camera, f.depth_m)\n"
            "assert len(feats) == 300, len(feats)\n"
            "assert not hasattr(_compiled._match, 'signatures')  # never compiled\n"
            "assert not hasattr(orb._describe, 'signatures')\n"
            "T, inl = ba.optimize_pose(np.eye(4), np.array([[0, 0, 2.0], [1, 0, 2], [0, 1, 2], [1, 1, 3]]),\n"
            "    np.array([[320, 240.0], [570, 240], [320, 490], [320 + 500 / 3, 240 + 500 / 3]]), np.full(4, np.nan),\n"
            "    np.ones(4), np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.0]]), 40.0)\n"
            "assert inl.all() and np.allclose(T, np.eye(4), atol=1e-6), T\n")
    env = {**os.environ, "MEMGS_DISABLE_NUMBA": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("describer", ["kernel", "opencv"])
@pytest.mark.parametrize("spec,cfg", [
    ("synthetic:w=640,h=480,n=3,noise=0.01,holes=0.05", TrackerConfig()),
    ("synthetic:w=320,h=240,n=3", TrackerConfig(n_features=300, n_levels=5, scale_factor=1.3, grid_cell_px=32)),
    ("synthetic:w=160,h=120,n=3", TrackerConfig(n_features=300)),  # the top levels find nothing
])
def test_extract_matches_the_multi_level_orb_reference(spec: str, cfg: TrackerConfig, describer: str) -> None:
    """One pyramid with an ORB per level, described by ``orb.describe`` or OpenCV's ``compute``,
    gives OpenCV's multi-level ORB's keypoints, octaves and descriptors (another order), with
    undistortion and depth lookups on top."""
    import cv2

    from memgs_ros.core.tracking.features.features import OrbExtractor
    from memgs_ros.io.synthetic import generate_frames, parse_spec

    ex = OrbExtractor(cfg)
    if describer == "opencv":
        ex._tests = None  # noqa: SLF001 - what a machine without numba runs
    elif ex._tests is None:  # noqa: SLF001
        pytest.skip("no numba here, or OpenCV's ORB tests could not be read off")
    for f in generate_frames(parse_spec(spec)):
        grey = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
        got, ref = ex.extract(grey, f.camera, f.depth_m), ex._extract_reference(grey, f.camera, f.depth_m)  # noqa: SLF001
        assert len(got) == len(ref) > 0.25 * cfg.n_features
        # Pair them by octave and position: OpenCV's level-to-image scaling differs by < 1e-3 px.
        key_got = np.column_stack([got.uv_raw, 1e4 * got.octave])
        key_ref = np.column_stack([ref.uv_raw, 1e4 * ref.octave])
        dist = np.linalg.norm(key_ref[:, None, :] - key_got[None, :, :], axis=2)
        j = dist.argmin(axis=1)
        assert dist[np.arange(len(ref)), j].max() < 1e-3 and len(set(j.tolist())) == len(ref)
        assert np.array_equal(got.desc[j], ref.desc) and np.array_equal(got.octave[j], ref.octave)
        np.testing.assert_allclose(got.uv[j], ref.uv, atol=1e-3)
        assert np.array_equal(np.isnan(got.depth_m[j]), np.isnan(ref.depth_m))
    blank = np.full((120, 160), 128, np.uint8)  # no corner anywhere: empty, not an error
    cam = next(iter(generate_frames(parse_spec("synthetic:w=160,h=120,n=1")))).camera
    assert len(ex.extract(blank, cam, None)) == 0 and len(ex._extract_reference(blank, cam, None)) == 0  # noqa: SLF001


def test_orthonormalized_matches_the_svd_reference() -> None:
    """The polar iteration's nearest rotation equals the SVD's, from rounding drift to a 10 %
    distortion (where it hands over to the SVD), and a reflection still comes out a rotation."""
    rng = np.random.default_rng(11)
    for trial in range(400):
        T = np.eye(4)
        noise = 10.0 ** rng.uniform(-16.0, -1.0)
        T[:3, :3] = Rotation.random(random_state=trial).as_matrix() @ (np.eye(3) + noise * rng.standard_normal((3, 3)))
        T[:3, 3] = rng.standard_normal(3)
        T[3] = rng.standard_normal(4)  # the bottom row is restored too
        got, ref = orthonormalized(T), _orthonormalized_svd(T)
        np.testing.assert_allclose(got, ref, rtol=0.0, atol=1e-13)
        assert np.abs(got[:3, :3] @ got[:3, :3].T - np.eye(3)).max() < 1e-13
        assert np.array_equal(got[3], [0.0, 0.0, 0.0, 1.0]) and np.array_equal(got[:3, 3], T[:3, 3])
    flip = np.diag([1.0, 1.0, -1.0, 1.0])
    got = orthonormalized(flip)
    assert np.linalg.det(got[:3, :3]) > 0.0 and np.array_equal(got, _orthonormalized_svd(flip))


def test_unroll_rolling_shutter_recovers_the_centre_row_view() -> None:
    rng = np.random.default_rng(5)
    h, readout = 480, 0.03
    omega = np.array([0.4, -2.5, 0.8])  # rad/s in the camera frame: a fast turn (150 deg/s)
    p_c0 = np.column_stack([rng.uniform(-1.0, 1.0, (400, 2)), rng.uniform(1.0, 3.0, 400)])
    centre = p_c0[:, :2] / p_c0[:, 2:] * 500.0 + [320.0, 240.0]

    # The rolling-shutter image: row v is exposed at s(v), when p_c = Exp(-omega s) p_c0.
    uv = centre.copy()
    for _ in range(20):  # fixed point: the row decides the time, the time decides the row
        s = (uv[:, 1] - 0.5 * (h - 1)) / h * readout
        p = np.einsum("nij,nj->ni", Rotation.from_rotvec(-s[:, None] * omega).as_matrix(), p_c0)
        uv = p[:, :2] / p[:, 2:] * 500.0 + [320.0, 240.0]
    assert np.abs(uv - centre).max() > 5.0  # the shutter does move the keypoints
    feats = FrameFeatures(uv.astype(np.float32), uv, np.zeros(400, np.int64),
                          np.zeros((400, 32), np.uint8), np.full(400, np.nan))
    # uv_raw is float32 (as detected): its row decides the time, an error of ~1e-5 px here.
    fixed = unroll_rolling_shutter(feats, K, omega, readout, h)
    assert np.abs(fixed.uv - centre).max() < 1e-3
    assert fixed.uv_raw is feats.uv_raw and fixed.desc is feats.desc
    assert unroll_rolling_shutter(feats, K, np.zeros(3), readout, h) is feats
    assert unroll_rolling_shutter(feats, K, omega, 0.0, h) is feats


def test_rolling_shutter_readout_is_validated() -> None:
    with pytest.raises(ConfigError, match="rolling_shutter_readout_s"):
        TrackerConfig(rolling_shutter_readout_s=-1.0)
    assert TrackerConfig(rolling_shutter_readout_s=-0.02).rolling_shutter_readout_s == -0.02  # read bottom to top
    assert TrackerConfig().rolling_shutter_readout_s == 0.0  # global shutter unless a camera says otherwise


def test_the_motion_prediction_spans_a_gap_of_skipped_frames() -> None:
    """Constant velocity over the elapsed time: a live tracker that dropped frames predicts the
    whole gap, and frames at the velocity's own interval (lockstep replays) keep it as it is."""
    from memgs_ros.core.tracking.frontend.pose_tracking import MotionModel

    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec([0.0, 0.04, 0.01]).as_matrix()  # ~2.4 degrees a frame
    step[:3, 3] = (0.01, 0.0, -0.005)
    m = MotionModel()
    assert m.motion_over(0.1) is m.velocity  # unknown velocity: the identity guess, unscaled
    m.update(step @ np.eye(4), np.eye(4), 1 / 30)
    for dt in (1 / 30, 1.2 / 30, 0.7 / 30):  # stamp jitter: the velocity itself
        np.testing.assert_array_equal(m.motion_over(dt), m.velocity)
    three = m.motion_over(3 / 30)  # two frames skipped
    np.testing.assert_allclose(Rotation.from_matrix(three[:3, :3]).as_rotvec(), [0.0, 0.12, 0.03], atol=1e-9)
    np.testing.assert_allclose(three, step @ step @ step, atol=1e-12)  # the screw motion, three times
    half = m.motion_over(0.5 / 30)  # an interval half the velocity's: the square root
    np.testing.assert_allclose(half @ half, step, atol=1e-12)


# ---------------------------------------------------------------- the compiled frame path, stage by stage

def test_the_compiled_rolling_shutter_correction_equals_the_reference() -> None:
    needs_numba()
    from memgs_ros.core.tracking.features.features import _unroll_rolling_shutter

    rng = np.random.default_rng(8)
    feats = _features(rng, 700)
    for omega in (np.array([0.4, -2.5, 0.8]), np.array([0.0, 0.0, 1e-4])):
        got = unroll_rolling_shutter(feats, K, omega, 0.02, 480)
        ref = _unroll_rolling_shutter(feats, K, omega, 0.02, 480)
        np.testing.assert_allclose(got.uv, ref.uv, rtol=0.0, atol=1e-9)
        assert got.uv_raw is feats.uv_raw and got.desc is feats.desc


def _tracked_passes(mode: str, n_frames: int) -> list[tuple]:
    """Run a tracker over synthetic frames (its own extraction, map and back-end inline) and give
    every frame's local-map tracking by the compiled matcher and by the reference matcher (built
    with compiled=False), on the same map, local keyframes, features and prediction."""
    from memgs_ros.core.tracking import make_tracker
    from memgs_ros.core.tracking.frontend.pose_tracking import LocalMapMatcher
    from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

    frames = list(generate_frames(SyntheticSpec(width=320, height=240, n_frames=n_frames, seed=2, supersample=1)))
    cfg = TrackerConfig(mode=mode, ba_threaded=False, rolling_shutter_readout_s=0.02)
    tracker = make_tracker(cfg, frames[0].camera)
    compiled = tracker.matcher
    reference = LocalMapMatcher(cfg, frames[0].camera, compiled.inv_sigma_levels, compiled=False)
    assert compiled.compiled and not reference.compiled
    pairs: list[tuple] = []
    firsts: list[bool] = []  # whether the first pass searched the last frame's points
    track = compiled.track

    def both(smap, local_kfs, feats, T_pred, fallback_kf, last_tracked):  # noqa: ANN001, ANN202 - the matcher's own signature
        firsts.append(last_tracked is not None)
        pairs.append((reference.track(smap, local_kfs, feats, T_pred, fallback_kf, last_tracked),
                      track(smap, local_kfs, feats, T_pred, fallback_kf, last_tracked)))
        return pairs[-1][1]

    compiled.track = both
    try:
        for f in frames:
            tracker.track(f)
    finally:
        tracker.close()
    # RGB-D frames after the first tracked one search the last frame's points first; mono never.
    assert (sum(firsts) >= n_frames // 2) if mode == "rgbd" else not any(firsts)
    return pairs


@pytest.mark.parametrize("mode", ["rgbd", "mono"])
def test_the_compiled_projection_passes_equal_the_reference_on_tracked_frames(mode: str) -> None:
    """Same matches (points, keypoints, count before outlier rejection) and the same pose within
    1e-6, frame after frame of a tracked sequence (the fr1/rpy head gave 200 of 200 identical)."""
    needs_numba()
    pairs = _tracked_passes(mode, 24 if mode == "rgbd" else 40)
    tracked = [(r, c) for r, c in pairs if r is not None or c is not None]
    assert len(tracked) >= 10
    for ref, got in tracked:
        assert ref is not None and got is not None
        assert np.array_equal(ref.point_ids, got.point_ids) and np.array_equal(ref.kp_idx, got.kp_idx)
        assert ref.n_matches == got.n_matches
        np.testing.assert_allclose(got.T_cw, ref.T_cw, rtol=0.0, atol=1e-6)


def test_the_compiled_statistics_equal_the_reference() -> None:
    """``SparseMap.count_seen`` adds what ``project`` + ``count_visible`` + ``count_found`` add."""
    needs_numba()
    from memgs_ros.core.geometry.camera import PinholeCamera
    from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap
    from memgs_ros.core.tracking.frontend.pose_tracking import LocalMapMatcher

    rng = np.random.default_rng(3)
    camera = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    cfg = TrackerConfig()
    feats = _features(rng, 400)
    p_w = np.column_stack([rng.uniform(-3.0, 3.0, (400, 2)), rng.uniform(-0.5, 4.0, 400)])
    maps = [SparseMap(), SparseMap()]
    for smap in maps:
        smap.add_keyframe(SparseKeyframe(0, 0, np.eye(4), feats, np.full(400, -1, np.int64)))
        smap.add_points(p_w, feats.desc, feats.octave, 0, np.arange(400))
    ids = np.arange(0, 400, 2)
    found = ids[::3]
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    view = (500.0, 500.0, 320.0, 240.0, 640.0, 480.0, cfg.min_depth_m * 0.5)
    maps[0].count_seen(ids, T, view, found)
    _, vis = LocalMapMatcher(cfg, camera, np.ones(8), compiled=False).project(p_w[ids], T)
    maps[1].count_visible(ids[vis])
    maps[1].count_found(found)
    assert 0 < vis.sum() < len(ids)
    assert np.array_equal(maps[0]._pts.n_visible, maps[1]._pts.n_visible)  # noqa: SLF001
    assert np.array_equal(maps[0]._pts.n_found, maps[1]._pts.n_found)  # noqa: SLF001
