"""Patch-Grid sampling on hand-made keypoint layouts, seeds for RGB-D and monocular keyframes,
and undistortion of keyframe images."""
from __future__ import annotations

import numpy as np
import pytest

from memgs_ros.core.geometry.camera import TUM_FR1, PinholeCamera
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.geometry.view import Undistorter, undistort_uv, view_preparation
from memgs_ros.core.sampling import (
    PG_RGBD,
    SOURCE_KEYPOINT,
    SOURCE_PATCH_GRID,
    PatchGridConfig,
    SeedPoints,
    patch_grid_uv,
    seeds_mono,
    seeds_rgbd,
)
from memgs_ros.errors import ConfigError, DataError


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _cell_counts(uv: np.ndarray, width: int, height: int, g: int) -> np.ndarray:
    nx, ny = -(-width // g), -(-height // g)
    c = np.zeros((ny, nx), dtype=int)
    np.add.at(c, (uv[:, 1].astype(int) // g, uv[:, 0].astype(int) // g), 1)
    return c


def _points_in_cell(cx: int, cy: int, n: int, g: int = 80, offset: int = 10) -> np.ndarray:
    """n distinct keypoints inside cell (cx, cy), sub-pixel positions."""
    k = np.arange(n)
    return np.c_[cx * g + offset + 3 * k + 0.3, cy * g + offset + 2 * k + 0.2]


def test_empty_image_640x480_at_80px_fills_every_cell() -> None:
    uv = patch_grid_uv(np.zeros((0, 2)), 640, 480, grid_size=80, rng=_rng())
    assert uv.shape == (384, 2)  # 48 cells x 8
    assert np.array_equal(_cell_counts(uv, 640, 480, 80), np.full((6, 8), 8))


def test_cells_filled_up_to_num_thr() -> None:
    kps = np.concatenate([
        _points_in_cell(0, 0, 8),  # full: no samples
        _points_in_cell(1, 0, 12),  # more than enough: no samples
        _points_in_cell(2, 0, 3),  # 3 keypoints: 5 samples
        _points_in_cell(3, 0, 7),  # 7 keypoints: 1 sample
    ])
    uv = patch_grid_uv(kps, 640, 480, grid_size=80, num_thr=8, rng=_rng(1))
    counts = _cell_counts(uv, 640, 480, 80)
    assert counts[0, :4].tolist() == [0, 0, 5, 1]
    assert (counts[0, 4:] == 8).all() and (counts[1:] == 8).all()
    assert uv.shape[0] == 384 - 8 - 8 - 3 - 7


def test_border_cell_rule_at_50px() -> None:
    # 640x480: right partial 40 px, bottom 30 px; neither is narrower than 50 - 30 = 20: kept.
    uv = patch_grid_uv(np.zeros((0, 2)), 640, 480, grid_size=50, rng=_rng())
    counts = _cell_counts(uv, 640, 480, 50)
    assert counts.shape == (10, 13)
    assert (counts == 8).all() and uv.shape[0] == 130 * 8
    # 615 px wide: the right partial is 15 px < 20 -> skipped; 620 px: 20 px is not narrower -> kept.
    uv = patch_grid_uv(np.zeros((0, 2)), 615, 480, grid_size=50, rng=_rng())
    assert uv[:, 0].max() < 600 and uv.shape[0] == 12 * 10 * 8
    uv = patch_grid_uv(np.zeros((0, 2)), 620, 480, grid_size=50, rng=_rng())
    assert uv.shape[0] == 13 * 10 * 8
    assert ((uv[:, 0] >= 605) & (uv[:, 0] < 615)).sum() == 10 * 8
    # 1200x680 at 80 px (Replica): the 40 px bottom row is shorter than 50 -> skipped.
    uv = patch_grid_uv(np.zeros((0, 2)), 1200, 680, grid_size=80, rng=_rng())
    assert uv.shape[0] == 15 * 8 * 8 and uv[:, 1].max() < 640


def test_samples_stay_inside_margins_on_integer_pixels() -> None:
    g, m = 50, 5
    uv = patch_grid_uv(np.zeros((0, 2)), 640, 480, grid_size=g, margin_px=m, rng=_rng(2))
    assert np.array_equal(uv, np.round(uv))
    x0 = (uv[:, 0] // g) * g
    y0 = (uv[:, 1] // g) * g
    x1 = np.minimum(x0 + g, 640)
    y1 = np.minimum(y0 + g, 480)
    assert ((uv[:, 0] >= x0 + m) & (uv[:, 0] < x1 - m)).all()
    assert ((uv[:, 1] >= y0 + m) & (uv[:, 1] < y1 - m)).all()
    # The whole margin box is used: over many draws both extremes show up.
    local = uv[:, 0] - x0
    assert local.min() == m and local[x1 - x0 == g].max() == g - m - 1


def test_samples_avoid_keypoint_pixels_and_each_other() -> None:
    # Tiny cells (12 px, margin 2 -> 8x8 sampling box) with 7 keypoints each: one sample per
    # cell, which hits a keypoint pixel 7/64 of the time unless redrawn.
    g, w, h = 12, 240, 240
    rng = _rng(3)
    kps = []
    for cy in range(h // g):
        for cx in range(w // g):
            box = rng.choice(64, size=7, replace=False)
            kps.append(np.c_[cx * g + 2 + box % 8, cy * g + 2 + box // 8] + rng.uniform(-0.4, 0.4, (7, 2)))
    kps_arr = np.concatenate(kps)
    uv = patch_grid_uv(kps_arr, w, h, grid_size=g, num_thr=8, margin_px=2, skip_short_px=0, rng=_rng(4))
    assert uv.shape[0] == (w // g) * (h // g)
    kp_pix = set(map(tuple, np.round(kps_arr).astype(int).tolist()))
    assert not any(tuple(p) in kp_pix for p in uv.astype(int).tolist())
    # 40 samples in one 8x8 box: collisions between samples are certain, all must be redrawn.
    uv2 = patch_grid_uv(np.zeros((0, 2)), 12, 12, grid_size=12, num_thr=40, margin_px=2,
                        skip_short_px=0, rng=_rng(5))
    assert uv2.shape[0] == 40
    assert len(set(map(tuple, uv2.astype(int).tolist()))) == 40


def test_keypoints_outside_the_image_are_ignored() -> None:
    kps = np.array([[-5.0, 10.0], [700.0, 10.0], [10.0, 500.0]])
    uv = patch_grid_uv(kps, 640, 480, rng=_rng())
    assert uv.shape[0] == 384


def test_deterministic_with_seed() -> None:
    kps = _points_in_cell(2, 3, 4)
    a = patch_grid_uv(kps, 640, 480, rng=_rng(7))
    b = patch_grid_uv(kps, 640, 480, rng=_rng(7))
    c = patch_grid_uv(kps, 640, 480, rng=_rng(8))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    cfg = PatchGridConfig(seed=3)
    assert np.array_equal(patch_grid_uv(kps, 640, 480, rng=cfg.rng_for(5)),
                          patch_grid_uv(kps, 640, 480, rng=cfg.rng_for(5)))
    assert not np.array_equal(patch_grid_uv(kps, 640, 480, rng=cfg.rng_for(5)),
                              patch_grid_uv(kps, 640, 480, rng=cfg.rng_for(6)))
    with pytest.raises(ValueError, match="rng"):
        patch_grid_uv(kps, 640, 480)


def test_config_validation_names_the_field() -> None:
    with pytest.raises(ConfigError, match="margin_px"):
        PatchGridConfig(grid_size=10, margin_px=5)
    with pytest.raises(ConfigError, match="min_depth_m < max_depth_m"):
        PatchGridConfig(min_depth_m=5.0, max_depth_m=1.0)
    assert PG_RGBD.grid_size == 80


# --- seeds ---------------------------------------------------------------------------------

CAM = PinholeCamera(160, 120, 100.0, 110.0, 79.5, 59.5)


def _pose() -> np.ndarray:
    c, s = np.cos(0.4), np.sin(0.4)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    T[:3, 3] = [1.0, -2.0, 0.5]
    return T


def _coded_rgb(h: int = 120, w: int = 160) -> np.ndarray:
    """Colour that encodes the pixel: R = u, G = v, B = 7."""
    v, u = np.mgrid[0:h, 0:w]
    return np.stack([u, v, np.full_like(u, 7)], axis=-1).astype(np.uint8)


def _to_pixels(seeds: SeedPoints, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    T_cw = invert_pose(T_wc)
    p_c = seeds.points_w.astype(np.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
    u, v = CAM.project(p_c)
    return u, v, p_c[:, 2]


def test_rgbd_seeds_backproject_to_their_pixels_and_depths() -> None:
    T = _pose()
    v, u = np.mgrid[0:120, 0:160]
    depth = (1.0 + 0.01 * u + 0.02 * v).astype(np.float32)
    kps = np.array([[10.2, 20.4], [100.0, 50.0], [30.0, 90.0]])
    kd = np.array([2.0, np.nan, 3.5])
    seeds = seeds_rgbd(_coded_rgb(), depth, CAM, T, 4, kps, kd, PG_RGBD, _rng())
    assert seeds.keyframe_id == 4
    assert seeds.points_w.dtype == np.float32 and seeds.colors.dtype == np.float32
    kp = seeds.source == SOURCE_KEYPOINT
    assert kp.sum() == 2  # the NaN-depth keypoint is dropped
    pu, pv, pz = _to_pixels(seeds, T)
    # Keypoints: back-projected at their pixel (10, 20) and (30, 90) with their own depth.
    assert np.allclose(pu[kp], [10, 30], atol=1e-3) and np.allclose(pv[kp], [20, 90], atol=1e-3)
    assert np.allclose(pz[kp], [2.0, 3.5], atol=1e-5)
    # By hand: pixel (10, 20) at depth 2 is p_c = ((10 - cx) / fx * 2, (20 - cy) / fy * 2, 2).
    p_c = np.array([(10 - 79.5) / 100.0 * 2, (20 - 59.5) / 110.0 * 2, 2.0])
    assert np.allclose(seeds.points_w[0], T[:3, :3] @ p_c + T[:3, 3], atol=1e-5)
    # Samples: back-projected with the depth image value at their pixel.
    pg = seeds.source == SOURCE_PATCH_GRID
    # 160x120 at 80 px: 2 full cells (the 40 px bottom row is shorter than 50: skipped); each
    # holds one keypoint (with or without depth, all count): 2 x 7 samples.
    assert pg.sum() == 2 * 7
    iu, iv = np.round(pu[pg]).astype(int), np.round(pv[pg]).astype(int)
    assert np.allclose(pu[pg], iu, atol=1e-3) and np.allclose(pv[pg], iv, atol=1e-3)
    assert np.allclose(pz[pg], depth[iv, iu], rtol=1e-5)
    # Colours are read at the pixel, in [0, 1].
    assert np.allclose(seeds.colors[:, 0] * 255, np.round(pu), atol=1e-3)
    assert np.allclose(seeds.colors[:, 1] * 255, np.round(pv), atol=1e-3)
    assert np.allclose(seeds.colors[:, 2], 7 / 255)


def test_rgbd_depth_validity_filter() -> None:
    depth = np.full((120, 160), 2.0, dtype=np.float32)
    depth[:, :40] = np.nan
    depth[:, 40:80] = 0.0
    depth[:, 80:120] = 50.0  # beyond max_depth_m 40
    seeds = seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 0, np.zeros((0, 2)), np.zeros(0), PG_RGBD, _rng())
    u, _, z = _to_pixels(seeds, np.eye(4))
    assert len(seeds) > 0 and (u >= 120 - 1e-3).all() and np.allclose(z, 2.0)
    # Parameterised range: allowing up to 60 m keeps the 50 m column too.
    wide = PatchGridConfig(max_depth_m=60.0)
    seeds_w = seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 0, np.zeros((0, 2)), np.zeros(0), wide, _rng())
    assert len(seeds_w) > len(seeds)
    assert seeds_w.n_patch_grid == seeds_w.source.size
    # Keypoint depths are filtered by the same range.
    kps = np.array([[130.0, 10.0], [131.0, 10.0], [132.0, 10.0]])
    s = seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 0, kps, np.array([0.0, 45.0, 1.0]), PG_RGBD, _rng())
    assert s.n_keypoint == 1


def test_rgbd_disabled_gives_keypoints_only_and_inputs_are_checked() -> None:
    depth = np.full((120, 160), 2.0, dtype=np.float32)
    off = PatchGridConfig(enabled=False)
    kps = np.array([[10.0, 10.0], [170.0, 10.0]])  # the second lies outside the image
    s = seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 0, kps, np.array([1.0, 1.0]), off, _rng())
    assert len(s) == 1 and s.n_keypoint == 1
    with pytest.raises(DataError, match="undistorted"):
        seeds_rgbd(_coded_rgb(480, 640), np.ones((480, 640), np.float32), TUM_FR1, np.eye(4), 0,
                   np.zeros((0, 2)), np.zeros(0), PG_RGBD, _rng())
    with pytest.raises(DataError, match=r"keyframe depth must be \[120, 160\]"):
        seeds_rgbd(_coded_rgb(), np.ones((10, 10), np.float32), CAM, np.eye(4), 0, kps,
                   np.ones(2), PG_RGBD, _rng())
    with pytest.raises(DataError, match="1 entries for 2 keypoints"):
        seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 0, kps, np.ones(1), PG_RGBD, _rng())


def test_rgbd_default_rng_is_per_keyframe_deterministic() -> None:
    depth = np.full((120, 160), 2.0, dtype=np.float32)
    a = seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 3, np.zeros((0, 2)), np.zeros(0))
    b = seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 3, np.zeros((0, 2)), np.zeros(0))
    c = seeds_rgbd(_coded_rgb(), depth, CAM, np.eye(4), 4, np.zeros((0, 2)), np.zeros(0))
    assert np.array_equal(a.points_w, b.points_w)
    assert not np.array_equal(a.points_w, c.points_w)


def test_mono_seeds_take_nearest_keypoint_depth_within_max_distance() -> None:
    T = _pose()
    kps = np.array([[20.0, 20.0], [60.0, 20.0], [140.0, 100.0], [100.0, 60.0]])
    kd = np.array([1.0, 2.0, 3.0, np.nan])  # the last has no 3D point
    cfg = PatchGridConfig(grid_size=40, max_px_dist=15.0)
    seeds = seeds_mono(_coded_rgb(), CAM, T, 9, kps, kd, cfg, _rng(11))
    assert seeds.n_keypoint == 3
    pu, pv, pz = _to_pixels(seeds, T)
    pg = seeds.source == SOURCE_PATCH_GRID
    assert pg.sum() > 0
    uv = np.c_[pu[pg], pv[pg]]
    with_depth = kps[:3]
    d = np.linalg.norm(uv[:, None, :] - with_depth[None], axis=-1)  # [S, 3]
    assert (d.min(axis=1) <= 15.0 + 1e-3).all()
    assert np.allclose(pz[pg], kd[:3][d.argmin(axis=1)], atol=1e-5)
    # Every sample that had a keypoint with depth within 15 px was kept.
    all_uv = patch_grid_uv(kps, 160, 120, 40, 8, 5, 30, _rng(11))
    dd = np.linalg.norm(all_uv[:, None, :] - with_depth[None], axis=-1).min(axis=1)
    assert pg.sum() == (dd <= 15.0).sum()
    # A larger radius keeps more samples.
    wide = seeds_mono(_coded_rgb(), CAM, T, 9, kps, kd, PatchGridConfig(grid_size=40, max_px_dist=200.0), _rng(11))
    assert wide.n_patch_grid == all_uv.shape[0] > pg.sum()


def test_mono_without_any_keypoint_depth_gives_no_seeds() -> None:
    s = seeds_mono(_coded_rgb(), CAM, np.eye(4), 0, np.array([[5.0, 5.0]]), np.array([np.nan]))
    assert len(s) == 0 and s.points_w.shape == (0, 3)


# --- undistortion --------------------------------------------------------------------------

def test_undistort_depth_is_nearest_and_agrees_with_undistort_uv() -> None:
    cam = TUM_FR1
    h, w = cam.height, cam.width
    v, u = np.mgrid[0:h, 0:w]
    code = (v * w + u).astype(np.float32)  # exact in float32 below 2^24
    rgb = np.zeros((h, w, 3), np.uint8)
    for crop in (False, True):
        und = Undistorter(cam, crop_to_valid=crop)
        rgb_u, depth_u, cam_u = und(rgb, code)
        assert depth_u is not None and rgb_u.shape == rgb.shape and not cam_u.has_distortion
        finite = np.isfinite(depth_u)
        if crop:
            # The zoomed camera sees only the region every output pixel samples: no border.
            assert cam_u.fx > cam.fx and finite.all() and und.valid_mask.all()
        else:
            assert cam_u == cam.undistorted() and 0.9 < finite.mean() < 0.99
            assert (und.valid_mask == finite).mean() > 0.995  # nearest vs bilinear reach differ at the edge
        # Nearest neighbour: every output value is one of the input values (no blends).
        vals = depth_u[finite]
        assert np.array_equal(vals, np.round(vals)) and vals.min() >= 0 and vals.max() < h * w
        # A distorted keypoint lands where undistort_uv says: the source pixel of that output
        # pixel is the keypoint's pixel (within one pixel of rounding); the tracker's keypoints
        # (undistorted in K) map there too.
        pts_d = np.array([[50.0, 60.0], [320.0, 240.0], [600.0, 420.0]])
        pts_u = und.undistort_uv(pts_d)
        assert np.allclose(und.from_pinhole_uv(undistort_uv(pts_d, cam)), pts_u, atol=1e-6)
        iu, iv = np.round(pts_u).astype(int).T
        src = depth_u[iv, iu].astype(int)
        src_uv = np.c_[src % w, src // w]
        assert np.abs(src_uv - pts_d).max() <= 1.5
        assert np.abs(pts_u - pts_d).max() > 2.0  # the distortion is real at the corners
    # The shared view preparation at full size gives the default (cropped) images.
    rgb_u, depth_u, cam_u = Undistorter(cam)(rgb, code)
    view = view_preparation(cam)
    rgb_c, depth_c = view(rgb, code)
    cam_c = view.camera
    assert cam_c == cam_u and np.array_equal(rgb_c, rgb_u)
    assert np.array_equal(depth_c, depth_u, equal_nan=True)


def test_undistort_without_distortion_is_identity_and_checks_size() -> None:
    rgb = _coded_rgb()
    rgb_u, depth_u, cam_u = Undistorter(CAM)(rgb, None)
    assert rgb_u is rgb and depth_u is None and cam_u == CAM
    assert np.array_equal(undistort_uv(np.array([[3.0, 4.0]]), CAM), [[3.0, 4.0]])
    with pytest.raises(DataError, match="160x120"):
        Undistorter(CAM)(np.zeros((10, 10, 3), np.uint8))
