"""The local bundle adjustment's reference twin: scipy's trust-region solver on the same residuals
with a sparse analytic Jacobian (``bundle_adjustment.local_bundle_adjustment`` is the fast path,
a Schur-complement Levenberg-Marquardt). Slow; the tests check the fast solver against it."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from memgs_ros.core.tracking.backend.bundle_adjustment import (
    CHI2_MONO,
    CHI2_STEREO,
    BAProblem,
    BAResult,
    _projection_jacobian,
    _residuals,
    _skew,
    observed_uvr,
    orthonormalized,
    so3_exp,
)

__all__ = ["local_bundle_adjustment_scipy"]


def local_bundle_adjustment_scipy(prob: BAProblem, K: np.ndarray, bf: float, huber_px: float,
                                  max_iterations: int) -> BAResult:
    """Reference twin of ``local_bundle_adjustment``: scipy TRF with a sparse analytic Jacobian.

    Slow (LSMR on the full system: seconds for ~10k observations), kept to check the fast
    Schur-complement solver against. Huber is applied per residual component here.
    """
    C, P = len(prob.T_cw), len(prob.points_w)
    free = np.flatnonzero(~prob.fixed)
    pose_col = np.full(C, -1, dtype=np.int64)
    pose_col[free] = np.arange(len(free)) * 6
    n_pose = 6 * len(free)
    obs, has_depth = observed_uvr(prob.obs_uv, prob.obs_depth, bf)
    s = prob.obs_inv_sigma
    cam, pt = prob.obs_cam, prob.obs_point
    fx, fy = K[0, 0], K[1, 1]
    T0 = prob.T_cw

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        R = T0[:, :3, :3].copy()
        t = T0[:, :3, 3].copy()
        if len(free):
            xi = x[:n_pose].reshape(-1, 6)
            dR = so3_exp(xi[:, :3])
            R[free] = dR @ T0[free, :3, :3]
            t[free] = np.einsum("cij,cj->ci", dR, T0[free, :3, 3]) + xi[:, 3:]
        return R, t, x[n_pose:].reshape(P, 3)

    def camera_points(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, t, pts = unpack(x)
        p_c = np.einsum("oij,oj->oi", R[cam], pts[pt]) + t[cam]
        p_c[:, 2] = np.maximum(p_c[:, 2], 1e-4)
        return p_c, R

    def fun(x: np.ndarray) -> np.ndarray:
        p_c, _ = camera_points(x)
        return (_residuals(p_c, obs, has_depth, K, bf) * s[:, None]).ravel()

    def jac(x: np.ndarray) -> sp.csr_matrix:
        p_c, R = camera_points(x)
        Jp = _projection_jacobian(p_c, fx, fy, bf)
        Jp[~has_depth, 2, :] = 0.0
        Jp *= s[:, None, None]
        J_pose = np.concatenate([-Jp @ _skew(p_c), Jp], axis=2)  # [O, 3, 6]
        return _sparse_jacobian(J_pose, Jp @ R[cam], cam, pt, pose_col, n_pose, P)

    x0 = np.concatenate([np.zeros(n_pose), prob.points_w.ravel()])
    res = least_squares(fun, x0, jac=jac, method="trf", loss="huber", f_scale=huber_px,
                        max_nfev=max_iterations, tr_solver="lsmr")
    R, t, pts = unpack(res.x)
    T = np.tile(np.eye(4), (C, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T = np.stack([orthonormalized(Ti) for Ti in T])
    p_c = np.einsum("oij,oj->oi", R[cam], pts[pt]) + t[cam]
    front = p_c[:, 2] > 1e-4
    p_c[:, 2] = np.where(front, p_c[:, 2], 1.0)
    r = _residuals(p_c, obs, has_depth, K, bf) * s[:, None]
    chi2 = np.einsum("ij,ij->i", r, r)
    inl = front & (chi2 < np.where(has_depth, CHI2_STEREO, CHI2_MONO))
    cost0 = float(_huber_cost(fun(x0), huber_px))
    return BAResult(T, pts, inl, cost0, float(_huber_cost(res.fun, huber_px)), int(res.nfev))


def _sparse_jacobian(J_pose: np.ndarray, J_pt: np.ndarray, cam: np.ndarray, pt: np.ndarray, pose_col: np.ndarray,
                     n_pose: int, n_points: int) -> sp.csr_matrix:
    """The BA Jacobian [3 O, n_pose + 3 P] from each observation's pose block J_pose [O, 3, 6] (its
    camera's 6 columns from ``pose_col``, -1: fixed) and point block J_pt [O, 3, 3]."""
    n_obs = len(cam)
    rows_base = (np.arange(n_obs) * 3)[:, None] + np.arange(3)[None, :]  # [O, 3]
    cam_free = pose_col[cam] >= 0
    r_pt = np.repeat(rows_base[:, :, None], 3, axis=2)
    c_pt = np.broadcast_to(n_pose + (pt * 3)[:, None, None] + np.arange(3)[None, None, :], (n_obs, 3, 3))
    rows, cols, vals = [r_pt.ravel()], [c_pt.ravel()], [J_pt.ravel()]
    if cam_free.any():
        r_po = np.repeat(rows_base[cam_free][:, :, None], 6, axis=2)
        c_po = np.broadcast_to(pose_col[cam[cam_free]][:, None, None] + np.arange(6)[None, None, :], r_po.shape)
        rows.append(r_po.ravel())
        cols.append(c_po.ravel())
        vals.append(J_pose[cam_free].ravel())
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(3 * n_obs, n_pose + 3 * n_points))


def _huber_cost(r: np.ndarray, delta: float) -> float:
    a = np.abs(r)
    return float(np.sum(np.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))))
