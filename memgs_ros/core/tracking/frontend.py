"""Frame-to-local-map feature tracking shared by the RGB-D and monocular trackers.

Per frame: ORB features -> project the local map with the constant-velocity prediction ->
match in a radius -> robust motion-only optimisation -> re-project with the optimised pose
in a tight radius -> optimise again -> (rolling shutter: re-correct the keypoints with the new
angular velocity, optimise once more) -> gate the pose change -> keyframe decision. New
keyframes go to a background local bundle adjustment whose refined poses are committed
under the map lock and applied to the tracker's last pose at the next frame.

Place recognition runs on a second background thread: each new keyframe gets a bag-of-words
vector in the keyframe database (relocalisation queries it), and, with ``loop_closure`` (RGB-D),
is checked for a loop: consistent candidates outside the local map, PnP verification, then a
pose graph over all keyframes (``loop_closing``). The correction is committed under the map
lock at the start of the next ``track()`` (keyframes, points, the last pose move together), so
tracking never waits for the optimisation and never sees half a correction.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from memgs_ros.core.camera import PinholeCamera
from memgs_ros.core.frame import Frame
from memgs_ros.core.geometry import invert_pose, nearest_pose_distance
from memgs_ros.core.tracking._compiled import warm_up
from memgs_ros.core.tracking.bundle_adjustment import (BAProblem, local_bundle_adjustment, optimize_pose,
                                                        orthonormalized)
from memgs_ros.core.tracking.config import KeyframeInfo, TrackerConfig, TrackingState, TrackResult
from memgs_ros.core.tracking.features import (FrameFeatures, OrbExtractor, match_by_projection, match_descriptors,
                                              unroll_rolling_shutter)
from memgs_ros.core.tracking.global_ba import global_bundle_adjustment
from memgs_ros.core.tracking.local_map import SparseKeyframe, SparseMap
from memgs_ros.core.tracking.loop_closing import (LoopCorrection, LoopDetector, optimise_pose_graph,
                                                  verify_loop)
from memgs_ros.core.tracking.protocol import SparseMapStats, Tracker
from memgs_ros.core.tracking.relocalisation import relocalise
from memgs_ros.core.tracking.vocabulary import KeyframeDatabase, Vocabulary, bow_score, default_vocabulary
from memgs_ros.errors import DataError

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

_MIN_PROJECTION_MATCHES = 30  # below this the first pass is retried with a wider radius
_WIDE_RADIUS_FACTOR = 3.0
_LOOP_CANDIDATES = 3  # best BoW candidates per query that enter the consistency check
_LOOP_GROUP = 10  # covisible keyframes forming a candidate's group
_LOOP_EDGE_WEIGHT = 10.0  # loop edges against the identity-weighted odometry edges
_GLOBAL_BA_MAX_PAIRS = 250_000  # observation pairs of one global BA (~150 MB of blocks and indices)
_NOMINAL_FRAME_DT_S = 1.0 / 30.0  # frame interval assumed until two stamps are known
_MAX_FRAME_DT_S = 0.5  # longer gaps: the velocity says nothing about the motion inside a frame


@dataclass(frozen=True)
class LoopStats:
    """Place recognition counters: queries, consistent candidates, verified+committed loops,
    rejected by verification, pose-graph time in total (s), global bundle adjustments."""

    keyframes_indexed: int = 0
    loops_detected: int = 0
    loops_accepted: int = 0
    loops_rejected: int = 0
    pose_graph_time_s: float = 0.0
    global_ba_runs: int = 0  # committed global bundle adjustments
    global_ba_discarded: int = 0  # stale (another correction came first) or not improving
    global_ba_time_s: float = 0.0
    last_loop: tuple[int, int] | None = None  # (query keyframe, matched keyframe)


@dataclass(frozen=True, eq=False)
class _TrackOutcome:
    """T_cw: [4, 4]; point_ids / kp_idx: [K] inlier matches; n_matches before outlier rejection."""

    T_cw: np.ndarray
    point_ids: np.ndarray
    kp_idx: np.ndarray
    n_matches: int


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix [3, 3] in degrees."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


class FeatureTracker(Tracker):
    """Common machinery; subclasses add initialisation and new map points (depth or triangulation)."""

    uses_depth = True

    def __init__(self, cfg: TrackerConfig, camera: PinholeCamera) -> None:
        self.cfg = cfg
        self.camera = camera
        self.K = camera.K
        self.bf = camera.fx * cfg.virtual_baseline_m
        self.extractor = OrbExtractor(cfg)
        warm_up()  # compile the numba kernels now rather than in the first frames
        self.inv_sigma_levels = cfg.scale_factor ** -np.arange(cfg.n_levels, dtype=np.float64)
        self.map = SparseMap()
        self.state = TrackingState.NOT_INITIALIZED
        self.segment_id = 0
        self._T_cw_last: np.ndarray | None = None
        self._velocity = np.eye(4)  # T_cw(k) = velocity @ T_cw(k-1)
        self._velocity_known = False  # False after a map start or relocalisation: the identity is a guess
        self._velocity_dt_s = _NOMINAL_FRAME_DT_S  # the interval the velocity spans
        self._last_stamp_ns: int | None = None
        self._last_good_T_cw: np.ndarray | None = None
        self._lost_frames = 0
        self._last_kf_id = -1
        self._frames_since_kf = 0
        self._local_kfs: list[int] = []
        self._last_kf_info: KeyframeInfo | None = None
        # Keyframe poses T_cw as the corrected path last saw them (creation, then each loop commit):
        # loop corrections are expressed against these, so the path also takes the local BA
        # refinements made since (frames were tracked near the keyframe's first pose).
        self._path_T_cw: dict[int, np.ndarray] = {}
        self._kp_tree: tuple[FrameFeatures, cKDTree] | None = None
        self._refined: list[tuple[int, np.ndarray]] = []
        self._loop_refined: list[tuple[int, np.ndarray]] = []  # keyframe poses a loop closure corrected
        self._pending: list[dict[int, tuple[np.ndarray, np.ndarray]]] = []
        self._out_lock = threading.Lock()
        self._ba_queue: queue.Queue[tuple[SparseMap, int]] = queue.Queue()
        self._stop = threading.Event()
        self._ba_thread: threading.Thread | None = None
        if cfg.ba_enabled and cfg.ba_threaded:
            self._ba_thread = threading.Thread(target=self._ba_loop, name="memgs-local-ba", daemon=True)
            self._ba_thread.start()
        self.ba_runs = 0
        self.ba_time_s = 0.0
        # Place recognition: vocabulary, database and its own thread.
        self.vocabulary: Vocabulary | None = None
        try:
            self.vocabulary = default_vocabulary()
        except DataError as err:  # relocalisation falls back to keyframes spread over the map
            logger.warning("place recognition off: %s", err)
        self.keyframe_db = KeyframeDatabase()
        self._db_lock = threading.Lock()
        self._loop_detector = LoopDetector(cfg.loop_consistency)
        self._loop_pending: list[LoopCorrection] = []
        self._loop_done: list[dict[int, np.ndarray]] = []  # committed corrections, for poll_loop_corrections
        self._last_loop_query = -(10**9)
        self._gba_followup_at: int | None = None  # keyframe id that triggers the follow-up global BA
        self.loop_stats = LoopStats()
        self._stats_lock = threading.Lock()
        self._place_queue: queue.Queue[tuple[SparseMap, int]] = queue.Queue()
        self._place_thread: threading.Thread | None = None
        if self.vocabulary is not None and cfg.ba_threaded:
            self._place_thread = threading.Thread(target=self._place_loop, name="memgs-loop-closing", daemon=True)
            self._place_thread.start()

    # -- public -------------------------------------------------------------------------
    def track(self, frame: Frame) -> TrackResult:
        """Estimate the pose of ``frame``; see TrackResult for what each state carries."""
        t0 = time.perf_counter()
        if frame.camera.width != self.camera.width or frame.camera.height != self.camera.height:
            raise DataError(
                f"frame is {frame.camera.width}x{frame.camera.height} but the tracker was built for "
                f"{self.camera.width}x{self.camera.height}")
        if self.uses_depth and frame.depth_m is None:
            raise DataError("the RGB-D tracker needs frame.depth_m; use mode='mono' for colour-only input")
        self._apply_ba_corrections()
        self._apply_loop_corrections()
        gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
        feats = self.extractor.extract(gray, self.camera, frame.depth_m if self.uses_depth else None)
        if self.state == TrackingState.NOT_INITIALIZED:
            T_cw, kf, n_m, n_i = self._initialise(frame, feats)
        else:
            T_cw, kf, n_m, n_i = self._track_frame(frame, feats)
        self._last_stamp_ns = frame.stamp_ns
        T_wc = None if T_cw is None else invert_pose(T_cw)
        return TrackResult(frame.stamp_ns, T_wc, self.state, kf, n_m, n_i, time.perf_counter() - t0,
                           self.segment_id, self._last_kf_id if T_wc is not None else -1)

    def poll_refined_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe_id, refined T_wc [4, 4]) from local BA since the last poll, oldest first:
        small refinements the mapper takes as new training poses (its Gaussians stay)."""
        with self._out_lock:
            out, self._refined = self._refined, []
        return out

    def poll_loop_corrected_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe_id, corrected T_wc [4, 4]) of every keyframe a loop closure moved, since the
        last poll, oldest first: the mapper moves each keyframe's Gaussians with it."""
        with self._out_lock:
            out, self._loop_refined = self._loop_refined, []
        return out

    def poll_loop_corrections(self) -> list[dict[int, np.ndarray]]:
        """Loop corrections committed since the last poll, oldest first: {keyframe_id: D [4, 4]}
        with D = T_wc_new T_wc_old^-1 the keyframe's world-frame correction (``AnchoredPath``)."""
        with self._out_lock:
            out, self._loop_done = self._loop_done, []
        return out

    def map_stats(self) -> SparseMapStats:
        """The sparse map's keyframes and good points, read under the map lock (BA may run)."""
        with self.map.lock:
            return SparseMapStats(frozenset(self.map.keyframes), self.map.n_good_points, self.map.keyframes_removed)

    def close(self) -> None:
        """Stop the bundle adjustment and place recognition threads (idempotent)."""
        self._stop.set()
        for name in ("_ba_thread", "_place_thread"):
            th = getattr(self, name)
            if th is not None:
                th.join(timeout=10.0)
                setattr(self, name, None)

    def wait_for_loop_closing(self, timeout_s: float = 60.0) -> None:
        """Block until queued keyframes are indexed and checked for loops, then commit a pending
        correction (for tests and offline evaluation; call from the tracking thread)."""
        deadline = time.monotonic() + timeout_s
        while True:
            while self._place_thread is not None and time.monotonic() < deadline:
                if self._place_queue.unfinished_tasks == 0:
                    break
                time.sleep(0.005)
            # A committed loop queues a global BA on the same thread: wait for that one too.
            if self._apply_loop_corrections() == 0 or time.monotonic() >= deadline:
                break

    def wait_for_ba(self, timeout_s: float = 30.0) -> None:
        """Block until queued local BA jobs are done (for tests and offline evaluation)."""
        deadline = time.monotonic() + timeout_s
        while self._ba_thread is not None and time.monotonic() < deadline:
            if self._ba_queue.unfinished_tasks == 0:
                return
            time.sleep(0.005)

    def __enter__(self) -> "FeatureTracker":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- subclass hooks -----------------------------------------------------------------
    def _initialise(self, frame: Frame, feats: FrameFeatures
                    ) -> tuple[np.ndarray | None, KeyframeInfo | None, int, int]:
        raise NotImplementedError

    def _create_points(self, kf: SparseKeyframe, frame: Frame) -> None:
        raise NotImplementedError

    def _need_close_points(self, feats: FrameFeatures, kp_idx: np.ndarray) -> bool:
        return False

    def _lost_timeout(self, frame: Frame, feats: FrameFeatures) -> np.ndarray | None:
        """Called when lost for too long; may start a new segment and return its pose T_cw."""
        return None

    # -- tracking -----------------------------------------------------------------------
    def _frame_dt_s(self, stamp_ns: int) -> float:
        """Seconds since the previous frame (nominal when unknown, out of order or a long gap)."""
        if self._last_stamp_ns is None:
            return _NOMINAL_FRAME_DT_S
        dt = (stamp_ns - self._last_stamp_ns) * 1e-9
        return dt if 0.0 < dt <= _MAX_FRAME_DT_S else _NOMINAL_FRAME_DT_S

    def _angular_velocity(self, velocity: np.ndarray, dt_s: float) -> np.ndarray:
        """Camera-frame angular velocity [3] (rad/s) of a per-frame motion ``velocity`` [4, 4] (T_cw).

        R_wc(k) = R_wc(k-1) Exp(omega dt), and velocity = T_cw(k) T_cw(k-1)^-1, so
        Exp(omega dt) = R(velocity)^T.
        """
        return Rotation.from_matrix(velocity[:3, :3].T).as_rotvec() / dt_s

    def _unrolled(self, feats: FrameFeatures, omega_c: np.ndarray) -> FrameFeatures:
        return unroll_rolling_shutter(feats, self.K, omega_c, self.cfg.rolling_shutter_readout_s,
                                      self.camera.height)

    def _refine_rolling_shutter(self, raw: FrameFeatures, outcome: _TrackOutcome, dt_s: float
                                ) -> tuple[FrameFeatures, _TrackOutcome]:
        """Re-correct the keypoints with this frame's own angular velocity and re-optimise the pose
        on the same matches (the first correction used the previous frame's; on fr1/rpy the
        rotation speed changes by up to 50 % from one frame to the next).

        The angular velocity is the mean over this interval and the previous one: one interval's
        estimate carries the pose noise of both its ends, and the correction feeds it back into
        this pose (fr1/rpy head, readout 20 ms: RPE1 1.09 -> 1.00 cm; at 30 ms one interval
        went unstable, RPE1 2.7 cm, two stayed at 1.6 cm).
        """
        assert self._T_cw_last is not None
        omega = self._angular_velocity(outcome.T_cw @ invert_pose(self._T_cw_last), dt_s)
        if self._velocity_known:
            omega = 0.5 * (omega + self._angular_velocity(self._velocity, self._velocity_dt_s))
        feats = self._unrolled(raw, omega)
        p_w, _, _ = self.map.point_arrays(outcome.point_ids)
        ki = outcome.kp_idx
        depth = feats.depth_m[ki] if self.cfg.track_with_depth else np.full(len(ki), np.nan)
        T, inl = optimize_pose(outcome.T_cw, p_w, feats.uv[ki], depth, self._inv_sigma(feats.octave[ki]),
                               self.K, self.bf, rounds=2)
        if inl.sum() < self.cfg.min_inliers:
            return feats, outcome
        return feats, _TrackOutcome(T, outcome.point_ids[inl], ki[inl], outcome.n_matches)

    def _inv_sigma(self, octave: np.ndarray) -> np.ndarray:
        return self.inv_sigma_levels[np.clip(octave, 0, len(self.inv_sigma_levels) - 1)]

    def _project(self, p_w: np.ndarray, T_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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

    def _match_and_optimise(self, feats: FrameFeatures, pids: np.ndarray, p_w: np.ndarray,
                            desc: np.ndarray, octave: np.ndarray, T_init: np.ndarray,
                            radius_px: float, rounds: int = 1, max_candidates: int = 12
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """One projection pass; returns (T_cw, point index, kp index, inlier mask, n visible)."""
        uv, vis = self._project(p_w, T_init)
        idx = np.flatnonzero(vis)
        radius = radius_px / self._inv_sigma(octave[idx])
        if self._kp_tree is None or self._kp_tree[0] is not feats:
            self._kp_tree = (feats, cKDTree(feats.uv))  # one tree per frame, shared by the passes
        pi, ki, _ = match_by_projection(uv[idx], desc[idx], feats, radius,
                                        self.cfg.max_descriptor_distance, self.cfg.match_ratio,
                                        max_candidates=max_candidates, kp_tree=self._kp_tree[1])
        pi = idx[pi]
        if len(pi) < 4:
            return T_init, pi, ki, np.zeros(len(pi), bool), len(idx)
        depth = feats.depth_m[ki] if self.cfg.track_with_depth else np.full(len(ki), np.nan)
        T, inl = optimize_pose(T_init, p_w[pi], feats.uv[ki], depth,
                               self._inv_sigma(feats.octave[ki]), self.K, self.bf, rounds=rounds)
        return T, pi, ki, inl, len(idx)

    def _ransac_pose(self, p_w: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
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

    def _track_local_map(self, feats: FrameFeatures, T_pred: np.ndarray,
                         allow_fallback: bool, count: bool = True) -> _TrackOutcome | None:
        """Frame-to-local-map tracking from the prediction ``T_pred`` [4, 4] (T_cw).

        ``count``: add this frame to the points' visible / found counts (the culling statistics);
        False when the caller compares several outcomes and counts the chosen one itself.
        """
        cfg = self.cfg
        pids = self.map.points_of(self._local_kfs)
        if len(pids) < cfg.min_inliers:
            return None
        p_w, desc, octave = self.map.point_arrays(pids)
        T, pi, ki, inl, _ = self._match_and_optimise(feats, pids, p_w, desc, octave, T_pred,
                                                     cfg.search_radius_px)
        if inl.sum() < _MIN_PROJECTION_MATCHES:
            T, pi, ki, inl, _ = self._match_and_optimise(feats, pids, p_w, desc, octave, T_pred,
                                                         cfg.search_radius_px * _WIDE_RADIUS_FACTOR)
        if inl.sum() < cfg.min_inliers and len(pi) >= 6:
            T_r = self._ransac_pose(p_w[pi], feats.uv[ki])
            if T_r is not None:
                T, pi, ki, inl, _ = self._match_and_optimise(feats, pids, p_w, desc, octave, T_r,
                                                             cfg.search_radius_px)
        if inl.sum() < cfg.min_inliers and allow_fallback:
            T_f = self._pose_from_keyframe(feats, self._last_kf_id)
            if T_f is not None:
                T, pi, ki, inl, _ = self._match_and_optimise(feats, pids, p_w, desc, octave, T_f,
                                                             cfg.search_radius_px)
        if inl.sum() < cfg.min_inliers:
            return None
        # Second pass: everything in view, tight radius around the optimised pose.
        T2, pi2, ki2, inl2, _ = self._match_and_optimise(feats, pids, p_w, desc, octave, T,
                                                         cfg.refine_radius_px, rounds=3)
        if inl2.sum() >= inl.sum():
            T, pi, ki, inl = T2, pi2, ki2, inl2
        outcome = _TrackOutcome(T, pids[pi[inl]], ki[inl], len(pi))
        if count:
            self._count_local_map(outcome)
        return outcome

    def _count_local_map(self, outcome: _TrackOutcome) -> None:
        """Local map points in view at the outcome's pose were visible; its inliers were found."""
        pids = self.map.points_of(self._local_kfs)
        p_w, _, _ = self.map.point_arrays(pids)
        _, vis = self._project(p_w, outcome.T_cw)
        self.map.count_visible(pids[vis])
        self.map.count_found(outcome.point_ids)

    def _pose_from_keyframe(self, feats: FrameFeatures, kf_id: int) -> np.ndarray | None:
        """Fallback: brute-force match against one keyframe's map points, then PnP RANSAC."""
        kf = self.map.keyframes.get(kf_id)
        if kf is None:
            return None
        has = np.flatnonzero(kf.point_ids >= 0)
        pids = kf.point_ids[has]
        ok = self.map.good(pids)
        has, pids = has[ok], pids[ok]
        q, t = match_descriptors(feats.desc, kf.feats.desc[has], ratio=0.8,
                                 max_distance=self.cfg.max_descriptor_distance)
        if len(q) < self.cfg.min_inliers:
            return None
        p_w, _, _ = self.map.point_arrays(pids[t])
        return self._ransac_pose(p_w, feats.uv[q])

    def _pose_is_plausible(self, T_cw: np.ndarray, T_pred: np.ndarray) -> bool:
        """Gate the change against the constant-velocity prediction (never emit a wild pose)."""
        d = T_cw @ invert_pose(T_pred)
        c_new = -T_cw[:3, :3].T @ T_cw[:3, 3]
        c_pred = -T_pred[:3, :3].T @ T_pred[:3, 3]
        return (np.linalg.norm(c_new - c_pred) <= self.cfg.max_translation_jump_m * self._scale_unit()
                and rotation_angle_deg(d[:3, :3]) <= self.cfg.max_rotation_jump_deg)

    def _scale_unit(self) -> float:
        """Metres per map unit for the translation gate (1 for RGB-D; mono overrides)."""
        return 1.0

    def _track_frame(self, frame: Frame, feats: FrameFeatures
                     ) -> tuple[np.ndarray | None, KeyframeInfo | None, int, int]:
        cfg = self.cfg
        assert self._T_cw_last is not None
        T_pred = orthonormalized(self._velocity @ self._T_cw_last)
        dt_s = self._frame_dt_s(frame.stamp_ns)
        rolling = self.cfg.rolling_shutter_readout_s > 0.0
        raw = feats
        if rolling:  # first guess: the angular velocity of the previous frame
            feats = self._unrolled(raw, self._angular_velocity(self._velocity, self._velocity_dt_s))
        outcome = None
        predicting = self.state == TrackingState.OK or (
            self.state == TrackingState.RECENTLY_LOST and self._lost_frames <= cfg.max_recently_lost_frames)
        if predicting and (self._velocity_known or not self.uses_depth):
            outcome = self._track_local_map(feats, T_pred, allow_fallback=True)
        elif predicting:
            # No motion model yet (the frame after a map start or relocalisation): the
            # zero-motion guess can sit a few degrees off in a fast turn, where rotation and
            # sideways translation explain the same matches. Also track from the pose the
            # keyframe's matches give, and keep the one with more inliers. RGB-D only: right
            # after a two-view start the monocular map is too thin to arbitrate (measured:
            # Sim(3) ATE 1.4 -> 17 cm on the synthetic mono case).
            outcome = self._track_local_map(feats, T_pred, allow_fallback=True, count=False)
            T_kf = self._pose_from_keyframe(feats, self._last_kf_id)
            if T_kf is not None and self._pose_is_plausible(T_kf, T_pred):
                alt = self._track_local_map(feats, T_kf, allow_fallback=False, count=False)
                if alt is not None and (outcome is None or len(alt.point_ids) > len(outcome.point_ids)):
                    outcome = alt
            if outcome is not None:
                self._count_local_map(outcome)
        if predicting and outcome is not None and not self._pose_is_plausible(outcome.T_cw, T_pred):
            logger.debug("frame %d: pose jump rejected", frame.stamp_ns)
            outcome = None
        relocalised = False
        if outcome is None and self.state != TrackingState.OK:
            outcome = self._relocalise(feats)
            relocalised = outcome is not None
        if outcome is not None:
            keep_velocity = self.state == TrackingState.OK or not relocalised
            if rolling and keep_velocity:
                feats, outcome = self._refine_rolling_shutter(raw, outcome, dt_s)
            T = outcome.T_cw
            if keep_velocity:
                self._velocity = orthonormalized(T @ invert_pose(self._T_cw_last))
                self._velocity_dt_s = dt_s
                self._velocity_known = True
            else:
                self._velocity = np.eye(4)
                self._velocity_known = False
            self.state = TrackingState.OK
            self._T_cw_last = T
            self._last_good_T_cw = T
            self._lost_frames = 0
            self._frames_since_kf += 1
            self._update_local_keyframes(outcome.point_ids)
            kf = None
            if self._need_keyframe(T, feats, outcome):
                kf = self._insert_keyframe(frame, feats, T, outcome)
            return T, kf, outcome.n_matches, len(outcome.point_ids)
        # Failure: coast on the velocity model for a few frames, then report no pose.
        self._lost_frames += 1
        if self._lost_frames <= cfg.max_recently_lost_frames and self.state != TrackingState.LOST:
            self.state = TrackingState.RECENTLY_LOST
            self._T_cw_last = T_pred
            return T_pred, None, 0, 0
        self.state = TrackingState.LOST
        if self._lost_frames > cfg.new_segment_after_lost_frames:
            T_new = self._lost_timeout(frame, feats)
            if T_new is not None:
                return T_new, self._last_kf_info, 0, 0
        return None, None, 0, 0

    def _relocalisation_candidates(self, feats: FrameFeatures) -> list[int] | None:
        """Keyframes to try, best BoW score first, plus the newest ones not indexed yet; None
        without a vocabulary (relocalise then spreads its candidates over the map)."""
        if self.vocabulary is None or len(feats) == 0:
            return None
        bow = self.vocabulary.transform(feats.desc)
        with self.map.lock:
            ids = sorted(self.map.keyframes, reverse=True)
        with self._db_lock:
            hits = [k for k, _ in self.keyframe_db.query(bow) if k in self.map.keyframes]
            unindexed = [k for k in ids if k not in self.keyframe_db][:5]
        return list(dict.fromkeys(unindexed + hits[: self.cfg.reloc_max_keyframes]))

    def _relocalise(self, feats: FrameFeatures) -> _TrackOutcome | None:
        found = relocalise(self.map, feats, self.K, self.bf, self.cfg, self.inv_sigma_levels,
                           candidates=self._relocalisation_candidates(feats))
        if found is None:
            return None
        T, _ = found
        # Confirm against the local map around the relocalised pose, strictly.
        saved = self._local_kfs
        with self.map.lock:
            pids = self._observed_points_near(T)
        self._local_kfs = self.map.covisible(pids, self.cfg.local_map_keyframes) if len(pids) else saved
        outcome = self._track_local_map(feats, T, allow_fallback=False)
        if outcome is None or len(outcome.point_ids) < self.cfg.reloc_min_inliers:
            self._local_kfs = saved
            return None
        return outcome

    def _observed_points_near(self, T_cw: np.ndarray) -> np.ndarray:
        """Ids of good points that project into the image at ``T_cw`` (all keyframes)."""
        ids = self.map.points_of(list(self.map.keyframes))
        p_w, _, _ = self.map.point_arrays(ids)
        _, vis = self._project(p_w, T_cw)
        return ids[vis]

    def _update_local_keyframes(self, point_ids: np.ndarray) -> None:
        cov = self.map.covisible(point_ids, self.cfg.local_map_keyframes)
        recent = sorted(self.map.keyframes)[-2:]
        self._local_kfs = list(dict.fromkeys(cov + recent))

    # -- keyframes ----------------------------------------------------------------------
    def _need_keyframe(self, T_cw: np.ndarray, feats: FrameFeatures, outcome: _TrackOutcome) -> bool:
        cfg = self.cfg
        if self._frames_since_kf < cfg.keyframe_min_frames:
            return False
        n_tracked = len(outcome.point_ids)
        if n_tracked < cfg.min_inliers:
            return False
        ref = self.map.keyframes.get(self._last_kf_id)
        if ref is None:
            return True
        ref_tracked = self._reference_tracked(ref)
        d = T_cw @ invert_pose(ref.T_cw)
        moved = np.linalg.norm(d[:3, 3]) / self._scale_unit()
        return (self._frames_since_kf >= cfg.keyframe_max_frames
                or n_tracked < self._keyframe_ratio() * ref_tracked
                or self._need_close_points(feats, outcome.kp_idx)
                or rotation_angle_deg(d[:3, :3]) > cfg.keyframe_max_rotation_deg
                or moved > cfg.keyframe_max_translation_m)

    def _keyframe_ratio(self) -> float:
        return self.cfg.keyframe_tracked_ratio

    def _reference_tracked(self, ref: SparseKeyframe) -> int:
        """Points of the reference keyframe seen by enough keyframes (ORB-SLAM's nMinObs)."""
        min_obs = 3 if len(self.map.keyframes) > 2 else 2
        ids = ref.point_ids[ref.point_ids >= 0]
        return int((self.map.n_observations(ids) >= min_obs).sum())

    def _make_keyframe(self, frame: Frame, feats: FrameFeatures, T_cw: np.ndarray) -> SparseKeyframe:
        kf = SparseKeyframe(self.map.new_keyframe_id(), frame.stamp_ns, T_cw.copy(), feats,
                      np.full(len(feats), -1, dtype=np.int64), self.segment_id)
        self.map.add_keyframe(kf)
        return kf

    def _insert_keyframe(self, frame: Frame, feats: FrameFeatures, T_cw: np.ndarray,
                         outcome: _TrackOutcome) -> KeyframeInfo:
        kf = self._make_keyframe(frame, feats, T_cw)
        self.map.add_observations(outcome.point_ids, kf.keyframe_id, outcome.kp_idx)
        self._create_points(kf, frame)
        self.map.cull_points(kf.keyframe_id, self.cfg.point_min_found_ratio, self._min_point_obs())
        self._cap_keyframes(kf.keyframe_id)
        return self._finish_keyframe(kf)

    def _cap_keyframes(self, newest_id: int) -> None:
        """Keep at most ``cfg.max_keyframes``: remove the most redundant keyframe outside the
        local map and the newest BA window, then compact the points nobody sees any more."""
        cap = self.cfg.max_keyframes
        if cap <= 0 or len(self.map.keyframes) <= cap:
            return
        with self.map.lock:
            ids = sorted(self.map.keyframes)
            protected = set(self._local_kfs) | set(ids[-self.cfg.ba_window:]) | {newest_id, self._last_kf_id}
            while len(ids) > cap:
                T_wc = invert_pose(np.stack([self.map.keyframes[i].T_cw for i in ids]))
                nearest = nearest_pose_distance(T_wc)
                nearest[[j for j, i in enumerate(ids) if i in protected]] = np.inf
                j = int(np.argmin(nearest))
                if not np.isfinite(nearest[j]):
                    break  # everything left is in use
                self.map.remove_keyframe(ids.pop(j))
            self.map.compact()

    def _min_point_obs(self) -> int:
        return 2

    def _finish_keyframe(self, kf: SparseKeyframe) -> KeyframeInfo:
        self._last_kf_id = kf.keyframe_id
        self._path_T_cw[kf.keyframe_id] = kf.T_cw.copy()
        self._frames_since_kf = 0
        if kf.keyframe_id not in self._local_kfs:
            self._local_kfs.append(kf.keyframe_id)
        if self.cfg.ba_enabled and len(self.map.keyframes) >= 2:
            if self._ba_thread is not None:
                self._ba_queue.put((self.map, kf.keyframe_id))
            else:
                self._run_local_ba(self.map, kf.keyframe_id)
        if self.vocabulary is not None:
            if self._place_thread is not None:
                self._place_queue.put((self.map, kf.keyframe_id))
            else:  # inline (lockstep): counted with the inline BA as back-end time, not front end
                t_pr = time.perf_counter()
                self._place_recognition(self.map, kf.keyframe_id)
                self._apply_loop_corrections()
                self.ba_time_s += time.perf_counter() - t_pr
        info = self._keyframe_info(kf)
        self._last_kf_info = info
        return info

    def _keyframe_info(self, kf: SparseKeyframe) -> KeyframeInfo:
        active = kf.point_ids >= 0
        depth = np.full(len(kf.point_ids), np.nan, dtype=np.float32)
        if active.any():
            p_w, _, _ = self.map.point_arrays(kf.point_ids[active])
            depth[active] = (p_w @ kf.T_cw[2, :3] + kf.T_cw[2, 3]).astype(np.float32)
        return KeyframeInfo(kf.keyframe_id, kf.stamp_ns, invert_pose(kf.T_cw),
                            kf.feats.uv.astype(np.float32), depth, active)

    # -- local bundle adjustment ----------------------------------------------------------
    def _ba_loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self._ba_queue.get(timeout=0.05)
            except queue.Empty:
                continue
            # Only the newest job matters: drop older ones queued while we were busy.
            skipped = 0
            while True:
                try:
                    newer = self._ba_queue.get_nowait()
                except queue.Empty:
                    break
                skipped += 1
                job = newer
            try:
                self._run_local_ba(*job)
            except Exception:  # a failed refinement must not kill tracking
                logger.exception("local bundle adjustment failed")
            finally:
                for _ in range(skipped + 1):
                    self._ba_queue.task_done()

    def _ba_fixed_count(self) -> int:
        return 1

    def _run_local_ba(self, smap: SparseMap, kf_id: int) -> None:
        t0 = time.perf_counter()
        cfg = self.cfg
        with smap.lock:
            kf = smap.keyframes.get(kf_id)
            if kf is None:  # removed by the keyframe cap while queued
                return
            layout = smap.layout_version
            epoch = smap.pose_epoch
            own = kf.point_ids[kf.point_ids >= 0]
            window = [kf_id] + smap.covisible(own, cfg.ba_window - 1, exclude=kf_id)
            pids = smap.points_of(window)
            counts: dict[int, int] = {}
            for pid in pids.tolist():
                for k in smap.observations[pid]:
                    if k not in window:
                        counts[k] = counts.get(k, 0) + 1
            outside = [k for k, _ in sorted(counts.items(), key=lambda kv: -kv[1])[:3]]
            cams = window + outside
            fixed = np.array([c in outside for c in cams])
            if not fixed.any():
                for c in sorted(window)[: self._ba_fixed_count()]:
                    fixed[cams.index(c)] = True
            if fixed.all():
                return
            cam_index = {c: i for i, c in enumerate(cams)}
            o_cam, o_pt, o_uv, o_depth, o_oct, o_kf = [], [], [], [], [], []
            for j, pid in enumerate(pids.tolist()):
                for k, i in smap.observations[pid].items():
                    ci = cam_index.get(k)
                    if ci is None:
                        continue
                    f = smap.keyframes[k].feats
                    o_cam.append(ci)
                    o_pt.append(j)
                    o_uv.append(f.uv[i])
                    o_depth.append(f.depth_m[i])
                    o_oct.append(f.octave[i])
                    o_kf.append(k)
            T_cw = np.stack([smap.keyframes[c].T_cw for c in cams])
            p_w, _, _ = smap.point_arrays(pids)
        if len(o_cam) < 20:
            return
        prob = BAProblem(T_cw, fixed, p_w, np.array(o_cam), np.array(o_pt), np.array(o_uv),
                         np.array(o_depth, dtype=np.float64), self._inv_sigma(np.array(o_oct)))
        res = local_bundle_adjustment(prob, self.K, self.bf, cfg.ba_huber_px, cfg.ba_max_iterations)
        if not np.isfinite(res.final_cost) or res.final_cost > res.initial_cost:
            return
        free = [c for c, f in zip(cams, fixed) if not f]
        T_new = res.T_cw[~fixed]
        outliers = [(int(pids[p]), k) for p, k, ok in zip(o_pt, o_kf, res.obs_inlier) if not ok]
        moved = smap.commit_refinement(free, T_new, pids, res.points_w, outliers, layout_version=layout,
                                       pose_epoch=epoch)
        if not moved:
            return  # a loop correction came in between: this result is stale
        with self._out_lock:
            if smap is self.map:
                self._pending.append(moved)
            self._refined.extend((k, invert_pose(T)) for k, T in zip(free, T_new))
        self.ba_runs += 1
        self.ba_time_s += time.perf_counter() - t0

    def _apply_ba_corrections(self) -> None:
        """Move the last pose with its keyframe when BA refined that keyframe (keeps velocity)."""
        with self._out_lock:
            pending, self._pending = self._pending, []
        if self._T_cw_last is None:
            return
        for moved in pending:
            if self._last_kf_id in moved:
                old, new = moved[self._last_kf_id]
                self._T_cw_last = orthonormalized(self._T_cw_last @ invert_pose(old) @ new)

    # -- place recognition and loop closing ------------------------------------------------
    def _bump(self, last_loop: tuple[int, int] | None = None, **add: float) -> None:
        with self._stats_lock:
            self.loop_stats = _replace_stats(self.loop_stats, last_loop, **add)

    def _place_loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self._place_queue.get(timeout=0.05)
            except queue.Empty:
                continue
            try:
                if job[1] < 0:
                    self._global_ba(job[0])
                else:
                    self._place_recognition(*job)  # every keyframe: the consistency check wants consecutive ones
            except Exception:  # a failed loop search must not kill tracking
                logger.exception("place recognition failed")
            finally:
                self._place_queue.task_done()

    def _place_recognition(self, smap: SparseMap, kf_id: int) -> None:
        """Index keyframe ``kf_id``; with loop closure, look for a loop and prepare its correction."""
        assert self.vocabulary is not None
        cfg = self.cfg
        with smap.lock:
            kf = smap.keyframes.get(kf_id)
            if kf is None:
                return
            desc = kf.feats.desc
            own = kf.point_ids[kf.point_ids >= 0]
            connected = smap.covisible(own, 10**6, exclude=kf_id)
        bow = self.vocabulary.transform(desc)
        looking = (cfg.loop_closure and self.uses_depth and smap is self.map
                   and kf_id - self._last_loop_query > cfg.loop_cooldown_keyframes)
        candidates: list[tuple[int, float]] = []
        with self._db_lock:
            if looking:
                near = [self.keyframe_db.vector(c) for c in connected[: cfg.local_map_keyframes]]
                scores = [bow_score(bow, v) for v in near if v is not None]
                if scores:
                    skip = set(connected) | set(range(kf_id - cfg.loop_min_keyframe_gap, kf_id + 1))
                    candidates = self.keyframe_db.query(bow, skip, min_score=min(scores),
                                                        max_results=_LOOP_CANDIDATES)
            self.keyframe_db.add(kf_id, bow)
        self._bump(keyframes_indexed=1)
        with self._out_lock:  # not before the last global BA is committed (it would be stale)
            gba_pending = any(c.is_global_ba for c in self._loop_pending)
        if self._gba_followup_at is not None and kf_id >= self._gba_followup_at and not gba_pending:
            # The keyframes made since the loop track against the old map: one more global BA
            # ties them (and the loop) in. Once per loop.
            self._gba_followup_at = None
            self._global_ba(smap, followup=True)
        if not looking:
            return
        with smap.lock:
            grouped = []
            for c, score in candidates:
                ck = smap.keyframes.get(c)
                if ck is None:
                    continue
                group = smap.covisible(ck.point_ids[ck.point_ids >= 0], _LOOP_GROUP, exclude=c)
                grouped.append((c, score, frozenset([c, *group])))
        found = self._loop_detector.update(kf_id, grouped)
        if found is None:
            return
        self._bump(loops_detected=1)
        correction = self._close_loop(smap, kf_id, found.candidate_id, found.group)
        if correction is None:
            self._bump(loops_rejected=1)
            return
        self._loop_detector.reset()
        self._last_loop_query = kf_id
        with self._out_lock:
            self._loop_pending.append(correction)

    def _close_loop(self, smap: SparseMap, kf_id: int, cand_id: int, group: frozenset[int]) -> LoopCorrection | None:
        """Verify the loop ``kf_id`` -> ``cand_id`` and optimise the pose graph; None if it fails."""
        t0 = time.perf_counter()
        cfg = self.cfg
        # Only the old map is the loop's reference: recent keyframes covisible with the candidate
        # (they may already see a few start points) carry the drift the loop is to remove.
        group = frozenset(c for c in group if c <= kf_id - cfg.loop_min_keyframe_gap)
        with smap.lock:
            kf = smap.keyframes.get(kf_id)
            if kf is None or cand_id not in group:
                return None
            pids = smap.points_of(sorted(group))
            p_w, p_desc, _ = smap.point_arrays(pids)
            f = kf.feats
        match = verify_loop(f, self._inv_sigma(f.octave), pids, p_w, p_desc, self.K, self.bf,
                            (self.camera.width, self.camera.height), cfg.loop_min_inliers, cfg.max_descriptor_distance,
                            cfg.ransac_reprojection_px, iterations=cfg.ransac_iterations * 2)
        if match is None:
            return None
        # Snapshot the graph: poses, ordered ids, covisibility from the observations.
        with smap.lock:
            ids = np.array(sorted(smap.keyframes), np.int64)
            T_wc = invert_pose(np.stack([smap.keyframes[int(i)].T_cw for i in ids]))
            obs = [tuple(d) for d in smap.observations if len(d) > 1]
            layout = smap.layout_version
            # The current group (the query's covisible keyframes and newer ones) for loop fusion.
            own = kf.point_ids[kf.point_ids >= 0]
            near = set(smap.covisible(own, _LOOP_GROUP, exclude=kf_id)) - set(group)
            cur_group = {k: smap.keyframes[k].feats for k in ids.tolist()
                         if k != kf_id and (k in near or k > kf_id)}
        index = {int(k): n for n, k in enumerate(ids.tolist())}
        pairs: dict[tuple[int, int], int] = {}
        for o in obs:
            js = sorted(index[k] for k in o if k in index)
            for a in range(len(js)):
                for b in range(a + 1, len(js)):
                    pairs[(js[a], js[b])] = pairs.get((js[a], js[b]), 0) + 1
        ei = list(range(len(ids) - 1))  # spanning tree: consecutive keyframes
        ej = list(range(1, len(ids)))
        for (a, b), w in pairs.items():
            if w >= cfg.loop_covisibility_edge_points and b != a + 1:
                ei.append(a)
                ej.append(b)
        weights = [1.0] * len(ei)
        Z = [invert_pose(T_wc[a]) @ T_wc[b] for a, b in zip(ei, ej)]
        q = index.get(kf_id)
        if q is None:
            return None
        T_wc_q = invert_pose(match.T_cw)
        for c in sorted(group):
            if c in index and c != kf_id:
                ei.append(index[c])
                ej.append(q)
                weights.append(_LOOP_EDGE_WEIGHT)
                Z.append(invert_pose(T_wc[index[c]]) @ T_wc_q)
        fixed = np.zeros(len(ids), bool)
        fixed[0] = True  # the oldest keyframe holds the gauge
        res = optimise_pose_graph(T_wc, np.array(ei), np.array(ej), np.stack(Z), np.array(weights), fixed)
        D = res.T_wc @ invert_pose(T_wc)
        D_cand = D[index[cand_id]] if cand_id in index else np.eye(4)  # the loop group barely moves
        fuse_kf, fuse_kp, fuse_pt = self._loop_fusion(cur_group, index, res.T_wc,
                                                      D_cand @ np.r_[p_w.T, np.ones((1, len(p_w)))], pids, p_desc)
        dt = time.perf_counter() - t0
        self._bump(pose_graph_time_s=dt)
        logger.info("loop %d -> %d: %d inliers, pose graph %d keyframes %d edges in %.2f s, %d fused in %d keyframes",
                    kf_id, cand_id, match.n_inliers, len(ids), len(ei), dt, len(fuse_kf), len(cur_group))
        return LoopCorrection(ids, D, kf_id, cand_id, np.r_[match.kp_idx, fuse_kp], np.r_[match.point_ids, fuse_pt],
                              layout, match.n_inliers, dt,
                              fuse_kf=np.r_[np.full(len(match.kp_idx), kf_id, np.int64), fuse_kf])

    def _loop_fusion(self, cur_group: dict[int, FrameFeatures], index: dict[int, int], T_wc_new: np.ndarray,
                     p_h: np.ndarray, pids: np.ndarray, p_desc: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Matches of the loop group's points (ids [P], corrected homogeneous positions p_h [4, P],
        desc [P, 32]) in the current group's keyframes at their pose-graph poses: (keyframe [K],
        keypoint [K], point id [K]) to fuse at commit. One loop link per keyframe of the seam
        instead of the query's alone (ORB-SLAM's loop fusion), which the global BA then uses."""
        cfg = self.cfg
        out_kf, out_kp, out_pt = [], [], []
        for k, f in cur_group.items():
            T_cw = invert_pose(T_wc_new[index[k]])
            p_c = (T_cw @ p_h)[:3].T
            z = np.where(p_c[:, 2] > 1e-3, p_c[:, 2], 1.0)
            uv = np.column_stack([self.K[0, 0] * p_c[:, 0] / z + self.K[0, 2], self.K[1, 1] * p_c[:, 1] / z + self.K[1, 2]])
            vis = np.flatnonzero((p_c[:, 2] > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < self.camera.width)
                                 & (uv[:, 1] >= 0) & (uv[:, 1] < self.camera.height))
            if len(vis) == 0:
                continue
            pi, ki, _ = match_by_projection(uv[vis], p_desc[vis], f, 3.0, cfg.max_descriptor_distance, 0.9)
            # Depth must agree too: a wrong fusion would tie the seam to a wrong point.
            d = f.depth_m[ki]
            ok = ~np.isfinite(d) | (np.abs(d - p_c[vis[pi], 2]) < 0.05 + 0.03 * p_c[vis[pi], 2])
            out_kf.append(np.full(int(ok.sum()), k, np.int64))
            out_kp.append(ki[ok])
            out_pt.append(pids[vis[pi[ok]]])
        if not out_kf:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(out_kf), np.concatenate(out_kp), np.concatenate(out_pt)

    def _global_ba(self, smap: SparseMap, followup: bool = False) -> None:
        """Bundle-adjust the whole map after a loop correction (loop-closing thread): every keyframe
        but the oldest (the gauge) and every point seen by two keyframes; the result goes to
        ``_loop_pending`` as a correction (D per keyframe plus point positions)."""
        t0 = time.perf_counter()
        cfg = self.cfg
        with smap.lock:
            if smap is not self.map or len(smap.keyframes) < 3:
                return
            epoch, layout = smap.pose_epoch, smap.layout_version
            ids = sorted(smap.keyframes)
            if cfg.loop_global_ba_followup_keyframes > 0 and self._gba_followup_at is None and not followup:
                self._gba_followup_at = ids[-1] + cfg.loop_global_ba_followup_keyframes
            cam_index = {k: i for i, k in enumerate(ids)}
            pids = np.array([p for p in smap.points_of(ids).tolist() if len(smap.observations[p]) >= 2], np.int64)
            per_point = _max_observations_per_point([len(smap.observations[p]) for p in pids.tolist()])
            o_cam, o_pt, o_uv, o_depth, o_oct, o_kf = [], [], [], [], [], []
            for j, pid in enumerate(pids.tolist()):
                seen = sorted(smap.observations[pid].items())
                if len(seen) > per_point:  # evenly spread over the keyframes that see it
                    seen = [seen[int(i)] for i in np.linspace(0, len(seen) - 1, per_point).round()]
                for k, i in seen:
                    f = smap.keyframes[k].feats
                    o_cam.append(cam_index[k])
                    o_pt.append(j)
                    o_uv.append(f.uv[i])
                    o_depth.append(f.depth_m[i])
                    o_oct.append(f.octave[i])
                    o_kf.append(k)
            T_cw = np.stack([smap.keyframes[k].T_cw for k in ids])
            p_w, _, _ = smap.point_arrays(pids)
        if len(o_cam) < 20:
            return
        fixed = np.zeros(len(ids), bool)
        fixed[0] = True
        prob = BAProblem(T_cw, fixed, p_w, np.array(o_cam), np.array(o_pt), np.array(o_uv),
                         np.array(o_depth, dtype=np.float64), self._inv_sigma(np.array(o_oct)))
        res = global_bundle_adjustment(prob, self.K, self.bf, cfg.ba_huber_px, cfg.loop_global_ba_iterations,
                                       cfg.loop_global_ba_budget_s)
        dt = time.perf_counter() - t0
        if not np.isfinite(res.final_cost) or res.final_cost >= res.initial_cost:
            self._bump(global_ba_discarded=1, global_ba_time_s=dt)
            return
        D = invert_pose(res.T_cw) @ T_cw  # T_wc_new T_cw_old: world-frame corrections (snapshot)
        outliers = tuple((int(pids[p]), k) for p, k, ok in zip(o_pt, o_kf, res.obs_inlier) if not ok)
        logger.info("global BA: %d keyframes %d points %d observations, cost %.0f -> %.0f in %.2f s",
                    len(ids), len(pids), len(o_cam), res.initial_cost, res.final_cost, dt)
        with self._out_lock:
            self._loop_pending.append(LoopCorrection(
                np.array(ids, np.int64), D, ids[-1], -1, np.zeros(0, np.int64), np.zeros(0, np.int64), layout,
                0, dt, pids, res.points_w, outliers, epoch, invert_pose(res.T_cw)))
        self._bump(global_ba_time_s=dt)

    @staticmethod
    def _correction_table(smap: SparseMap, c: LoopCorrection) -> tuple[np.ndarray, np.ndarray]:
        """World-frame corrections (ids [M], D [M, 4, 4]) for ``c`` at commit time (map lock held).

        A global BA's poses replace the current ones (local BA results since its snapshot are
        superseded). Keyframes made after the snapshot take the correction of the snapshot keyframe
        they share most points with: after a loop they track against the old map, which a
        correction barely moves, not against the query keyframe.
        """
        ids, D = c.kf_ids, c.D
        if c.T_wc_new is not None:
            cur = np.stack([smap.keyframes[k].T_cw if k in smap.keyframes else invert_pose(T)
                            for k, T in zip(ids.tolist(), c.T_wc_new)])
            D = c.T_wc_new @ cur
        table = {k: n for n, k in enumerate(ids.tolist())}
        extra_ids, extra_D = [], []
        for k, kf in smap.keyframes.items():
            if k in table or k <= c.query_id:
                continue
            counts: dict[int, int] = {}
            for pid in kf.point_ids[kf.point_ids >= 0].tolist():
                for o in smap.observations[pid]:
                    if o in table:
                        counts[o] = counts.get(o, 0) + 1
            if counts:
                extra_ids.append(k)
                extra_D.append(D[table[max(counts, key=counts.__getitem__)]])
        if extra_ids:
            ids = np.concatenate([ids, np.array(extra_ids, np.int64)])
            D = np.concatenate([D, np.stack(extra_D)])
        return ids, D

    def _apply_loop_corrections(self) -> int:
        """Commit prepared loop corrections and global BAs (tracking thread, under the map lock):
        keyframes and points move, the loop's duplicate points fuse, the last pose moves with its
        keyframe; each committed loop queues a global BA. Returns how many were committed."""
        with self._out_lock:
            pending, self._loop_pending = self._loop_pending, []
        committed = 0
        for c in pending:
            smap = self.map
            with smap.lock:
                if c.pose_epoch is not None and c.pose_epoch != smap.pose_epoch:
                    self._bump(global_ba_discarded=1)  # another correction came in between: stale
                    continue
                kf_ids, D = self._correction_table(smap, c)
                q = int(np.flatnonzero(c.kf_ids == c.query_id)[0])
                moved = smap.apply_loop_correction(kf_ids, D, c.D[q], newer_than=c.query_id)
                if c.point_ids is not None:  # global BA: its point positions, then drop its outliers
                    smap.commit_refinement([], np.zeros((0, 4, 4)), c.point_ids, c.points_w, list(c.outliers),
                                           layout_version=c.layout_version)
                olds = smap.renumber(c.fuse_points, c.layout_version)
                fuse_kf = c.fuse_kf if c.fuse_kf is not None else np.full(len(c.fuse_kp), c.query_id, np.int64)
                if olds is not None:
                    for k, kp, old in zip(fuse_kf.tolist(), c.fuse_kp.tolist(), olds.tolist()):
                        fkf = smap.keyframes.get(k)
                        if fkf is None or old < 0 or not smap.good(np.array([old]))[0]:
                            continue
                        cur = int(fkf.point_ids[kp])
                        if cur >= 0 and cur != old:
                            smap.merge_point(cur, old)
                        elif cur < 0 and k not in smap.observations[old]:
                            smap.add_observations(np.array([old]), k, np.array([kp]))
                refined = [(k, invert_pose(new)) for k, (_, new) in sorted(moved.items())]
            for T_attr in ("_T_cw_last", "_last_good_T_cw"):
                T = getattr(self, T_attr)
                if T is not None and self._last_kf_id in moved:
                    old, new = moved[self._last_kf_id]
                    setattr(self, T_attr, orthonormalized(T @ invert_pose(old) @ new))
            # T_wc_new T_cw_path: the path's frames move with their keyframe, BA refinements included.
            D_wc = {k: invert_pose(new) @ self._path_T_cw.get(k, old) for k, (old, new) in moved.items()}
            self._path_T_cw.update((k, new.copy()) for k, (_, new) in moved.items())
            with smap.lock:
                self._path_T_cw = {k: T for k, T in self._path_T_cw.items() if k in smap.keyframes}
            with self._out_lock:
                self._loop_refined.extend(refined)
                self._loop_done.append(D_wc)
            committed += 1
            if c.is_global_ba:
                self._bump(global_ba_runs=1)
                continue
            self._bump(loops_accepted=1, last_loop=(c.query_id, c.candidate_id))
            if self.cfg.loop_global_ba:
                if self._place_thread is not None:
                    self._place_queue.put((smap, -1))
                else:  # inline (lockstep)
                    self._global_ba(smap)
                    committed += self._apply_loop_corrections()
        return committed


def _max_observations_per_point(counts: list[int]) -> int:
    """Observations kept per point in the global BA so that its observation pairs (the sum of
    n_obs^2, ~600 B each in the reduced system) stay under ``_GLOBAL_BA_MAX_PAIRS``: a place seen
    again and again (a robot circling a room) gives points with a hundred observations, and the
    unbounded system took the tracker to 2 GB resident on bench_load's looped sequence."""
    c = np.asarray(counts, dtype=np.int64)
    if len(c) == 0 or int((c * c).sum()) <= _GLOBAL_BA_MAX_PAIRS:
        return int(c.max(initial=2))
    m = int(c.max())
    while m > 2 and int((np.minimum(c, m) ** 2).sum()) > _GLOBAL_BA_MAX_PAIRS:
        m -= 1
    return m


def _replace_stats(st: LoopStats, last_loop: tuple[int, int] | None = None, **add: float) -> LoopStats:
    """``st`` with the counters in ``add`` added and ``last_loop`` set when given."""
    vals = {k: getattr(st, k) + v for k, v in add.items()}
    if last_loop is not None:
        vals["last_loop"] = last_loop
    return replace(st, **vals)
