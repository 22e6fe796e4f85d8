"""The bundle adjustments' compiled kernels (``backend/ba_kernels.py``) against their numpy twins:
stage by stage on a problem with every kind of observation, and whole local and global BAs,
including the local BAs a tracker asks for on tracked frames."""
from __future__ import annotations

import numpy as np
import pytest
from kernel_support import BF, K, needs_numba

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking import TrackerConfig, make_tracker
from memgs_ros.core.tracking.backend import actor as backend_actor
from memgs_ros.core.tracking.backend.bundle_adjustment import (
    BAGeometry,
    BAProblem,
    BAResult,
    apply_left_update,
    local_bundle_adjustment,
)
from memgs_ros.core.tracking.backend.global_ba import global_bundle_adjustment
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames


def _problem(seed: int = 4, n_cams: int = 6, n_pts: int = 400) -> BAProblem:
    """Cameras along a short arc looking at points 2-6 m ahead, seen by a random subset of them:
    two fixed cameras, a third of the observations without depth, octave scales, 5 % gross
    outliers (Huber weights below 1) and points seen by one camera only or by fixed ones only."""
    rng = np.random.default_rng(seed)
    T = np.stack([np.eye(4)] * n_cams)
    for c in range(n_cams):
        T[c] = apply_left_update(np.eye(4), np.r_[0.0, 0.05 * c, 0.0, -0.1 * c, 0.0, 0.0])
    X = np.column_stack([rng.uniform(-2.0, 2.0, n_pts), rng.uniform(-1.5, 1.5, n_pts), rng.uniform(2.0, 6.0, n_pts)])
    seen = rng.random((n_pts, n_cams)) < 0.6
    seen[:10] = False
    seen[:10, 3] = True  # one camera only
    seen[10:20] = False
    seen[10:20, :2] = True  # the fixed cameras only
    pts, cams = np.nonzero(seen)
    p_c = np.einsum("oij,oj->oi", T[cams, :3, :3], X[pts]) + T[cams, :3, 3]
    uv = K[:2, :2] @ (p_c[:, :2] / p_c[:, 2:]).T
    uv = uv.T + K[:2, 2] + rng.normal(0.0, 0.5, (len(pts), 2))
    uv[rng.random(len(pts)) < 0.05] += 30.0
    depth = p_c[:, 2] + rng.normal(0.0, 0.01, len(pts))
    depth[rng.random(len(pts)) < 0.33] = np.nan
    T0 = T.copy()
    for c in range(2, n_cams):
        T0[c] = apply_left_update(T[c], rng.normal(0.0, 0.01, 6))
    fixed = np.arange(n_cams) < 2
    sigma = 1.2 ** -rng.integers(0, 4, len(pts)).astype(float)
    return BAProblem(T0, fixed, X + rng.normal(0.0, 0.02, X.shape), cams, pts, uv, depth, sigma)


def _assert_same(got: BAResult, ref: BAResult) -> None:
    np.testing.assert_allclose(got.T_cw, ref.T_cw, rtol=0.0, atol=1e-9)
    # A point seen by one camera without depth is barely constrained along its ray: there the
    # two summation orders part by ~1e-7 of the point's distance.
    off = np.linalg.norm(got.points_w - ref.points_w, axis=1)
    assert np.all(off <= 1e-6 * np.linalg.norm(ref.points_w, axis=1) + 1e-9), off.max()
    assert np.array_equal(got.obs_inlier, ref.obs_inlier)
    assert got.n_evaluations == ref.n_evaluations
    assert got.final_cost == pytest.approx(ref.final_cost, rel=1e-9)


def test_each_kernel_equals_its_numpy_twin() -> None:
    needs_numba()
    prob = _problem()
    fast, ref = BAGeometry(prob, K, BF, 2.45, compiled=True), BAGeometry(prob, K, BF, 2.45, compiled=False)
    x = fast.initial()
    (pc_f, r_f), cost_f = fast.evaluate(x)
    (pc_r, r_r), cost_r = ref.evaluate(x)
    np.testing.assert_allclose(pc_f, pc_r, rtol=1e-13, atol=0.0)
    np.testing.assert_allclose(r_f, r_r, rtol=1e-12, atol=1e-12)
    assert cost_f == pytest.approx(cost_r, rel=1e-12)
    e = np.linalg.norm(r_r, axis=1)
    assert (e > 2.45).sum() > 20  # the Huber weights are exercised
    b_f, b_r = fast.blocks(x, (pc_r, r_r)), ref.blocks(x, (pc_r, r_r))
    for name in ("Hpp", "gp", "Hcp", "Hcc", "gc"):
        a, b = getattr(b_f, name), getattr(b_r, name)
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-9 * np.abs(b).max(), err_msg=name)
    for lam in (1e-3, 10.0):
        inv_f, S_f, rhs_f = fast.reduce(b_r, lam)
        inv_r, S_r, rhs_r = ref.reduce(b_r, lam)
        np.testing.assert_allclose(inv_f, inv_r, rtol=1e-8, atol=1e-9 * np.abs(inv_r).max())
        np.testing.assert_allclose(S_f, S_r, rtol=0.0, atol=1e-10 * np.abs(S_r).max())
        np.testing.assert_allclose(rhs_f, rhs_r, rtol=0.0, atol=1e-10 * np.abs(rhs_r).max())
    dc = np.random.default_rng(0).normal(0.0, 1e-3, (fast.nf, 6))
    dX_f, dX_r = fast.back_substitute(b_r, inv_r, dc), ref.back_substitute(b_r, inv_r, dc)
    np.testing.assert_allclose(dX_f, dX_r, rtol=0.0, atol=1e-10 * np.abs(dX_r).max())


def test_local_and_global_ba_compiled_equal_numpy() -> None:
    needs_numba()
    prob = _problem(seed=5)
    got = local_bundle_adjustment(prob, K, BF, 2.45, 10, compiled=True)
    ref = local_bundle_adjustment(prob, K, BF, 2.45, 10, compiled=False)
    assert got.final_cost < 0.5 * got.initial_cost
    _assert_same(got, ref)
    g_got = global_bundle_adjustment(prob, K, BF, 2.45, 10, compiled=True)
    g_ref = global_bundle_adjustment(prob, K, BF, 2.45, 10, compiled=False)
    _assert_same(g_got, g_ref)
    # No free camera: the points alone move.
    only_points = BAProblem(prob.T_cw, np.ones(len(prob.T_cw), bool), prob.points_w, prob.obs_cam, prob.obs_point,
                            prob.obs_uv, prob.obs_depth, prob.obs_inv_sigma)
    got = local_bundle_adjustment(only_points, K, BF, 2.45, 5, compiled=True)
    _assert_same(got, local_bundle_adjustment(only_points, K, BF, 2.45, 5, compiled=False))
    np.testing.assert_allclose(got.T_cw, prob.T_cw, rtol=0.0, atol=1e-12)  # re-orthonormalised only
    assert got.final_cost < got.initial_cost


@pytest.mark.parametrize("mode", ["rgbd", "mono"])
def test_the_trackers_local_bas_compiled_equal_numpy(mode: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every local BA a tracker asks for over a synthetic sequence (its own features, map and
    back-end inline), solved by the kernels and by the numpy twins: the same poses within 1e-9."""
    needs_numba()
    from memgs_ros.core.tracking.frontend import monocular

    asked: list[tuple] = []

    def both(prob: BAProblem, K: np.ndarray, bf: float, huber: float, iterations: int) -> BAResult:
        got = local_bundle_adjustment(prob, K, bf, huber, iterations, compiled=True)
        asked.append((got, local_bundle_adjustment(prob, K, bf, huber, iterations, compiled=False)))
        return got

    monkeypatch.setattr(backend_actor, "local_bundle_adjustment", both)
    monkeypatch.setattr(monocular, "local_bundle_adjustment", both)
    frames = list(generate_frames(SyntheticSpec(width=320, height=240, n_frames=30 if mode == "rgbd" else 40, seed=2,
                                                supersample=1)))
    tracker = make_tracker(TrackerConfig(mode=mode, ba_threaded=False, keyframe_max_frames=5), frames[0].camera)
    try:
        for f in frames:
            tracker.track(f)
    finally:
        tracker.close()
    assert len(asked) >= 3
    for got, ref in asked:
        _assert_same(got, ref)
        assert np.isfinite(got.final_cost) and got.final_cost <= got.initial_cost
    # The poses are the map's: a camera moved by a BA is still a rigid transform.
    for got, _ in asked:
        np.testing.assert_allclose(got.T_cw[:, :3, :3] @ got.T_cw[:, :3, :3].transpose(0, 2, 1),
                                   np.broadcast_to(np.eye(3), (len(got.T_cw), 3, 3)), atol=1e-12)
        assert np.allclose(invert_pose(invert_pose(got.T_cw)), got.T_cw)
