"""Global bundle adjustment (sparse Schur) on a toy ring map with a loop error, and the LM loop it shares."""
from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.backend.bundle_adjustment import (
    BAProblem,
    apply_left_update,
    local_bundle_adjustment,
)
from memgs_ros.core.tracking.backend.global_ba import global_bundle_adjustment

K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
BF = 200.0 * 0.08


def _ring(n_cams: int = 24, n_pts: int = 1500, seed: int = 0) -> tuple[np.ndarray, np.ndarray, BAProblem]:
    """Cameras on a 2 m circle looking outwards at points on a 4 m cylinder; the loop closes
    through shared points between the last and first cameras. Returns (T_cw_true, X_true, problem
    with drifted poses and points)."""
    rng = np.random.default_rng(seed)
    T_wc = []
    for a in np.linspace(0, 2 * np.pi, n_cams, endpoint=False):
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])  # z -> outwards
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [2 * np.sin(a), 0, 2 * np.cos(a)]
        T_wc.append(T)
    T_cw = invert_pose(np.stack(T_wc))
    phi = rng.uniform(0, 2 * np.pi, n_pts)
    X = np.column_stack([4.5 * np.sin(phi), rng.uniform(-1, 1, n_pts), 4.5 * np.cos(phi)])
    cams, pts, uvs, deps = [], [], [], []
    for c in range(n_cams):
        p_c = X @ T_cw[c, :3, :3].T + T_cw[c, :3, 3]
        z = p_c[:, 2]
        uv = np.column_stack([K[0, 0] * p_c[:, 0] / z + K[0, 2], K[1, 1] * p_c[:, 1] / z + K[1, 2]])
        vis = np.flatnonzero((z > 0.5) & (uv[:, 0] > 0) & (uv[:, 0] < 320) & (uv[:, 1] > 0) & (uv[:, 1] < 240))
        cams += [c] * len(vis)
        pts += vis.tolist()
        uvs.append(uv[vis] + rng.normal(0, 0.5, (len(vis), 2)))
        deps.append(z[vis] + rng.normal(0, 0.005, len(vis)))
    # Drift: each camera accumulates a small rotation and translation error; points follow their first camera.
    T_drift = T_cw.copy()
    acc = np.eye(4)
    for c in range(1, n_cams):
        acc = apply_left_update(acc, np.r_[rng.normal(0, 0.004, 3), rng.normal(0, 0.01, 3)])
        T_drift[c] = T_cw[c] @ invert_pose(acc)
    obs_cam, obs_pt = np.array(cams), np.array(pts)
    first = np.full(n_pts, -1)
    for c, p in zip(obs_cam[::-1], obs_pt[::-1]):
        first[p] = c
    X_drift = X.copy()
    for p in range(n_pts):
        c = first[p]
        if c >= 0:
            D = invert_pose(T_drift[c]) @ T_cw[c]  # T_wc_drift T_cw_true
            X_drift[p] = D[:3, :3] @ X[p] + D[:3, 3]
    fixed = np.zeros(n_cams, bool)
    fixed[0] = True
    prob = BAProblem(T_drift, fixed, X_drift, obs_cam, obs_pt, np.concatenate(uvs), np.concatenate(deps),
                     np.ones(len(obs_cam)))
    return T_cw, X, prob


def _pos_err(T_cw: np.ndarray, T_true: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((invert_pose(T_cw)[:, :3, 3] - invert_pose(T_true)[:, :3, 3]) ** 2, 1))))


def test_global_ba_removes_the_loop_error_and_matches_the_dense_solver() -> None:
    T_true, _, prob = _ring()
    before = _pos_err(prob.T_cw, T_true)
    res = global_bundle_adjustment(prob, K, BF, huber_px=2.45, max_iterations=15)
    assert res.final_cost < 0.05 * res.initial_cost
    after = _pos_err(res.T_cw, T_true)
    assert before > 0.05 and after < 0.4 * before, (before, after)
    assert np.all(res.T_cw[0] == prob.T_cw[0])  # the gauge stays
    assert res.obs_inlier.mean() > 0.95
    dense = local_bundle_adjustment(prob, K, BF, huber_px=2.45, max_iterations=15)
    assert abs(dense.final_cost - res.final_cost) < 0.05 * dense.final_cost + 1.0


def test_global_ba_time_budget_returns_the_best_so_far() -> None:
    _, _, prob = _ring(n_cams=12, n_pts=400)
    res = global_bundle_adjustment(prob, K, BF, huber_px=2.45, max_iterations=50, time_budget_s=0.0)
    assert res.n_evaluations == 1 and res.final_cost == res.initial_cost


def test_global_ba_observations_per_point_are_bounded() -> None:
    # A place seen again and again gives points with a hundred observations: the global BA keeps
    # few enough per point that its observation pairs stay bounded; ordinary maps keep them all.
    from memgs_ros.core.tracking.backend.ba_problem import _GLOBAL_BA_MAX_PAIRS, _max_observations_per_point

    assert _max_observations_per_point([2, 3, 5]) == 5
    m = _max_observations_per_point([100] * 23000)
    assert 2 <= m < 100 and 23000 * m * m <= _GLOBAL_BA_MAX_PAIRS


def test_one_lm_loop_stops_on_convergence_or_budget() -> None:
    from memgs_ros.core.tracking.backend.lm import LMSettings, lm_iterations, solve

    # Fit a, b of y = a * exp(b t): Gauss-Newton with the shared damping loop.
    t = np.linspace(0.0, 1.0, 20)
    y = 2.0 * np.exp(-1.5 * t)

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, float]:
        r = x[0] * np.exp(x[1] * t) - y
        return r, 0.5 * float(r @ r)

    def linearise(x: np.ndarray, r: np.ndarray) -> Callable[[float], np.ndarray | None]:
        J = np.column_stack([np.exp(x[1] * t), x[0] * t * np.exp(x[1] * t)])
        H, g = J.T @ J, J.T @ r

        def propose(lam: float) -> np.ndarray | None:
            return x - np.linalg.solve(H + lam * np.diag(np.diag(H)), g)

        return propose

    steps = list(lm_iterations(np.array([1.0, 0.0]), evaluate, linearise, 50, LMSettings(rel_tol=1e-12)))
    assert steps[0].iterations == 0 and steps[0].n_evaluations == 1
    assert [s.iterations for s in steps] == list(range(len(steps))) and len(steps) < 51
    np.testing.assert_allclose(steps[-1].x, [2.0, -1.5], atol=1e-6)
    assert all(b.cost <= a.cost for a, b in itertools.pairwise(steps))
    first = solve(lm_iterations(np.array([1.0, 0.0]), evaluate, linearise, 50), time_budget_s=0.0)
    assert first.iterations == 0 and first.cost == first.initial_cost
