"""Synthetic RGB-D generator: determinism, exact depth and pose, noise and holes, spec strings."""
from __future__ import annotations

import numpy as np
import pytest

from memgs_ros.errors import ConfigError
from memgs_ros.io.synthetic import (
    SyntheticSpec,
    build_scene,
    generate_frames,
    parse_spec,
    render,
    trajectory,
)

SMALL = dict(width=64, height=48, n_frames=4)


@pytest.fixture(scope="module")
def scene0():
    return build_scene(0)


def test_same_seed_same_bytes_different_seed_differs(scene0):
    a = list(generate_frames(SyntheticSpec(seed=0, **SMALL), scene0))
    b = list(generate_frames(SyntheticSpec(seed=0, **SMALL)))  # scene rebuilt from scratch
    c = list(generate_frames(SyntheticSpec(seed=1, **SMALL)))
    assert len(a) == len(b) == 4
    for fa, fb in zip(a, b):
        assert fa.stamp_ns == fb.stamp_ns
        assert fa.rgb.tobytes() == fb.rgb.tobytes()
        assert fa.depth_m.tobytes() == fb.depth_m.tobytes()
        np.testing.assert_array_equal(fa.T_wc_gt, fb.T_wc_gt)
    assert any(fa.rgb.tobytes() != fc.rgb.tobytes() for fa, fc in zip(a, c))
    assert not np.allclose(a[0].T_wc_gt, c[0].T_wc_gt)


def test_scene_of_another_seed_is_refused(scene0):
    with pytest.raises(ConfigError, match="seed 0, the spec has seed 1"):
        next(generate_frames(SyntheticSpec(seed=1, **SMALL), scene0))


def test_frames_have_camera_stamps_and_texture(scene0):
    spec = SyntheticSpec(fps=30.0, **SMALL)
    frames = list(generate_frames(spec, scene0))
    assert [f.camera for f in frames] == [spec.camera] * 4
    stamps = np.array([f.stamp_ns for f in frames])
    assert np.all(stamps % 1000 == 0)  # whole microseconds: TUM text files round-trip exactly
    assert np.abs(np.diff(stamps) - 1e9 / 30).max() <= 1000
    for f in frames:
        assert f.rgb.dtype == np.uint8 and f.rgb.shape == (48, 64, 3)
        assert f.depth_m.dtype == np.float32 and f.valid_depth_mask().all()
        assert float(f.depth_m.min()) > 0.3 and float(f.depth_m.max()) < 8.0
        # a textured view, not a flat colour
        assert f.rgb.reshape(-1, 3).std(axis=0).min() > 10
        R = f.T_wc_gt[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_depth_backprojects_onto_the_hit_plane(scene0):
    """Every pixel's backprojected point lies on one of the scene's face planes, within the face."""
    spec = SyntheticSpec(width=80, height=60, n_frames=3)
    for f in generate_frames(spec, scene0):
        v, u = np.mgrid[0:60, 0:80]
        p_c = f.camera.backproject(u.ravel(), v.ravel(), f.depth_m.ravel().astype(np.float64))
        p_w = p_c @ f.T_wc_gt[:3, :3].T + f.T_wc_gt[:3, 3]
        normals = np.array([s.normal for s in scene0.surfaces])
        ds = np.array([s.plane_d for s in scene0.surfaces])
        dist = np.abs(p_w @ normals.T - ds)  # [M, S]
        best = dist.argmin(1)
        # float32 depth: 1e-6 relative of ~5 m
        assert dist.min(1).max() < 2e-5
        # and inside the face extent (the plane alone is not enough)
        for k in np.unique(best):
            s = scene0.surfaces[k]
            rel = p_w[best == k] - s.origin
            assert (rel @ s.u_axis > -1e-4).all() and (rel @ s.u_axis < s.size_m[0] + 1e-4).all()
            assert (rel @ s.v_axis > -1e-4).all() and (rel @ s.v_axis < s.size_m[1] + 1e-4).all()


def test_known_view_depth_on_far_wall(scene0):
    """Looking straight down +x from x=-1 at the wall x=3 (no box on the centre ray): depth 4 m."""
    spec = SyntheticSpec(width=65, height=49)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # optical z -> world +x
    T[:3, 3] = (-1.0, 0.0, 2.2)
    _, depth = render(scene0, spec.camera, T)
    cy, cx = int(round(spec.camera.cy)), int(round(spec.camera.cx))
    assert depth[cy, cx] == pytest.approx(4.0, abs=1e-5)


def test_noise_and_holes(scene0):
    clean = next(generate_frames(SyntheticSpec(**SMALL), scene0))
    noisy = next(generate_frames(SyntheticSpec(depth_noise_std_m=0.01, **SMALL), scene0))
    holes = next(generate_frames(SyntheticSpec(hole_fraction=0.1, **SMALL), scene0))
    diff = noisy.depth_m - clean.depth_m
    assert 0.007 < float(diff.std()) < 0.013 and abs(float(diff.mean())) < 0.003
    frac = float((holes.depth_m == 0).mean())
    assert 0.07 < frac < 0.13
    keep = holes.depth_m > 0
    np.testing.assert_array_equal(holes.depth_m[keep], clean.depth_m[keep])
    np.testing.assert_array_equal(noisy.rgb, clean.rgb)
    # holes are blobs, not salt: most hole pixels have a hole neighbour
    m = holes.depth_m == 0
    neigh = np.zeros_like(m)
    neigh[1:] |= m[:-1]
    neigh[:-1] |= m[1:]
    assert (neigh[m]).mean() > 0.8


def test_path_stays_inside_room_and_moves(scene0):
    stamps, poses = trajectory(SyntheticSpec(n_frames=300))
    pos = poses[:, :3, 3]
    lo, hi = scene0.room_lo, scene0.room_hi
    assert (pos > lo + 1.0).all() and (pos < hi - 0.8).all()
    for blo, bhi in zip(scene0.boxes_lo, scene0.boxes_hi):
        inside = np.all((pos > blo - 0.3) & (pos < bhi + 0.3), axis=1)
        assert not inside.any()
    travel = np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()
    assert 1.0 < travel < 2.5
    angles = [np.degrees(np.arccos(np.clip((np.trace(poses[0, :3, :3].T @ P[:3, :3]) - 1) / 2, -1, 1))) for P in poses]
    assert 20 < max(angles) < 120
    assert np.all(np.diff(stamps) > 0)


def test_parse_spec_round_trip_and_errors():
    s = parse_spec("synthetic:w=160,h=120,n=60,seed=3,noise=0.01,holes=0.05")
    assert (s.width, s.height, s.n_frames, s.seed) == (160, 120, 60, 3)
    assert s.depth_noise_std_m == 0.01 and s.hole_fraction == 0.05
    assert parse_spec(s.to_string()) == s
    assert parse_spec("synthetic") == SyntheticSpec()
    with pytest.raises(ConfigError, match="bad item 'bogus=1'"):
        parse_spec("synthetic:bogus=1")
    with pytest.raises(ConfigError, match="w='x' is not a number"):
        parse_spec("synthetic:w=x")
    with pytest.raises(ConfigError, match="hole fraction"):
        parse_spec("synthetic:holes=1.5")
