"""Frame-to-local-map pose estimation and the constant-velocity motion model (front-end pieces).

``LocalMapMatcher``: project the local map's points with a predicted pose, match in a radius,
robust motion-only optimisation, then again in a tight radius around the optimised pose (with
PnP RANSAC and a keyframe's matches as fallbacks). Where numba is, each pass is one compiled call
(``kernel_calls.track_pass_kernel``) on the map's store, read in place, and the visible / found
statistics another; the numpy path (``_match_and_optimise_reference``) is the reference they are
tested against (same matches, same pose). It reads the map it is given and keeps only per-frame
caches of the keypoints' arrays. ``MotionModel``: the per-frame motion T_cw(k) T_cw(k-1)^-1 and the
angular velocity the rolling-shutter correction needs.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import invert_pose, rotmat_to_rotvec
from memgs_ros.core.tracking.backend.bundle_adjustment import (
    CHI2_MONO,
    CHI2_STEREO,
    observed_uvr,
    optimize_pose,
    orthonormalized,
    pose_covariance,
    so3_exp,
)
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.features.features import (
    MATCH_CELL_PX,
    FrameFeatures,
    match_by_projection,
    match_descriptors,
)
from memgs_ros.core.tracking.frontend.local_map import SparseMap
from memgs_ros.core.tracking.kernel_calls import View, numba_available, track_pass_kernel

_MIN_PROJECTION_MATCHES = 30  # below this the first pass is retried with a wider radius
_WIDE_RADIUS_FACTOR = 3.0
_NOMINAL_FRAME_DT_S = 1.0 / 30.0  # frame interval assumed until two stamps are known
_MAX_FRAME_DT_S = 0.5  # longer gaps: the velocity says nothing about the motion inside a frame
_GAP_RATIO = 1.5  # an interval this many times the velocity's spans a skipped frame: scale the motion
_POSE_ITERATIONS = 6  # Gauss-Newton steps per outlier round (optimize_pose's default)


@dataclass(frozen=True, eq=False)
class _Observations:
    """A frame's keypoints as the compiled pass reads them: obs [M, 3] (u, v, u - bf/z), has_depth
    [M], w2 [M] squared 1/sigma (``optimize_pose``'s inputs, for every keypoint at once)."""

    feats: FrameFeatures
    obs: np.ndarray
    has_depth: np.ndarray
    w2: np.ndarray


@dataclass(frozen=True, eq=False)
class TrackOutcome:
    """T_cw: [4, 4]; point_ids / kp_idx: [K] inlier matches; n_matches before outlier rejection."""

    T_cw: np.ndarray
    point_ids: np.ndarray
    kp_idx: np.ndarray
    n_matches: int


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix [3, 3] in degrees."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian [3, 3] at rotation vector ``phi`` [3]: SE(3)'s exp maps (phi, rho)
    to translation V(phi) rho."""
    theta2 = float(phi @ phi)
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta2 < 1e-12:
        return np.eye(3) + 0.5 * K
    theta = np.sqrt(theta2)
    return np.eye(3) + (1.0 - np.cos(theta)) / theta2 * K + (theta - np.sin(theta)) / (theta2 * theta) * (K @ K)


class MotionModel:
    """Constant velocity: T_cw(k) = velocity @ T_cw(k-1), over ``dt_s`` seconds."""

    def __init__(self) -> None:
        self.velocity = np.eye(4)
        self.known = False  # False after a map start or relocalisation: the identity is a guess
        self.dt_s = _NOMINAL_FRAME_DT_S  # the interval the velocity spans
        self.last_stamp_ns: int | None = None

    def reset(self) -> None:
        self.velocity = np.eye(4)
        self.known = False

    def motion_over(self, dt_s: float) -> np.ndarray:
        """The predicted motion [4, 4] (T_cw(k) T_cw(k-1)^-1) over ``dt_s`` seconds.

        The velocity itself while frames come at the interval it spans; over a gap of a skipped
        frame or more (a live tracker dropping stale frames) it is scaled to the gap as a screw
        motion (the velocity twice for twice its interval): unscaled, it predicted a third of the
        motion after two skipped frames on fr1/rpy, and such frames took the slow paths (wide
        search, PnP).
        """
        ratio = dt_s / self.dt_s
        if not self.known or 1.0 / _GAP_RATIO < ratio < _GAP_RATIO:
            return self.velocity
        # The screw motion's power: rotation vector phi and translation t = V(phi) rho scale to
        # ratio * phi and V(ratio * phi) ratio * rho (V: SO(3)'s left Jacobian).
        phi = rotmat_to_rotvec(self.velocity[:3, :3])
        rho = np.linalg.solve(_left_jacobian(phi), self.velocity[:3, 3])
        out = np.eye(4)
        out[:3, :3] = so3_exp(ratio * phi)
        out[:3, 3] = _left_jacobian(ratio * phi) @ (ratio * rho)
        return out

    def update(self, T_cw: np.ndarray, T_cw_prev: np.ndarray, dt_s: float) -> None:
        self.velocity = orthonormalized(T_cw @ invert_pose(T_cw_prev))
        self.dt_s = dt_s
        self.known = True

    def frame_dt_s(self, stamp_ns: int) -> float:
        """Seconds since the previous frame (nominal when unknown, out of order or a long gap)."""
        if self.last_stamp_ns is None:
            return _NOMINAL_FRAME_DT_S
        dt = (stamp_ns - self.last_stamp_ns) * 1e-9
        return dt if 0.0 < dt <= _MAX_FRAME_DT_S else _NOMINAL_FRAME_DT_S

    @staticmethod
    def angular_velocity(velocity: np.ndarray, dt_s: float) -> np.ndarray:
        """Camera-frame angular velocity [3] (rad/s) of a per-frame motion ``velocity`` [4, 4] (T_cw).

        R_wc(k) = R_wc(k-1) Exp(omega dt), and velocity = T_cw(k) T_cw(k-1)^-1, so
        Exp(omega dt) = R(velocity)^T.
        """
        return rotmat_to_rotvec(velocity[:3, :3].T) / dt_s

    def frame_angular_velocity(self, T_cw: np.ndarray, T_cw_prev: np.ndarray, dt_s: float) -> np.ndarray:
        """This interval's angular velocity [3], averaged with the previous interval's when known:
        one interval's estimate carries the pose noise of both its ends, and the rolling-shutter
        correction feeds it back into this pose (fr1/rpy head, readout 20 ms: RPE1 1.09 -> 1.00 cm;
        at 30 ms one interval went unstable, RPE1 2.7 cm, two stayed at 1.6 cm)."""
        omega = self.angular_velocity(T_cw @ invert_pose(T_cw_prev), dt_s)
        if self.known:
            omega = 0.5 * (omega + self.angular_velocity(self.velocity, self.dt_s))
        return omega


class LocalMapMatcher:
    """Pose of a frame against a sparse map (see the module docstring)."""

    def __init__(self, cfg: TrackerConfig, camera: PinholeCamera, inv_sigma_levels: np.ndarray,
                 compiled: bool | None = None) -> None:
        self.cfg, self.camera, self.K = cfg, camera, camera.K
        self.chi2_scale = cfg.chi2_scale  # the inlier bounds, from max_reprojection_px
        self.bf = camera.fx * cfg.virtual_baseline_m
        self.inv_sigma_levels = inv_sigma_levels
        # One compiled call per projection pass and one for the statistics, on the map's own
        # arrays (default: where numba is); else the reference path (numpy around the kernels).
        self.compiled = numba_available() if compiled is None else compiled
        self._view: View = (float(self.K[0, 0]), float(self.K[1, 1]), float(self.K[0, 2]), float(self.K[1, 2]),
                            float(camera.width), float(camera.height), cfg.min_depth_m * 0.5)
        self._kp_tree: tuple[FrameFeatures, cKDTree] | None = None
        self._kp_obs: _Observations | None = None  # the compiled pass's keypoint arrays, per frame
        # The last ``track`` call's local map (map, keyframes, point ids, positions or None): ``count``
        # follows it within the same frame, on an unchanged map, and takes it once.
        self._local: tuple[SparseMap, tuple[int, ...], np.ndarray, np.ndarray | None] | None = None

    def inv_sigma(self, octave: np.ndarray) -> np.ndarray:
        return self.inv_sigma_levels[np.clip(octave, 0, len(self.inv_sigma_levels) - 1)]

    def project(self, p_w: np.ndarray, T_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map points [P, 3] to undistorted pixels [P, 2] and in-view mask [P]."""
        p_c = p_w @ T_cw[:3, :3].T + T_cw[:3, 3]
        z = p_c[:, 2]
        front = z > self.cfg.min_depth_m * 0.5
        zs = np.where(front, z, 1.0)
        uv = np.column_stack([self.K[0, 0] * p_c[:, 0] / zs + self.K[0, 2],
                              self.K[1, 1] * p_c[:, 1] / zs + self.K[1, 2]])
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < self.camera.width) & \
            (uv[:, 1] >= 0) & (uv[:, 1] < self.camera.height)
        return uv, inside

    def covariance(self, T_cw: np.ndarray, smap: SparseMap, feats: FrameFeatures, outcome: TrackOutcome
                   ) -> np.ndarray | None:
        """``bundle_adjustment.pose_covariance`` of a pose fitted on ``outcome``'s matches (its map
        points at its keypoints), with the residuals ``optimise`` uses."""
        kp_idx, p_w = outcome.kp_idx, smap.point_arrays(outcome.point_ids)[0]
        depth = feats.depth_m[kp_idx] if self.cfg.track_with_depth else np.full(len(kp_idx), np.nan)
        return pose_covariance(T_cw, p_w, depth, self.inv_sigma(feats.octave[kp_idx]), self.K, self.bf)

    def optimise(self, T_cw: np.ndarray, p_w: np.ndarray, feats: FrameFeatures, kp_idx: np.ndarray,
                 rounds: int) -> tuple[np.ndarray, np.ndarray]:
        """Motion-only refinement on matches (points p_w [K, 3], keypoints kp_idx [K]): (T_cw, inlier [K])."""
        depth = feats.depth_m[kp_idx] if self.cfg.track_with_depth else np.full(len(kp_idx), np.nan)
        return optimize_pose(T_cw, p_w, feats.uv[kp_idx], depth, self.inv_sigma(feats.octave[kp_idx]),
                             self.K, self.bf, chi2_scale=self.chi2_scale, rounds=rounds)

    def _observations(self, feats: FrameFeatures) -> _Observations:
        """The keypoint arrays of ``feats`` for the compiled pass (made once per features object)."""
        if self._kp_obs is None or self._kp_obs.feats is not feats:
            depth = feats.depth_m if self.cfg.track_with_depth else np.full(len(feats), np.nan)
            obs, has_depth = observed_uvr(feats.uv, depth, self.bf)
            self._kp_obs = _Observations(feats, obs, has_depth, self.inv_sigma(feats.octave) ** 2)
        return self._kp_obs

    def _match_and_optimise(self, feats: FrameFeatures, smap: SparseMap, pids: np.ndarray,
                            local: tuple[np.ndarray, np.ndarray, np.ndarray] | None, T_init: np.ndarray,
                            radius_px: float, rounds: int = 1, max_candidates: int = 12
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One projection pass over the local map's points ``pids``; returns (T_cw, index into pids,
        kp index, inlier mask). Compiled: one ``track_pass_kernel`` call on the map's store; else
        the reference on ``local`` (the points' pos, desc, octave)."""
        if local is not None:
            return self._match_and_optimise_reference(feats, *local, T_init, radius_px, rounds, max_candidates)
        kp = self._observations(feats)
        pos, desc, octave = smap.store()
        T, pi, ki, inl = track_pass_kernel(
            pos, desc, octave, pids, T_init, self._view, radius_px, self.inv_sigma_levels, feats.uv, feats.desc,
            kp.obs, kp.has_depth, kp.w2, self.cfg.max_descriptor_distance, self.cfg.match_ratio, max_candidates,
            MATCH_CELL_PX, self.bf, CHI2_MONO * self.chi2_scale, CHI2_STEREO * self.chi2_scale, rounds,
            _POSE_ITERATIONS)
        return (T_init if len(pi) < 4 else orthonormalized(T)), pi, ki, inl

    def _match_and_optimise_reference(self, feats: FrameFeatures, p_w: np.ndarray, desc: np.ndarray,
                                      octave: np.ndarray, T_init: np.ndarray, radius_px: float, rounds: int = 1,
                                      max_candidates: int = 12
                                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Reference twin of the compiled pass: project, ``match_by_projection``, ``optimize_pose``."""
        uv, vis = self.project(p_w, T_init)
        idx = np.flatnonzero(vis)
        radius = radius_px / self.inv_sigma(octave[idx])
        tree = None
        if not numba_available():  # only the plain matcher searches a k-d tree
            if self._kp_tree is None or self._kp_tree[0] is not feats:
                self._kp_tree = (feats, cKDTree(feats.uv))  # one tree per frame, shared by the passes
            tree = self._kp_tree[1]
        pi, ki, _ = match_by_projection(uv[idx], desc[idx], feats, radius,
                                        self.cfg.max_descriptor_distance, self.cfg.match_ratio,
                                        max_candidates=max_candidates, kp_tree=tree)
        pi = idx[pi]
        if len(pi) < 4:
            return T_init, pi, ki, np.zeros(len(pi), bool)
        T, inl = self.optimise(T_init, p_w[pi], feats, ki, rounds)
        return T, pi, ki, inl

    def ransac_pose(self, p_w: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
        if len(p_w) < 6:
            return None
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            p_w.astype(np.float64), uv.astype(np.float64), self.K, None,
            iterationsCount=self.cfg.ransac_iterations, reprojectionError=self.cfg.ransac_reprojection_px,
            confidence=0.99, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < self.cfg.min_inliers // 2:
            return None
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        return orthonormalized(T)

    def track(self, smap: SparseMap, local_kfs: list[int], feats: FrameFeatures, T_pred: np.ndarray,
              fallback_kf: int | None, last_tracked: np.ndarray | None = None) -> TrackOutcome | None:
        """Frame-to-local-map tracking from the prediction ``T_pred`` [4, 4] (T_cw); when that fails,
        from PnP RANSAC on the first matches, then (``fallback_kf``) from that keyframe's matches.

        ``last_tracked``: the point ids the previous frame tracked. The first pass then searches
        only those (ORB-SLAM's motion-model search), and the whole local map when they give too
        few inliers; the second pass searches the whole local map either way. On fr1/rpy this
        took ``bench_tracking.py --cases tum_nothread`` from 1.31 to 1.08 cm and the first pass's
        cost by about half: the points the last frame found make fewer wrong matches in the wide
        first radius."""
        cfg = self.cfg
        pids = smap.points_of(local_kfs)
        if len(pids) < cfg.min_inliers:
            return None
        local = None if self.compiled else smap.point_arrays(pids)
        self._local = (smap, tuple(local_kfs), pids, None if local is None else local[0])

        def run(T_init: np.ndarray, radius_px: float, rounds: int = 1
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            return self._match_and_optimise(feats, smap, pids, local, T_init, radius_px, rounds)

        sub = None if last_tracked is None else np.flatnonzero(smap.mask_of(last_tracked)[pids])
        if sub is not None and len(sub) >= _MIN_PROJECTION_MATCHES:
            T, pi, ki, inl = self._match_and_optimise(
                feats, smap, pids[sub], None if local is None else (local[0][sub], local[1][sub], local[2][sub]),
                T_pred, cfg.search_radius_px)
            pi = sub[pi]
        else:
            T, pi, ki, inl = run(T_pred, cfg.search_radius_px)
        if inl.sum() < _MIN_PROJECTION_MATCHES:
            T, pi, ki, inl = run(T_pred, cfg.search_radius_px * _WIDE_RADIUS_FACTOR)
        if inl.sum() < cfg.min_inliers and len(pi) >= 6:
            T_r = self.ransac_pose(smap.point_arrays(pids[pi])[0], feats.uv[ki])
            if T_r is not None:
                T, pi, ki, inl = run(T_r, cfg.search_radius_px)
        if inl.sum() < cfg.min_inliers and fallback_kf is not None:
            T_f = self.pose_from_keyframe(smap, feats, fallback_kf)
            if T_f is not None:
                T, pi, ki, inl = run(T_f, cfg.search_radius_px)
        if inl.sum() < cfg.min_inliers:
            return None
        # Second pass: everything in view, tight radius around the optimised pose.
        T2, pi2, ki2, inl2 = run(T, cfg.refine_radius_px, rounds=3)
        if inl2.sum() >= inl.sum():
            T, pi, ki, inl = T2, pi2, ki2, inl2
        return TrackOutcome(T, pids[pi[inl]], ki[inl], len(pi))

    def count(self, smap: SparseMap, local_kfs: list[int], outcome: TrackOutcome) -> None:
        """Local map points in view at the outcome's pose were visible; its inliers were found
        (the statistics point culling uses)."""
        local, self._local = self._local, None
        if local is not None and local[0] is smap and local[1] == tuple(local_kfs):
            pids, p_w = local[2], local[3]
        else:
            pids, p_w = smap.points_of(local_kfs), None
        if self.compiled:
            smap.count_seen(pids, outcome.T_cw, self._view, outcome.point_ids)
            return
        if p_w is None:
            p_w = smap.point_arrays(pids)[0]
        _, vis = self.project(p_w, outcome.T_cw)
        smap.count_visible(pids[vis])
        smap.count_found(outcome.point_ids)

    def pose_from_keyframe(self, smap: SparseMap, feats: FrameFeatures, kf_id: int) -> np.ndarray | None:
        """Brute-force match against one keyframe's map points, then PnP RANSAC."""
        kf = smap.keyframes.get(kf_id)
        if kf is None:
            return None
        has = np.flatnonzero(kf.point_ids >= 0)
        pids = kf.point_ids[has]
        ok = smap.good(pids)
        has, pids = has[ok], pids[ok]
        q, t = match_descriptors(feats.desc, kf.feats.desc[has], ratio=0.8,
                                 max_distance=self.cfg.max_descriptor_distance)
        if len(q) < self.cfg.min_inliers:
            return None
        p_w, _, _ = smap.point_arrays(pids[t])
        return self.ransac_pose(p_w, feats.uv[q])

    def observed_points_near(self, smap: SparseMap, T_cw: np.ndarray) -> np.ndarray:
        """Ids of good points that project into the image at ``T_cw`` (all keyframes)."""
        ids = smap.points_of(list(smap.keyframes))
        p_w, _, _ = smap.point_arrays(ids)
        _, vis = self.project(p_w, T_cw)
        return ids[vis]


__all__ = ["LocalMapMatcher", "MotionModel", "TrackOutcome", "rotation_angle_deg"]
