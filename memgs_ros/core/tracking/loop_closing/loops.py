"""Loop closing pieces: consistent loop candidates, 3D-2D verification, SE(3) pose-graph optimisation.

The tracker's back-end runs these (``place_recognition.PlaceRecognition``, on map snapshots);
nothing here keeps state across calls but the detector, so each piece is testable alone:

- ``LoopDetector``: ORB-SLAM's consistency check. A keyframe's candidates (BoW hits outside its
  local map, not recent) each bring a group (the candidate and its covisible keyframes); a group
  that shares a keyframe with a group of the previous query inherits its count + 1. A candidate
  whose count reaches ``consistency`` (3 consecutive keyframes agreeing) is returned.
- ``verify_loop``: descriptor matches between the query keyframe's keypoints and the candidate
  group's map points, PnP RANSAC, then robust refinement with depth: the query's pose T_cw in
  the (older, less drifted) frame of the candidate, with its inliers.
- ``optimise_pose_graph``: Levenberg-Marquardt over keyframe poses T_wc on SE(3) with relative-pose
  edges (spanning tree, strong covisibility, loop), sparse normal equations.

Loop closure is RGB-D only (metric depth makes the loop transform SE(3)); the monocular tracker
would need Sim(3) and does not detect loops (it still uses the BoW index to relocalise).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.backend.bundle_adjustment import (
    apply_left_update,
    optimize_pose,
    orthonormalized,
)
from memgs_ros.core.tracking.backend.lm import LMSettings, lm_iterations, solve
from memgs_ros.core.tracking.features.features import (
    FrameFeatures,
    match_by_projection,
    match_descriptors,
)

# ------------------------------------------------------------------------------ detection


@dataclass(frozen=True, eq=False)
class LoopCandidate:
    """A consistent loop candidate: the matched keyframe and its covisible group."""

    query_id: int
    candidate_id: int
    group: frozenset[int]
    score: float


class LoopDetector:
    """Consistency over consecutive query keyframes (see the module docstring)."""

    def __init__(self, consistency: int) -> None:
        self.consistency = consistency
        self._groups: list[tuple[frozenset[int], int]] = []  # (group, consistent count) of the last query

    def reset(self) -> None:
        self._groups = []

    def update(self, query_id: int, candidates: list[tuple[int, float, frozenset[int]]]) -> LoopCandidate | None:
        """Feed one query keyframe's candidates ((id, score, group) best first); returns the best
        candidate that is consistent over ``consistency`` consecutive queries, else None."""
        found: LoopCandidate | None = None
        new_groups: list[tuple[frozenset[int], int]] = []
        for kf_id, score, group in candidates:
            count = 1 + max((c for g, c in self._groups if g & group), default=0)
            new_groups.append((group, count))
            if count >= self.consistency and found is None:
                found = LoopCandidate(query_id, kf_id, group, score)
        self._groups = new_groups
        return found


# --------------------------------------------------------------------------- verification


@dataclass(frozen=True, eq=False)
class LoopMatch:
    """A verified loop. T_cw: [4, 4] the query keyframe in the candidate's frame;
    kp_idx: [K] query keypoints matched to map points point_ids [K] of the candidate group."""

    T_cw: np.ndarray
    kp_idx: np.ndarray
    point_ids: np.ndarray
    n_inliers: int


def verify_loop(query: FrameFeatures, q_inv_sigma: np.ndarray, point_ids: np.ndarray, p_w: np.ndarray,
                p_desc: np.ndarray, K: np.ndarray, bf: float, image_size: tuple[int, int], min_inliers: int,
                max_distance: int, ransac_px: float, iterations: int = 200,
                guided_radius_px: float = 4.0) -> LoopMatch | None:
    """Geometric verification of a loop (RGB-D).

    Match the query keyframe's keypoints (``query``, inv_sigma [M]) to the candidate group's
    points (ids [P], p_w [P, 3], desc [P, 32]) by descriptor, PnP RANSAC, robust refinement; then
    project every group point with that pose, match in ``guided_radius_px`` and refine again
    (repeated textures give RANSAC-consistent wrong poses whose projections find few further
    matches). None unless ``min_inliers`` survive each stage. image_size: (width, height).
    """
    q_uv, q_desc, q_depth = query.uv, query.desc, query.depth_m
    q, t = match_descriptors(q_desc, p_desc, ratio=0.8, max_distance=max_distance)
    if len(q) < min_inliers:
        return None
    obj, img = p_w[t].astype(np.float64), q_uv[q].astype(np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=iterations,
                                             reprojectionError=ransac_px, confidence=0.999,
                                             flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    T, inlier = optimize_pose(orthonormalized(T), obj, img, q_depth[q], q_inv_sigma[q], K, bf)
    if int(inlier.sum()) < min_inliers:
        return None
    # Guided pass: all group points in view, tight radius around the verified pose.
    p_c = p_w @ T[:3, :3].T + T[:3, 3]
    z = np.where(p_c[:, 2] > 1e-3, p_c[:, 2], 1.0)
    uv = np.column_stack([K[0, 0] * p_c[:, 0] / z + K[0, 2], K[1, 1] * p_c[:, 1] / z + K[1, 2]])
    vis = np.flatnonzero((p_c[:, 2] > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < image_size[0])
                         & (uv[:, 1] >= 0) & (uv[:, 1] < image_size[1]))
    pi, ki, _ = match_by_projection(uv[vis], p_desc[vis], query, guided_radius_px / q_inv_sigma.max(initial=1.0),
                                    max_distance, 0.9)
    if len(pi) < min_inliers:
        return None
    pi = vis[pi]
    T, inlier = optimize_pose(T, p_w[pi], q_uv[ki], q_depth[ki], q_inv_sigma[ki], K, bf)
    n = int(inlier.sum())
    if n < min_inliers:
        return None
    return LoopMatch(T, ki[inlier], point_ids[pi][inlier], n)


# ------------------------------------------------------------------------------ pose graph


@dataclass(frozen=True, eq=False)
class PoseGraphResult:
    """T_wc: [N, 4, 4] optimised poses; cost before/after (0.5 sum of squared weighted residuals)."""

    T_wc: np.ndarray
    initial_cost: float
    final_cost: float
    iterations: int


def _edge_residuals(T_wc: np.ndarray, ei: np.ndarray, ej: np.ndarray, Z_inv: np.ndarray,
                    sqrt_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals [E, 6] (rotation vector, translation of Z^-1 T_i^-1 T_j) and A = Z^-1 T_i^-1 [E, 4, 4]."""
    A = Z_inv @ invert_pose(T_wc[ei])
    E = A @ T_wc[ej]
    r = np.concatenate([Rotation.from_matrix(E[:, :3, :3]).as_rotvec(), E[:, :3, 3]], axis=1)
    return r * sqrt_w[:, None], A


# Pose-graph damping: residuals are small near the optimum, so start and shrink the damping lower
# than bundle adjustment does, and stop only on a tiny absolute decrease.
_POSE_GRAPH_LM = LMSettings(lam0=1e-4, lam_down=10.0, lam_min=1e-9, attempts=8, rel_tol=1e-8, abs_tol=1e-10)


def optimise_pose_graph(T_wc: np.ndarray, edges_i: np.ndarray, edges_j: np.ndarray, Z: np.ndarray,
                        weights: np.ndarray, fixed: np.ndarray, max_iterations: int = 20) -> PoseGraphResult:
    """SE(3) pose graph by Levenberg-Marquardt (the ``lm`` loop).

    T_wc: [N, 4, 4] initial poses; edges_i/edges_j: [E] node indices; Z: [E, 4, 4] measured
    relative poses T_wc_i^-1 T_wc_j; weights: [E] information (same for the 6 components,
    rotation in rad, translation in m); fixed: [N] bool (at least one, the gauge).
    Poses update on the left (``apply_left_update``); the Jacobian of an edge is the adjoint of
    A = Z^-1 T_i^-1 applied to (delta_j - delta_i), exact at zero residual.
    """
    n = len(T_wc)
    ei, ej = np.asarray(edges_i, np.int64), np.asarray(edges_j, np.int64)
    Z_inv = invert_pose(np.asarray(Z, np.float64))
    sqrt_w = np.sqrt(np.asarray(weights, np.float64))
    slot = np.full(n, -1, np.int64)
    free = np.flatnonzero(~np.asarray(fixed, bool))
    slot[free] = np.arange(len(free))
    m = len(ei)

    def evaluate(T: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], float]:
        r, A = _edge_residuals(T, ei, ej, Z_inv, sqrt_w)
        return (r, A), 0.5 * float(np.sum(r * r))

    def linearise(T: np.ndarray, aux: tuple[np.ndarray, np.ndarray]) -> Callable[[float], np.ndarray | None]:
        r, A = aux
        # Ad_A = [[R, 0], [t^ R, R]] for (w, v) ordering; d r / d delta_j = Ad_A, d r / d delta_i = -Ad_A.
        R, t = A[:, :3, :3], A[:, :3, 3]
        tx = np.zeros((m, 3, 3))
        tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 0] = -t[:, 2], t[:, 1], t[:, 2]
        tx[:, 1, 2], tx[:, 2, 0], tx[:, 2, 1] = -t[:, 0], -t[:, 1], t[:, 0]
        Ad = np.zeros((m, 6, 6))
        Ad[:, :3, :3] = R
        Ad[:, 3:, :3] = tx @ R
        Ad[:, 3:, 3:] = R
        Ad *= sqrt_w[:, None, None]
        rows, cols, vals = [], [], []
        base_rows = (np.arange(m) * 6)[:, None, None] + np.arange(6)[None, :, None]  # [E, 6, 1]
        for nodes, sign in ((ej, 1.0), (ei, -1.0)):
            s = slot[nodes]
            use = s >= 0
            rr = np.broadcast_to(base_rows[use], (int(use.sum()), 6, 6))
            cc = np.broadcast_to((s[use] * 6)[:, None, None] + np.arange(6)[None, None, :], rr.shape)
            rows.append(rr.ravel())
            cols.append(cc.ravel())
            vals.append((sign * Ad[use]).ravel())
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(6 * m, 6 * len(free)))
        H = (J.T @ J).tocsc()
        g = J.T @ r.ravel()
        diag = H.diagonal()

        def propose(lam: float) -> np.ndarray | None:
            try:
                dx = -spla.spsolve(H + sp.diags(lam * (diag + 1e-9)), g)
            except (RuntimeError, ValueError):
                return None
            if not np.all(np.isfinite(dx)):
                return None
            T_new = T.copy()
            for k, c in enumerate(free.tolist()):
                T_new[c] = apply_left_update(T[c], dx[6 * k:6 * k + 6])
            return T_new

        return propose

    T0 = np.asarray(T_wc, np.float64).copy()
    if len(free) == 0 or m == 0:
        cost0 = evaluate(T0)[1]
        return PoseGraphResult(T0, cost0, cost0, 0)
    res = solve(lm_iterations(T0, evaluate, linearise, max_iterations, _POSE_GRAPH_LM))
    T = np.stack([orthonormalized(Ti) for Ti in res.x])
    return PoseGraphResult(T, res.initial_cost, res.cost, res.iterations)


@dataclass(frozen=True, eq=False)
class LoopCorrection:
    """A loop correction ready to commit (made by the back-end from a map snapshot, committed by
    the front-end to its map at its next frame: ``corrections.commit_correction``).

    kf_ids: [N] keyframes of the snapshot; D: [N, 4, 4] each one's world-frame correction
    T_wc_new inv(T_wc_old); query_id: the loop keyframe (keyframes newer than the snapshot move
    with it); fuse_kp / fuse_points: [K] keypoints of keyframes ``fuse_kf`` (default the query)
    and the loop map points they matched (point ids at ``layout_version``), merged after the
    correction.

    A global bundle adjustment commits through the same path (``candidate_id`` -1): its point_ids
    [P] / points_w [P, 3] (numbered at ``layout_version``) overwrite those points after the
    keyframes moved, outliers [(point id, keyframe id)] lose that observation, and ``pose_epoch``
    (the snapshot's) discards it when another correction came in between; its T_wc_new replace the
    keyframe poses (D is then recomputed at commit).
    """

    kf_ids: np.ndarray
    D: np.ndarray
    query_id: int
    candidate_id: int
    fuse_kp: np.ndarray
    fuse_points: np.ndarray
    layout_version: int
    n_inliers: int
    time_s: float
    point_ids: np.ndarray | None = None
    points_w: np.ndarray | None = None
    outliers: tuple[tuple[int, int], ...] = ()
    pose_epoch: int | None = None
    T_wc_new: np.ndarray | None = None  # [N, 4, 4] global BA: poses that replace the current ones
    fuse_kf: np.ndarray | None = None  # [K] keyframe of each fuse entry (None: all the query's)

    @property
    def is_global_ba(self) -> bool:
        return self.candidate_id < 0


__all__ = ["LoopCandidate", "LoopCorrection", "LoopDetector", "LoopMatch", "PoseGraphResult",
           "optimise_pose_graph", "verify_loop"]
