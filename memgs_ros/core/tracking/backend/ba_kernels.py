"""numba kernels of the bundle adjustments' linear algebra (local and global BA share them).

``BAGeometry`` (``bundle_adjustment``) evaluates the residuals and forms the normal equations with
numpy: arrays of [O, 3, 3] and [O, 3, 6] Jacobians, einsums and reductions, each a pass over
memory and most of them holding the GIL. ``local_bundle_adjustment`` then reduced the camera
system densely per point ([P, 3, 6C] blocks, an einsum over all of them); on the fr1/rpy head a
local BA took ~50 ms, as much CPU as the frame path at 60 Hz, on the tracker's back-end thread
beside it. The kernels do the same arithmetic observation by observation:

- ``evaluate``: camera-frame points, whitened residuals and the Huber cost (twin:
  ``bundle_adjustment._huber_residuals``);
- ``blocks``: the Huber-weighted normal-equation blocks (twin: ``BAGeometry._blocks_reference``);
- ``reduce_cameras``: the points eliminated (Schur complement) over the pairs of observations of
  each point, as the global BA does, into the [6 nf, 6 nf] camera system, undamped, and its
  right-hand side (twin: the reduction in ``global_ba``'s ``propose``);
- ``back_substitute``: the points' steps once the cameras' are solved.

Each solver damps the reduced system its own way and solves it with numpy (a failed solve stays
a ``LinAlgError``). The kernels release the GIL, so the tracker's frame path runs beside a BA.
Sums run in another order than numpy's: results agree to rounding (the parity tests bound
them), not bit for bit. Where numba is missing, ``BAGeometry`` keeps its numpy path.
"""
from __future__ import annotations

import numpy as np

from memgs_ros.core.runtime.cpu import numba_available

__all__ = ["back_substitute", "blocks", "evaluate", "reduce_cameras", "warm_up"]


def _evaluate(T, X, cam, pt, obs, has_depth, s, fx, fy, cx, cy, bf, huber):
    """(p_c [O, 3], r [O, 3], cost) of poses T [C, 4, 4] (T_cw) and points X [P, 3]: observation o
    of point pt[o] by camera cam[o] at obs[o] (u, v, u_right), its residual scaled by s[o], the
    third zero without depth; the Huber cost (threshold ``huber``) of each residual's norm."""
    n = cam.shape[0]
    p_c = np.empty((n, 3))
    r = np.empty((n, 3))
    cost = 0.0
    for o in range(n):
        c = cam[o]
        p = pt[o]
        x0, x1, x2 = X[p, 0], X[p, 1], X[p, 2]
        px = T[c, 0, 0] * x0 + T[c, 0, 1] * x1 + T[c, 0, 2] * x2 + T[c, 0, 3]
        py = T[c, 1, 0] * x0 + T[c, 1, 1] * x1 + T[c, 1, 2] * x2 + T[c, 1, 3]
        pz = max(T[c, 2, 0] * x0 + T[c, 2, 1] * x1 + T[c, 2, 2] * x2 + T[c, 2, 3], 1e-4)
        p_c[o, 0], p_c[o, 1], p_c[o, 2] = px, py, pz
        u = fx * px / pz + cx
        v = fy * py / pz + cy
        r0 = (u - obs[o, 0]) * s[o]
        r1 = (v - obs[o, 1]) * s[o]
        r2 = ((u - bf / pz) - obs[o, 2]) * s[o] if has_depth[o] else 0.0
        r[o, 0], r[o, 1], r[o, 2] = r0, r1, r2
        e = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        cost += 0.5 * e * e if e <= huber else huber * (e - 0.5 * huber)
    return p_c, r, cost


def _blocks(T, p_c, r, cam, pt, has_depth, s, fx, fy, bf, huber, cam_slot, f_of_o, n_points, nf, n_free_obs):
    """Normal-equation blocks at camera points p_c [O, 3] and whitened residuals r [O, 3] with Huber
    IRLS weights: Hpp [P, 3, 3], gp [P, 3] per point; Hcp [F, 6, 3] per observation by a free
    camera (observation o is f_of_o[o], -1 for a fixed camera, whose slot cam_slot[c] is -1);
    Hcc [nf, 6, 6], gc [nf, 6] per free camera. Poses are perturbed on the left (rotation first)."""
    Hpp = np.zeros((n_points, 3, 3))
    gp = np.zeros((n_points, 3))
    Hcp = np.empty((n_free_obs, 6, 3))
    Hcc = np.zeros((nf, 6, 6))
    gc = np.zeros((nf, 6))
    Jp = np.empty((3, 3))
    Jx = np.empty((3, 3))
    Jc = np.empty((3, 6))
    for o in range(cam.shape[0]):
        c = cam[o]
        p = pt[o]
        r0, r1, r2 = r[o, 0], r[o, 1], r[o, 2]
        e = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        w = 1.0 if e <= huber else huber / max(e, 1e-12)
        x, y, z = p_c[o, 0], p_c[o, 1], p_c[o, 2]
        iz = 1.0 / z
        iz2 = iz * iz
        so = s[o]
        Jp[0, 0], Jp[0, 1], Jp[0, 2] = fx * iz * so, 0.0, -fx * x * iz2 * so
        Jp[1, 0], Jp[1, 1], Jp[1, 2] = 0.0, fy * iz * so, -fy * y * iz2 * so
        if has_depth[o]:
            Jp[2, 0], Jp[2, 1], Jp[2, 2] = fx * iz * so, 0.0, (-fx * x * iz2 + bf * iz2) * so
        else:
            Jp[2, 0], Jp[2, 1], Jp[2, 2] = 0.0, 0.0, 0.0
        for i in range(3):  # d r / d X = Jp R
            for j in range(3):
                Jx[i, j] = Jp[i, 0] * T[c, 0, j] + Jp[i, 1] * T[c, 1, j] + Jp[i, 2] * T[c, 2, j]
        for i in range(3):
            gp[p, i] += w * (Jx[0, i] * r0 + Jx[1, i] * r1 + Jx[2, i] * r2)
            for j in range(3):
                Hpp[p, i, j] += w * (Jx[0, i] * Jx[0, j] + Jx[1, i] * Jx[1, j] + Jx[2, i] * Jx[2, j])
        slot = cam_slot[c]
        if slot < 0:
            continue
        for i in range(3):  # d r / d (w, v) = [-Jp [p_c]x, Jp]
            Jc[i, 0] = -(Jp[i, 1] * z - Jp[i, 2] * y)
            Jc[i, 1] = -(Jp[i, 2] * x - Jp[i, 0] * z)
            Jc[i, 2] = -(Jp[i, 0] * y - Jp[i, 1] * x)
            Jc[i, 3], Jc[i, 4], Jc[i, 5] = Jp[i, 0], Jp[i, 1], Jp[i, 2]
        f = f_of_o[o]
        for i in range(6):
            gc[slot, i] += w * (Jc[0, i] * r0 + Jc[1, i] * r1 + Jc[2, i] * r2)
            for j in range(3):
                Hcp[f, i, j] = w * (Jc[0, i] * Jx[0, j] + Jc[1, i] * Jx[1, j] + Jc[2, i] * Jx[2, j])
            for j in range(6):
                Hcc[slot, i, j] += w * (Jc[0, i] * Jc[0, j] + Jc[1, i] * Jc[1, j] + Jc[2, i] * Jc[2, j])
    return Hpp, gp, Hcp, Hcc, gc


def _inverse3(A, lam, out):
    """out [3, 3] = (A + lam diag(A) + 1e-9 I)^-1 by cofactors (A [3, 3] symmetric positive)."""
    a, b, c = A[0, 0] + lam * A[0, 0] + 1e-9, A[0, 1], A[0, 2]
    d, e, f = A[1, 0], A[1, 1] + lam * A[1, 1] + 1e-9, A[1, 2]
    g, h, i = A[2, 0], A[2, 1], A[2, 2] + lam * A[2, 2] + 1e-9
    ca, cb, cc = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * ca + b * cb + c * cc
    k = 1.0 / det
    out[0, 0], out[0, 1], out[0, 2] = ca * k, (c * h - b * i) * k, (b * f - c * e) * k
    out[1, 0], out[1, 1], out[1, 2] = cb * k, (a * i - c * g) * k, (c * d - a * f) * k
    out[2, 0], out[2, 1], out[2, 2] = cc * k, (b * g - a * h) * k, (a * e - b * d) * k


def _reduce_cameras(Hpp, gp, Hcp, Hcc, gc, fp_start, fp_obs, of_slot, lam):
    """The points eliminated: (Hpp_inv [P, 3, 3] of the damped point blocks, S [6 nf, 6 nf] =
    blockdiag(Hcc) - sum over points of Hcp_a Hpp_inv Hcp_b^T over pairs (a, b) of its observations
    by free cameras, rhs [6 nf] = gc - sum of Hcp_a Hpp_inv gp). Point p's free observations are
    fp_obs[fp_start[p]:fp_start[p + 1]] (indices into Hcp, their camera slots of_slot)."""
    n_points = Hpp.shape[0]
    nf = Hcc.shape[0]
    Hpp_inv = np.empty((n_points, 3, 3))
    S = np.zeros((6 * nf, 6 * nf))
    rhs = np.empty(6 * nf)
    for k in range(nf):
        for i in range(6):
            rhs[6 * k + i] = gc[k, i]
            for j in range(6):
                S[6 * k + i, 6 * k + j] = Hcc[k, i, j]
    W = np.empty((6, 3))
    for p in range(n_points):
        A = Hpp_inv[p]
        _inverse3(Hpp[p], lam, A)
        g0, g1, g2 = gp[p, 0], gp[p, 1], gp[p, 2]
        for qa in range(fp_start[p], fp_start[p + 1]):
            a = fp_obs[qa]
            ra = 6 * of_slot[a]
            for i in range(6):  # W = Hcp_a Hpp_inv
                for j in range(3):
                    W[i, j] = Hcp[a, i, 0] * A[0, j] + Hcp[a, i, 1] * A[1, j] + Hcp[a, i, 2] * A[2, j]
                rhs[ra + i] -= W[i, 0] * g0 + W[i, 1] * g1 + W[i, 2] * g2
            for qb in range(fp_start[p], fp_start[p + 1]):
                b = fp_obs[qb]
                rb = 6 * of_slot[b]
                for i in range(6):
                    for j in range(6):
                        S[ra + i, rb + j] -= W[i, 0] * Hcp[b, j, 0] + W[i, 1] * Hcp[b, j, 1] + W[i, 2] * Hcp[b, j, 2]
    return Hpp_inv, S, rhs


def _back_substitute(Hpp_inv, gp, Hcp, fp_start, fp_obs, of_slot, dc):
    """Points' steps dX [P, 3] = -Hpp_inv (gp + sum over free observations of Hcp_a^T dc[slot_a])
    for the cameras' steps dc [nf, 6]."""
    n_points = Hpp_inv.shape[0]
    dX = np.empty((n_points, 3))
    for p in range(n_points):
        v0, v1, v2 = gp[p, 0], gp[p, 1], gp[p, 2]
        for q in range(fp_start[p], fp_start[p + 1]):
            a = fp_obs[q]
            k = of_slot[a]
            for i in range(6):
                d = dc[k, i]
                v0 += Hcp[a, i, 0] * d
                v1 += Hcp[a, i, 1] * d
                v2 += Hcp[a, i, 2] * d
        for i in range(3):
            dX[p, i] = -(Hpp_inv[p, i, 0] * v0 + Hpp_inv[p, i, 1] * v1 + Hpp_inv[p, i, 2] * v2)
    return dX


if numba_available():
    import numba

    _jit = numba.njit(cache=True, nogil=True)
    _evaluate = _jit(_evaluate)
    _blocks = _jit(_blocks)
    _inverse3 = numba.njit(cache=True, nogil=True, inline="always")(_inverse3)
    _reduce_cameras = _jit(_reduce_cameras)
    _back_substitute = _jit(_back_substitute)


def evaluate(T: np.ndarray, X: np.ndarray, cam: np.ndarray, pt: np.ndarray, obs: np.ndarray, has_depth: np.ndarray,
             s: np.ndarray, K: np.ndarray, bf: float, huber: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Camera points p_c [O, 3], whitened residuals r [O, 3] and the Huber cost of poses T [C, 4, 4]
    and points X [P, 3] (observations: cameras cam [O], points pt [O], obs [O, 3] (u, v, u_right),
    has_depth [O], scales s [O]); the depth clamped at 0.1 mm as the reference does."""
    return _evaluate(T, X, cam, pt, obs, has_depth, s, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                     float(K[1, 2]), float(bf), float(huber))


def blocks(T: np.ndarray, p_c: np.ndarray, r: np.ndarray, cam: np.ndarray, pt: np.ndarray, has_depth: np.ndarray,
           s: np.ndarray, K: np.ndarray, bf: float, huber: float, cam_slot: np.ndarray, f_of_o: np.ndarray,
           n_points: int, nf: int, n_free_obs: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(Hpp [P, 3, 3], gp [P, 3], Hcp [F, 6, 3], Hcc [nf, 6, 6], gc [nf, 6]); see ``_blocks``."""
    return _blocks(T, p_c, r, cam, pt, has_depth, s, float(K[0, 0]), float(K[1, 1]), float(bf), float(huber),
                   cam_slot, f_of_o, int(n_points), int(nf), int(n_free_obs))


def reduce_cameras(Hpp: np.ndarray, gp: np.ndarray, Hcp: np.ndarray, Hcc: np.ndarray, gc: np.ndarray,
                   fp_start: np.ndarray, fp_obs: np.ndarray, of_slot: np.ndarray, lam: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Hpp_inv [P, 3, 3], S [6 nf, 6 nf], rhs [6 nf]); see ``_reduce_cameras``."""
    return _reduce_cameras(Hpp, gp, Hcp, Hcc, gc, fp_start, fp_obs, of_slot, float(lam))


def back_substitute(Hpp_inv: np.ndarray, gp: np.ndarray, Hcp: np.ndarray, fp_start: np.ndarray, fp_obs: np.ndarray,
                    of_slot: np.ndarray, dc: np.ndarray) -> np.ndarray:
    """The points' steps dX [P, 3]; see ``_back_substitute``."""
    return _back_substitute(Hpp_inv, gp, Hcp, fp_start, fp_obs, of_slot, np.ascontiguousarray(dc, np.float64))


def warm_up() -> None:
    """Compile (or load from the disk cache) the kernels on a two-camera problem, so that the first
    local BA of a live run does not."""
    if not numba_available():
        return
    T = np.stack([np.eye(4), np.eye(4)])
    X = np.array([[0.0, 0.0, 2.0], [0.5, 0.1, 3.0]])
    cam, pt = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
    obs = np.full((4, 3), 300.0)
    has_depth, s, K = np.array([True, False, True, True]), np.ones(4), np.array([[500.0, 0, 320], [0, 500, 240],
                                                                                  [0, 0, 1]])
    p_c, r, _ = evaluate(T, X, cam, pt, obs, has_depth, s, K, 40.0, 2.45)
    slot, f_of_o = np.array([-1, 0]), np.array([-1, 0, -1, 1])
    Hpp, gp, Hcp, Hcc, gc = blocks(T, p_c, r, cam, pt, has_depth, s, K, 40.0, 2.45, slot, f_of_o, 2, 1, 2)
    start, order, of_slot = np.array([0, 1, 2]), np.array([0, 1]), np.array([0, 0])
    Hpp_inv, _, _ = reduce_cameras(Hpp, gp, Hcp, Hcc, gc, start, order, of_slot, 1e-3)
    back_substitute(Hpp_inv, gp, Hcp, start, order, of_slot, np.zeros((1, 6)))
