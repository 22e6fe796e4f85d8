"""Motion-only pose optimisation and local bundle adjustment.

Residuals are ORB-SLAM's: reprojection (u, v) in pixels and, where depth was measured,
a virtual-stereo disparity residual ``u - bf / z`` (``bf`` = fx * virtual baseline), so
depth errors are pixels too and one robust scale serves both. Each residual is divided
by ``scale_factor ** octave`` (coarser levels are less precise).

Poses are ``T_cw`` perturbed on the left: ``R <- exp(w) R``, ``t <- exp(w) t + v``; then
``d p_c / d w = -[p_c]_x`` and ``d p_c / d v = I``.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from memgs_ros.core.tracking.backend import ba_kernels
from memgs_ros.core.tracking.backend.lm import LMProgress, lm_iterations, solve
from memgs_ros.core.tracking.kernel_calls import numba_available, optimize_pose_kernel

CHI2_MONO = 5.991  # chi-square 95 %, 2 dof
CHI2_STEREO = 7.815  # chi-square 95 %, 3 dof


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Axis-angle [..., 3] to rotation matrices [..., 3, 3]."""
    w = np.asarray(w, dtype=np.float64)
    return Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(w.shape[:-1] + (3, 3))


# Newton steps of the polar decomposition, and the largest last step that counts as converged.
_POLAR_STEPS = 3
_POLAR_LAST_STEP = 1e-7


def orthonormalized(T: np.ndarray) -> np.ndarray:
    """The pose [4, 4] with its rotation projected back onto SO(3), the nearest rotation.

    Products of rotations drift off SO(3); ``invert_pose`` transposes, so the drift would
    compound through the velocity model every frame. Several calls a frame: a rotation a
    rounding error off SO(3) takes Newton's polar iteration R <- (R + R^-T) / 2 on Python
    floats (~7 us against ~25 us for the SVD); anything else, or a step that does not
    converge, takes ``_orthonormalized_svd``, the reference.
    """
    (a, b, c), (d, e, f), (g, h, i) = T[:3, :3].tolist()
    step = np.inf
    for _ in range(_POLAR_STEPS):
        # R^-T = cofactor(R) / det(R), the cofactors written out.
        ca, cb, cc = e * i - f * h, f * g - d * i, d * h - e * g
        cd, ce, cf = c * h - b * i, a * i - c * g, b * g - a * h
        cg, ch, ci = b * f - c * e, c * d - a * f, a * e - b * d
        det = a * ca + b * cb + c * cc
        if not det > 0.0:  # a reflection, singular or NaN: the SVD decides
            return _orthonormalized_svd(T)
        k = 0.5 / det
        da, db, dc = k * ca - 0.5 * a, k * cb - 0.5 * b, k * cc - 0.5 * c
        dd, de, df = k * cd - 0.5 * d, k * ce - 0.5 * e, k * cf - 0.5 * f
        dg, dh, di = k * cg - 0.5 * g, k * ch - 0.5 * h, k * ci - 0.5 * i
        a, b, c, d, e, f, g, h, i = a + da, b + db, c + dc, d + dd, e + de, f + df, g + dg, h + dh, i + di
        step = max(abs(da), abs(db), abs(dc), abs(dd), abs(de), abs(df), abs(dg), abs(dh), abs(di))
    # Quadratic convergence: the error left is about the last step squared.
    if not step <= _POLAR_LAST_STEP:
        return _orthonormalized_svd(T)
    R = ((a, b, c), (d, e, f), (g, h, i))
    out = T.astype(np.float64, copy=True)
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _orthonormalized_svd(T: np.ndarray) -> np.ndarray:
    """Reference twin of ``orthonormalized`` (SVD): the pose [4, 4] with its rotation replaced by
    the nearest rotation, det +1 even for a reflection."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.astype(np.float64, copy=True)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def apply_left_update(T_cw: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """T_cw [4, 4] updated by xi = (w, v) [6] on the left; returns a new [4, 4]."""
    R = cv2.Rodrigues(np.asarray(xi[:3], dtype=np.float64))[0]
    out = np.eye(4)
    out[:3, :3] = R @ T_cw[:3, :3]
    out[:3, 3] = R @ T_cw[:3, 3] + xi[3:]
    return out


def _projection_jacobian(p_c: np.ndarray, fx: float, fy: float, bf: float) -> np.ndarray:
    """d (u, v, u_right) / d p_c for camera points [N, 3] -> [N, 3, 3]."""
    x, y, z = p_c[:, 0], p_c[:, 1], p_c[:, 2]
    iz = 1.0 / z
    iz2 = iz * iz
    J = np.zeros((len(p_c), 3, 3))
    J[:, 0, 0] = fx * iz
    J[:, 0, 2] = -fx * x * iz2
    J[:, 1, 1] = fy * iz
    J[:, 1, 2] = -fy * y * iz2
    J[:, 2, 0] = J[:, 0, 0]
    J[:, 2, 2] = J[:, 0, 2] + bf * iz2
    return J


def _skew(p: np.ndarray) -> np.ndarray:
    """[N, 3] -> [N, 3, 3] cross-product matrices."""
    S = np.zeros((len(p), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -p[:, 2], p[:, 1]
    S[:, 1, 0], S[:, 1, 2] = p[:, 2], -p[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -p[:, 1], p[:, 0]
    return S


def _residuals(p_c: np.ndarray, obs_uvr: np.ndarray, has_depth: np.ndarray, K: np.ndarray,
               bf: float) -> np.ndarray:
    """Residuals [N, 3] (predicted minus observed); third is 0 where there is no depth."""
    z = p_c[:, 2]
    u = K[0, 0] * p_c[:, 0] / z + K[0, 2]
    v = K[1, 1] * p_c[:, 1] / z + K[1, 2]
    r = np.stack([u - obs_uvr[:, 0], v - obs_uvr[:, 1], (u - bf / z) - obs_uvr[:, 2]], axis=1)
    r[~has_depth, 2] = 0.0
    return r


def observed_uvr(uv: np.ndarray, depth_m: np.ndarray, bf: float) -> tuple[np.ndarray, np.ndarray]:
    """Observations [N, 3] (u, v, u - bf/depth) and has_depth [N] bool from uv [N, 2], depth [N]."""
    has_depth = np.isfinite(depth_m) & (depth_m > 0)
    ur = np.where(has_depth, uv[:, 0] - bf / np.where(has_depth, depth_m, 1.0), 0.0)
    return np.column_stack([uv, ur]), has_depth


def optimize_pose(T_cw: np.ndarray, p_w: np.ndarray, uv: np.ndarray, depth_m: np.ndarray,
                  inv_sigma: np.ndarray, K: np.ndarray, bf: float, chi2_scale: float = 1.0,
                  rounds: int = 4, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Motion-only robust pose refinement (Gauss-Newton, Huber, outlier rounds as in ORB-SLAM).

    T_cw: [4, 4] initial pose; p_w: [N, 3] map points; uv: [N, 2] undistorted observations;
    depth_m: [N] (NaN where none); inv_sigma: [N] 1 / scale^octave.
    ``chi2_scale`` multiplies the chi-square inlier bounds (1.0 = 95 %).
    Returns (T_cw [4, 4], inlier [N] bool). Runs the numba kernel
    (``kernel_calls.optimize_pose_kernel``, ~10x faster) when numba is available, else its plain
    twin ``_optimize_pose``.
    """
    n = len(p_w)
    if n < 4 or not numba_available():
        return _optimize_pose(T_cw, p_w, uv, depth_m, inv_sigma, K, bf, chi2_scale, rounds, iterations)
    obs, has_depth = observed_uvr(uv, depth_m, bf)
    T, inlier = optimize_pose_kernel(T_cw, p_w, obs, has_depth, inv_sigma ** 2, K, bf,
                                     CHI2_MONO * chi2_scale, CHI2_STEREO * chi2_scale, rounds, iterations)
    return orthonormalized(T), inlier


def _optimize_pose(T_cw: np.ndarray, p_w: np.ndarray, uv: np.ndarray, depth_m: np.ndarray,
                   inv_sigma: np.ndarray, K: np.ndarray, bf: float, chi2_scale: float = 1.0,
                   rounds: int = 4, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Plain twin of ``optimize_pose`` (numpy), with the same arguments and result; the reference
    the kernel is checked against."""
    n = len(p_w)
    inlier = np.ones(n, dtype=bool)
    if n < 4:
        return T_cw.copy(), np.zeros(n, dtype=bool)
    obs, has_depth = observed_uvr(uv, depth_m, bf)
    th_mono, th_stereo = CHI2_MONO * chi2_scale, CHI2_STEREO * chi2_scale
    w2 = inv_sigma ** 2
    T = T_cw.copy()
    fx, fy = K[0, 0], K[1, 1]
    for rnd in range(rounds):
        use = inlier.copy()
        if use.sum() < 4:
            break
        robust = rounds == 1 or rnd < rounds - 1
        for _ in range(iterations):
            p_c = p_w[use] @ T[:3, :3].T + T[:3, 3]
            if np.any(p_c[:, 2] <= 1e-6):
                p_c[:, 2] = np.maximum(p_c[:, 2], 1e-6)
            r = _residuals(p_c, obs[use], has_depth[use], K, bf)  # [n, 3]
            Jp = _projection_jacobian(p_c, fx, fy, bf)  # [n, 3, 3]
            Jp[~has_depth[use], 2, :] = 0.0
            J = np.concatenate([-Jp @ _skew(p_c), Jp], axis=2)  # [n, 3, 6]
            chi2 = w2[use] * np.einsum("ij,ij->i", r, r)
            wt = w2[use].copy()
            if robust:
                delta = np.where(has_depth[use], np.sqrt(th_stereo), np.sqrt(th_mono))
                e = np.sqrt(chi2)
                wt = wt * np.where(e <= delta, 1.0, delta / np.maximum(e, 1e-12))
            sw = np.sqrt(wt)[:, None, None]
            Jw = (J * sw).reshape(-1, 6)
            H = np.einsum("ni,nj->ij", Jw, Jw)
            g = np.einsum("ni,n->i", Jw, (r[:, :, None] * sw).ravel())
            try:
                dx = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
            except np.linalg.LinAlgError:
                break
            T = apply_left_update(T, dx)
            if np.linalg.norm(dx) < 1e-5:  # 10 um / 10 urad: far below pixel noise
                break
        p_c = p_w @ T[:3, :3].T + T[:3, 3]
        front = p_c[:, 2] > 1e-6
        p_c[:, 2] = np.where(front, p_c[:, 2], 1.0)
        r = _residuals(p_c, obs, has_depth, K, bf)
        chi2 = w2 * np.einsum("ij,ij->i", r, r)
        new_inlier = front & (chi2 < np.where(has_depth, th_stereo, th_mono))
        settled = np.array_equal(new_inlier, inlier) and rnd < rounds - 1
        inlier = new_inlier
        if settled:
            break  # the same set again: more rounds would repeat this one
    return orthonormalized(T), inlier


def pose_covariance(T_cw: np.ndarray, p_w: np.ndarray, depth_m: np.ndarray, inv_sigma: np.ndarray,
                    K: np.ndarray, bf: float, pixel_sigma: float = 1.0) -> np.ndarray | None:
    """The covariance [6, 6] of a pose optimised on K inlier matches (points p_w [K, 3], their
    observations' depth_m [K] (NaN where none) and inv_sigma [K]), from the motion-only problem's
    information matrix H = J^T W J at the pose (``optimize_pose``'s residuals and weights, no robust
    kernel): Sigma = pixel_sigma^2 H^-1. Returned for the camera's pose in the world (T_wc), in ROS
    order (x, y, z, then rotations about the world's x, y, z); None when H is singular (fewer than
    3 points). Fewer or worse-spread inliers give a larger covariance."""
    if len(p_w) < 3:
        return None
    p_c = p_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    x, y, z = p_c[:, 0], p_c[:, 1], np.maximum(p_c[:, 2], 1e-6)
    has_depth = np.isfinite(depth_m) & (depth_m > 0)
    fx, fy = K[0, 0], K[1, 1]
    iz, zero = 1.0 / z, np.zeros(len(z))
    # The rows a = d(u, v, u_right) / d p_c of the observations (u_right only with depth), then
    # a @ [-[p_c]x, I]: the left update (rotation, translation) of T_cw, as optimize_pose's J.
    d = has_depth
    a0 = np.concatenate([fx * iz, zero, fx * iz[d]])
    a1 = np.concatenate([zero, fy * iz, zero[d]])
    a2 = np.concatenate([-fx * x * iz * iz, -fy * y * iz * iz, (bf - fx * x[d]) * iz[d] * iz[d]])
    px, py, pz = (np.concatenate([c, c, c[d]]) for c in (x, y, z))
    w = np.concatenate([inv_sigma, inv_sigma, inv_sigma[d]])
    J = np.column_stack([a2 * py - a1 * pz, a0 * pz - a2 * px, a1 * px - a0 * py, a0, a1, a2]) * w[:, None]
    H = J.T @ J
    try:
        cov_cw = pixel_sigma ** 2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov_cw)):
        return None
    # T_cw <- Exp(d) T_cw is T_wc <- T_wc Exp(-d): a perturbation in the camera frame; in the world
    # frame (ROS: position, then rotation about fixed axes) both blocks turn by R_wc.
    R_wc = T_cw[:3, :3].T
    A = np.zeros((6, 6))
    A[:3, 3:] = R_wc  # position <- the translation part
    A[3:, :3] = R_wc  # rotation <- the rotation part
    cov = A @ cov_cw @ A.T
    return 0.5 * (cov + cov.T)


@dataclass(frozen=True, eq=False)
class BAProblem:
    """A local bundle adjustment snapshot.

    T_cw: [C, 4, 4] keyframe poses; fixed: [C] bool (held constant).
    points_w: [P, 3]; obs_cam: [O] camera index; obs_point: [O] point index;
    obs_uv: [O, 2] undistorted pixels; obs_depth: [O] metres (NaN where none);
    obs_inv_sigma: [O] 1 / scale^octave.
    """

    T_cw: np.ndarray
    fixed: np.ndarray
    points_w: np.ndarray
    obs_cam: np.ndarray
    obs_point: np.ndarray
    obs_uv: np.ndarray
    obs_depth: np.ndarray
    obs_inv_sigma: np.ndarray


@dataclass(frozen=True, eq=False)
class BAResult:
    """T_cw: [C, 4, 4]; points_w: [P, 3]; obs_inlier: [O] bool; cost before/after (robust, 0.5 sum)."""

    T_cw: np.ndarray
    points_w: np.ndarray
    obs_inlier: np.ndarray
    initial_cost: float
    final_cost: float
    n_evaluations: int


def _huber_residuals(T: np.ndarray, X: np.ndarray, cam: np.ndarray, pt: np.ndarray, obs: np.ndarray,
                     has_depth: np.ndarray, inv_sigma: np.ndarray, K: np.ndarray, bf: float,
                     huber_px: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Camera-frame points, whitened residuals and Huber cost of a BA state (local and global BA).

    T: [C, 4, 4] T_cw; X: [P, 3]; cam, pt: [O] observation camera / point; obs: [O, 3] (u, v,
    u_right); has_depth: [O]; inv_sigma: [O]. Returns (p_c [O, 3], r [O, 3], cost).
    """
    p_c = np.einsum("oij,oj->oi", T[cam, :3, :3], X[pt]) + T[cam, :3, 3]
    p_c[:, 2] = np.maximum(p_c[:, 2], 1e-4)
    r = _residuals(p_c, obs, has_depth, K, bf) * inv_sigma[:, None]
    e = np.sqrt(np.einsum("ij,ij->i", r, r))
    cost = float(np.sum(np.where(e <= huber_px, 0.5 * e * e, huber_px * (e - 0.5 * huber_px))))
    return p_c, r, cost


def _obs_pairs(obs_point: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """All ordered pairs (o1, o2) of observations of the same point, [Q] each (o1 == o2 included)."""
    order = np.argsort(obs_point, kind="stable")
    counts = np.bincount(obs_point, minlength=n_points)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    k = counts[obs_point[order]]  # group size of each sorted observation
    o1 = np.repeat(order, k)
    first_of_rep = np.repeat(np.cumsum(k) - k, k)
    within = np.arange(len(o1)) - first_of_rep
    o2 = order[start[obs_point[o1]] + within]
    return o1, o2


class _Segments:
    """Sums of per-observation values grouped by an integer key in [0, n) (sort once, reduceat)."""

    def __init__(self, keys: np.ndarray, n: int) -> None:
        self.order = np.argsort(keys, kind="stable")
        k = keys[self.order]
        self.start = np.flatnonzero(np.r_[True, k[1:] != k[:-1]]) if len(k) else np.zeros(0, np.int64)
        self.keys = k[self.start]
        self.n = n

    def sum(self, a: np.ndarray) -> np.ndarray:
        """a: [len(keys), ...] -> [n, ...] (zeros for keys never seen)."""
        out = np.zeros((self.n,) + a.shape[1:])
        if len(self.start):
            out[self.keys] = np.add.reduceat(a[self.order], self.start, axis=0)
        return out


@dataclass(frozen=True, eq=False)
class BABlocks:
    """Normal-equation blocks of a BA state (Huber IRLS weights applied).

    Hpp: [P, 3, 3], gp: [P, 3] per point; Hcp: [F, 6, 3] per observation by a free camera;
    Hcc: [nf, 6, 6], gc: [nf, 6] per free camera.
    """

    Hpp: np.ndarray
    gp: np.ndarray
    Hcp: np.ndarray
    Hcc: np.ndarray
    gc: np.ndarray


BAState = tuple[np.ndarray, np.ndarray]  # (T_cw [C, 4, 4], points_w [P, 3])
BAAux = tuple[np.ndarray, np.ndarray]  # (p_c [O, 3], whitened residuals r [O, 3])


class BAGeometry:
    """What stays fixed while one BA problem is solved: observations, free cameras, groupings.

    Shared by the local and global solvers; both run the one Levenberg-Marquardt loop of ``lm``
    and eliminate the points the same way (``reduce``, ``back_substitute``), each damping the
    reduced camera system its own way. ``free``: [nf] free camera indices; ``of``: [F]
    observations by free cameras, with their slot ``of_slot`` [F] and point ``of_pt`` [F];
    ``per_point``, ``per_cam`` and ``per_free_point`` sum per-observation values over those
    groupings. ``compiled`` (default: where numba is at hand) runs ``ba_kernels``; the numpy
    methods named ``_reference`` are their twins.
    """

    def __init__(self, prob: BAProblem, K: np.ndarray, bf: float, huber_px: float,
                 compiled: bool | None = None) -> None:
        self.prob, self.K, self.bf, self.huber_px = prob, K, bf, huber_px
        self.compiled = numba_available() if compiled is None else compiled
        self.n_points = len(prob.points_w)
        self.free = np.flatnonzero(~prob.fixed)
        self.nf = len(self.free)
        self.cam_slot = np.full(len(prob.T_cw), -1, dtype=np.int64)
        self.cam_slot[self.free] = np.arange(self.nf)
        self.obs, self.has_depth = observed_uvr(prob.obs_uv, prob.obs_depth, bf)
        self.cam, self.pt = np.asarray(prob.obs_cam, np.int64), np.asarray(prob.obs_point, np.int64)
        self.s = np.asarray(prob.obs_inv_sigma, np.float64)
        o_slot = self.cam_slot[self.cam]
        self.of = np.flatnonzero(o_slot >= 0)
        self.of_slot, self.of_pt = o_slot[self.of], self.pt[self.of]
        self.f_of_o = np.full(len(self.cam), -1, np.int64)
        self.f_of_o[self.of] = np.arange(len(self.of))
        self.per_point = _Segments(self.pt, self.n_points)
        self.per_cam = _Segments(self.of_slot, self.nf)
        self.per_free_point = _Segments(self.of_pt, self.n_points)
        # Each point's observations by free cameras, as indices into ``of``: fp_obs[fp_start[p]:fp_start[p + 1]].
        self.fp_obs = self.per_free_point.order
        self.fp_start = np.r_[0, np.cumsum(np.bincount(self.of_pt, minlength=self.n_points))].astype(np.int64)
        self._pairs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def initial(self) -> BAState:
        return self.prob.T_cw.copy(), self.prob.points_w.copy()

    def evaluate(self, x: BAState) -> tuple[BAAux, float]:
        if self.compiled:
            p_c, r, cost = ba_kernels.evaluate(x[0], x[1], self.cam, self.pt, self.obs, self.has_depth, self.s,
                                               self.K, self.bf, self.huber_px)
        else:
            p_c, r, cost = _huber_residuals(x[0], x[1], self.cam, self.pt, self.obs, self.has_depth, self.s,
                                            self.K, self.bf, self.huber_px)
        return (p_c, r), cost

    def blocks(self, x: BAState, aux: BAAux) -> BABlocks:
        if not self.compiled:
            return self._blocks_reference(x, aux)
        return BABlocks(*ba_kernels.blocks(x[0], aux[0], aux[1], self.cam, self.pt, self.has_depth, self.s, self.K,
                                           self.bf, self.huber_px, self.cam_slot, self.f_of_o, self.n_points,
                                           self.nf, len(self.of)))

    def reduce(self, b: BABlocks, lam: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The points eliminated (Schur complement), undamped on the cameras: (Hpp_inv [P, 3, 3] of
        the point blocks with ``lam`` times their diagonal added, S [6 nf, 6 nf] = blockdiag(Hcc) -
        Hcp Hpp_inv Hcp^T, rhs [6 nf] = gc - Hcp Hpp_inv gp)."""
        if self.compiled:
            return ba_kernels.reduce_cameras(b.Hpp, b.gp, b.Hcp, b.Hcc, b.gc, self.fp_start, self.fp_obs,
                                             self.of_slot, lam)
        return self._reduce_reference(b, lam)

    def back_substitute(self, b: BABlocks, Hpp_inv: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """The points' steps dX [P, 3] = Hpp_inv (-gp - Hpc dc) for the cameras' steps dc [nf, 6]."""
        if self.compiled:
            return ba_kernels.back_substitute(Hpp_inv, b.gp, b.Hcp, self.fp_start, self.fp_obs, self.of_slot, dc)
        corr = self.per_free_point.sum(np.einsum("fij,fi->fj", b.Hcp, dc[self.of_slot]))
        return -np.einsum("pij,pj->pi", Hpp_inv, b.gp + corr)

    def _reduce_reference(self, b: BABlocks, lam: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Twin of ``ba_kernels.reduce_cameras``: the camera-camera blocks accumulated over the
        pairs of observations of each point (each point is seen by a handful of keyframes)."""
        nf = self.nf
        if self._pairs is None:
            q1, q2 = _obs_pairs(self.of_pt, self.n_points)
            idx = ((self.of_slot[q1] * 6)[:, None, None] + np.arange(6)[None, :, None]) * (6 * nf) \
                + (self.of_slot[q2] * 6)[:, None, None] + np.arange(6)[None, None, :]  # [Q, 6, 6] into S.ravel()
            self._pairs = q1, q2, idx
        q1, q2, pair_idx = self._pairs
        Hpp_inv = np.linalg.inv(b.Hpp + lam * b.Hpp * np.eye(3) + 1e-9 * np.eye(3))  # [P, 3, 3]
        W = np.matmul(b.Hcp, Hpp_inv[self.of_pt])  # [F, 6, 3]
        S = np.zeros((6 * nf, 6 * nf))
        for i in range(nf):
            S[6 * i:6 * i + 6, 6 * i:6 * i + 6] = b.Hcc[i]
        blocks = np.matmul(W[q1], b.Hcp[q2].transpose(0, 2, 1))  # [Q, 6, 6]
        S -= np.bincount(pair_idx.ravel(), blocks.ravel(), minlength=S.size).reshape(S.shape)
        rhs = b.gc - self.per_cam.sum(np.einsum("fij,fj->fi", W, b.gp[self.of_pt]))
        return Hpp_inv, S, rhs.ravel()

    def _blocks_reference(self, x: BAState, aux: BAAux) -> BABlocks:
        """Twin of ``ba_kernels.blocks``."""
        T, (p_c, r), of = x[0], aux, self.of
        e = np.sqrt(np.einsum("ij,ij->i", r, r))
        w = np.where(e <= self.huber_px, 1.0, self.huber_px / np.maximum(e, 1e-12))  # IRLS Huber weight [O]
        Jp = _projection_jacobian(p_c, self.K[0, 0], self.K[1, 1], self.bf)
        Jp[~self.has_depth, 2, :] = 0.0
        Jp *= self.s[:, None, None]
        Jx = np.matmul(Jp, T[self.cam, :3, :3])  # d r / d X [O, 3, 3]
        wJxT = (Jx * w[:, None, None]).transpose(0, 2, 1)  # [O, 3, 3]
        Hpp = self.per_point.sum(np.matmul(wJxT, Jx))
        gp = self.per_point.sum(np.matmul(wJxT, r[:, :, None])[:, :, 0])
        Jc = np.concatenate([-np.matmul(Jp[of], _skew(p_c[of])), Jp[of]], axis=2)  # [F, 3, 6]
        wJcT = (Jc * w[of, None, None]).transpose(0, 2, 1)  # [F, 6, 3]
        return BABlocks(Hpp, gp, np.matmul(wJcT, Jx[of]), self.per_cam.sum(np.matmul(wJcT, Jc)),
                        self.per_cam.sum(np.matmul(wJcT, r[of, :, None])[:, :, 0]))

    def linearise(self, damp_cameras: bool) -> Callable[[BAState, BAAux], Callable[[float], BAState | None]]:
        """LM's linearisation: at a state, its blocks; for a damping ``lam``, the Schur step (the
        cameras' reduced system solved, the points back-substituted), or None when it is singular.
        Damped on the reduced system's diagonal (local BA), or with ``damp_cameras`` on the camera
        blocks' own before the points' share is taken off (global BA)."""

        def at(x: BAState, aux: BAAux) -> Callable[[float], BAState | None]:
            b = self.blocks(x, aux)

            def propose(lam: float) -> BAState | None:
                Hpp_inv, S, rhs = self.reduce(b, lam)
                dc = np.zeros((0, 6))
                if self.nf:
                    diag = np.einsum("kii->ki", b.Hcc).ravel() if damp_cameras else np.diag(S)
                    S += np.diag(lam * diag) + 1e-9 * np.eye(6 * self.nf)
                    try:
                        dc = -np.linalg.solve(S, rhs).reshape(self.nf, 6)
                    except np.linalg.LinAlgError:
                        return None
                return self.stepped(x, dc, self.back_substitute(b, Hpp_inv, dc))

            return propose

        return at

    def stepped(self, x: BAState, dc: np.ndarray, dX: np.ndarray) -> BAState:
        """State after camera steps dc [nf, 6] (left update) and point steps dX [P, 3]."""
        T_new = x[0].copy()
        for i, c in enumerate(self.free.tolist()):
            T_new[c] = apply_left_update(x[0][c], dc[i])
        return T_new, x[1] + dX

    def result(self, progress: LMProgress[BAState, BAAux]) -> BAResult:
        """The BAResult of an LM state: poses re-orthonormalised, chi-square inliers per observation."""
        (T, X), (_, r) = progress.x, progress.aux
        chi2 = np.einsum("ij,ij->i", r, r)
        p_cz = np.einsum("oij,oj->oi", T[self.cam, :3, :3], X[self.pt])[:, 2] + T[self.cam, 2, 3]
        inl = (p_cz > 1e-4) & (chi2 < np.where(self.has_depth, CHI2_STEREO, CHI2_MONO))
        T = np.stack([orthonormalized(Ti) for Ti in T])
        return BAResult(T, X, inl, progress.initial_cost, progress.cost, progress.n_evaluations)


def camera_shift_ratio(prob: BAProblem, T_cw_after: np.ndarray, cam: int) -> float:
    """How far camera ``cam`` moved (its centre, metres) over the median depth (metres) of the
    points it observes at its pose before; ``T_cw_after``: [C, 4, 4]. 0.0 when it sees no point in
    front of it. A scale-free size of a move: 1 cm at 1 m and 4 cm at 4 m are the same 0.01."""
    R0, t0 = prob.T_cw[cam, :3, :3], prob.T_cw[cam, :3, 3]
    R1, t1 = T_cw_after[cam, :3, :3], T_cw_after[cam, :3, 3]
    shift = float(np.linalg.norm(R1.T @ t1 - R0.T @ t0))  # camera centres -R^T t
    z = prob.points_w[prob.obs_point[prob.obs_cam == cam]] @ R0[2] + t0[2]
    z = z[z > 0]
    return shift / float(np.median(z)) if len(z) else 0.0


def local_bundle_adjustment(prob: BAProblem, K: np.ndarray, bf: float, huber_px: float,
                            max_iterations: int, compiled: bool | None = None) -> BAResult:
    """Jointly refine free keyframe poses and all points: Levenberg-Marquardt with the Schur complement.

    Residuals per observation are (u, v[, u_right]) scaled by ``obs_inv_sigma``; Huber on the
    observation's whitened error norm with threshold ``huber_px`` (iteratively reweighted).
    Points are eliminated per point (3x3 blocks, ``BAGeometry.reduce``), so each step solves one
    dense [6C, 6C] system. ``compiled``: see ``BAGeometry`` (False: the numpy twins).
    Twin: ``ba_reference.local_bundle_adjustment_scipy`` (same residuals, scipy TRF).
    """
    g = BAGeometry(prob, K, bf, huber_px, compiled)
    return g.result(solve(lm_iterations(g.initial(), g.evaluate, g.linearise(damp_cameras=False), max_iterations)))
