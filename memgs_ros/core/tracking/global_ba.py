"""Global bundle adjustment: every keyframe and point, sparse Schur complement.

``local_bundle_adjustment`` forms the camera-point blocks densely per point ([P, 3, 6C]), fine for a
window of ~10 keyframes but quadratic in memory and time for the whole map. Here the reduced camera
system is accumulated only over pairs of observations of the same point (each point is seen by a
handful of keyframes), so one Levenberg-Marquardt step costs O(sum over points of n_obs^2) plus one
dense [6C, 6C] solve: ~0.1 s for 60 keyframes and 20k observations.

Same residuals, Huber IRLS weights and pose parametrisation as ``bundle_adjustment`` (left update
of T_cw); the loop-closing thread runs it after a pose-graph correction (ORB-SLAM's global BA).
"""
from __future__ import annotations

import time

import numpy as np

from memgs_ros.core.tracking.bundle_adjustment import (
    CHI2_MONO,
    CHI2_STEREO,
    BAProblem,
    BAResult,
    _huber_residuals,
    _obs_pairs,
    _projection_jacobian,
    _skew,
    apply_left_update,
    observed_uvr,
    orthonormalized,
)


def global_bundle_adjustment(prob: BAProblem, K: np.ndarray, bf: float, huber_px: float,
                             max_iterations: int, time_budget_s: float | None = None) -> BAResult:
    """Jointly refine the free keyframe poses and all points (see the module docstring).

    prob: BAProblem (T_cw [C, 4, 4], fixed [C], points_w [P, 3], observations [O]); at least one
    camera should be fixed (the gauge). Stops after ``max_iterations`` accepted or rejected
    steps, on convergence, or once ``time_budget_s`` of wall time is spent (the result so far).
    """
    t_start = time.perf_counter()
    C, P = len(prob.T_cw), len(prob.points_w)
    free = np.flatnonzero(~prob.fixed)
    nf = len(free)
    slot = np.full(C, -1, dtype=np.int64)
    slot[free] = np.arange(nf)
    obs, has_depth = observed_uvr(prob.obs_uv, prob.obs_depth, bf)
    s = prob.obs_inv_sigma
    cam, pt = prob.obs_cam, prob.obs_point
    fx, fy = K[0, 0], K[1, 1]
    o_slot = slot[cam]
    of = np.flatnonzero(o_slot >= 0)  # observations by free cameras
    of_slot, of_pt = o_slot[of], pt[of]
    # Observation pairs of one point, both by free cameras: the reduced system's off-diagonal blocks.
    q1, q2 = _obs_pairs(of_pt, P)
    pair_idx = ((of_slot[q1] * 6)[:, None, None] + np.arange(6)[None, :, None]) * (6 * nf) \
        + (of_slot[q2] * 6)[:, None, None] + np.arange(6)[None, None, :]  # [Q, 6, 6] into S.ravel()
    T = prob.T_cw.copy()
    X = prob.points_w.copy()

    def per_point(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
        out = np.zeros((P,) + a.shape[1:])
        np.add.at(out, idx, a)
        return out

    def per_cam(a: np.ndarray) -> np.ndarray:
        out = np.zeros((nf,) + a.shape[1:])
        np.add.at(out, of_slot, a)
        return out

    def evaluate(T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return _huber_residuals(T, X, cam, pt, obs, has_depth, s, K, bf, huber_px)

    p_c, r, cost = evaluate(T, X)
    cost0 = cost
    lam = 1e-3
    n_eval = 1
    for _ in range(max_iterations):
        if time_budget_s is not None and time.perf_counter() - t_start > time_budget_s:
            break
        e = np.sqrt(np.einsum("ij,ij->i", r, r))
        w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-12))  # IRLS Huber weight [O]
        Jp = _projection_jacobian(p_c, fx, fy, bf)
        Jp[~has_depth, 2, :] = 0.0
        Jp *= s[:, None, None]
        Jx = np.matmul(Jp, T[cam, :3, :3])  # d r / d X [O, 3, 3]
        wJxT = (Jx * w[:, None, None]).transpose(0, 2, 1)
        Hpp = per_point(np.matmul(wJxT, Jx), pt)  # [P, 3, 3]
        gp = per_point(np.matmul(wJxT, r[:, :, None])[:, :, 0], pt)  # [P, 3]
        Jc = np.concatenate([-np.matmul(Jp[of], _skew(p_c[of])), Jp[of]], axis=2)  # [F, 3, 6]
        wJcT = (Jc * w[of, None, None]).transpose(0, 2, 1)  # [F, 6, 3]
        Hcp = np.matmul(wJcT, Jx[of])  # [F, 6, 3]
        Hcc = per_cam(np.matmul(wJcT, Jc))  # [nf, 6, 6]
        gc = per_cam(np.matmul(wJcT, r[of, :, None])[:, :, 0])  # [nf, 6]
        improved = converged = False
        for _attempt in range(6):
            Hpp_inv = np.linalg.inv(Hpp + lam * Hpp * np.eye(3) + 1e-9 * np.eye(3))  # [P, 3, 3]
            W = np.matmul(Hcp, Hpp_inv[of_pt])  # [F, 6, 3]
            S = np.zeros((6 * nf, 6 * nf))
            for i in range(nf):
                S[6 * i:6 * i + 6, 6 * i:6 * i + 6] = Hcc[i] + lam * Hcc[i] * np.eye(6) + 1e-9 * np.eye(6)
            blocks = np.matmul(W[q1], Hcp[q2].transpose(0, 2, 1))  # [Q, 6, 6]
            S -= np.bincount(pair_idx.ravel(), blocks.ravel(), minlength=S.size).reshape(S.shape)
            b = gc - per_cam(np.einsum("fij,fj->fi", W, gp[of_pt]))
            try:
                dc = -np.linalg.solve(S, b.ravel()).reshape(nf, 6)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            # dX = Hpp^-1 (-gp - Hpc dc)
            corr = per_point(np.einsum("fij,fi->fj", Hcp, dc[of_slot]), of_pt)
            dX = -np.einsum("pij,pj->pi", Hpp_inv, gp + corr)
            T_new = T.copy()
            for i, c in enumerate(free.tolist()):
                T_new[c] = apply_left_update(T[c], dc[i])
            X_new = X + dX
            p_c_new, r_new, cost_new = evaluate(T_new, X_new)
            n_eval += 1
            if np.isfinite(cost_new) and cost_new < cost:
                converged = (cost - cost_new) < 1e-6 * cost
                T, X, p_c, r, cost = T_new, X_new, p_c_new, r_new, cost_new
                lam = max(lam / 3.0, 1e-7)
                improved = True
                break
            lam *= 10.0
        if not improved or converged:
            break
    chi2 = np.einsum("ij,ij->i", r, r)
    p_cz = np.einsum("oij,oj->oi", T[cam, :3, :3], X[pt])[:, 2] + T[cam, 2, 3]
    inl = (p_cz > 1e-4) & (chi2 < np.where(has_depth, CHI2_STEREO, CHI2_MONO))
    T = np.stack([orthonormalized(Ti) for Ti in T])
    return BAResult(T, X, inl, cost0, cost, n_eval)


__all__ = ["global_bundle_adjustment"]
