"""Place recognition and loop search on map snapshots (run by the tracker's back-end).

Each new keyframe gets a bag-of-words vector in the keyframe database (the front-end keeps its
own copy for relocalisation). With loop closure (RGB-D), it is also checked for a loop:
candidates outside its covisible set and older than ``loop_min_keyframe_gap`` keyframes, the
consistency check over consecutive keyframes (``LoopDetector``), PnP verification against the
candidate group, then an SE(3) pose graph over every keyframe of the snapshot and loop fusion.
The result is a ``LoopCorrection`` that the front-end commits to its map.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, fields

import numpy as np

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.backend.bundle_adjustment import _obs_pairs
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.core.tracking.features.features import FrameFeatures, match_by_projection
from memgs_ros.core.tracking.features.vocabulary import BowVector, KeyframeDatabase, Vocabulary, bow_score
from memgs_ros.core.tracking.frontend.map_snapshot import MapSnapshot
from memgs_ros.core.tracking.loop_closing.loops import LoopCorrection, LoopDetector, optimise_pose_graph, verify_loop

logger = logging.getLogger(__name__)

_LOOP_CANDIDATES = 3  # best BoW candidates per query that enter the consistency check
_LOOP_GROUP = 10  # covisible keyframes forming a candidate's group
_LOOP_EDGE_WEIGHT = 10.0  # loop edges against the identity-weighted odometry edges


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

    def plus(self, other: LoopStats) -> LoopStats:
        """Counters added; ``last_loop`` from ``other`` when it has one."""
        vals = {f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self) if f.name != "last_loop"}
        return LoopStats(**vals, last_loop=other.last_loop if other.last_loop is not None else self.last_loop)


@dataclass(frozen=True, eq=False)
class PlaceOutcome:
    """What place recognition made of keyframe ``kf_id``: its BoW vector (None when the keyframe
    was gone from the snapshot), a loop correction to commit, and the counters to add."""

    kf_id: int
    bow: BowVector | None
    loop: LoopCorrection | None
    stats: LoopStats


class PlaceRecognition:
    """The keyframe database, the consistency detector and the loop cooldown of one back-end.

    K: [3, 3]; bf: fx times the virtual baseline; image_size: (width, height); inv_sigma_levels:
    [L] 1 / scale^level. ``loop_closure``: look for loops (RGB-D), else only index keyframes.
    """

    def __init__(self, cfg: TrackerConfig, vocabulary: Vocabulary, K: np.ndarray, bf: float,
                 image_size: tuple[int, int], inv_sigma_levels: np.ndarray, loop_closure: bool) -> None:
        self.cfg, self.vocabulary, self.K, self.bf = cfg, vocabulary, K, bf
        self.image_size, self.inv_sigma_levels, self.loop_closure = image_size, inv_sigma_levels, loop_closure
        self.keyframe_db = KeyframeDatabase()
        self._detector = LoopDetector(cfg.loop_consistency)
        self._last_loop_query = -(10**9)
        self._forgotten: set[int] = set()

    def forget(self, kf_ids: tuple[int, ...]) -> None:
        """Culled keyframes: out of the database, and not indexed should their request still come."""
        self._forgotten.update(kf_ids)
        for k in kf_ids:
            self.keyframe_db.remove(k)

    def load(self, vectors: list[tuple[int, BowVector]]) -> None:
        """A loaded map's keyframes, indexed: loops close onto the earlier session too."""
        for k, bow in vectors:
            self.keyframe_db.add(k, bow)

    def process(self, snap: MapSnapshot, kf_id: int) -> PlaceOutcome:
        """Index keyframe ``kf_id``; with loop closure, look for a loop and prepare its correction."""
        cfg = self.cfg
        if kf_id not in snap or kf_id in self._forgotten:
            return PlaceOutcome(kf_id, None, None, LoopStats())
        own = snap.kf_points(kf_id)
        connected = snap.covisible(own[own >= 0], 10**6, exclude=(kf_id,))
        bow = self.vocabulary.transform(snap.kf_feats(kf_id).desc)
        looking = self.loop_closure and kf_id - self._last_loop_query > cfg.loop_cooldown_keyframes
        candidates: list[tuple[int, float]] = []
        if looking:
            near = [self.keyframe_db.vector(c) for c in connected[: cfg.local_map_keyframes]]
            scores = [bow_score(bow, v) for v in near if v is not None]
            if scores:
                skip = set(connected) | set(range(kf_id - cfg.loop_min_keyframe_gap, kf_id + 1))
                candidates = self.keyframe_db.query(bow, skip, min_score=min(scores), max_results=_LOOP_CANDIDATES)
        self.keyframe_db.add(kf_id, bow)
        indexed = LoopStats(keyframes_indexed=1)
        if not looking:
            return PlaceOutcome(kf_id, bow, None, indexed)
        grouped = []
        for c, score in candidates:
            if c in snap:
                cp = snap.kf_points(c)
                grouped.append((c, score, frozenset([c, *snap.covisible(cp[cp >= 0], _LOOP_GROUP, exclude=(c,))])))
        found = self._detector.update(kf_id, grouped)
        if found is None:
            return PlaceOutcome(kf_id, bow, None, indexed)
        correction = self._close_loop(snap, kf_id, found.candidate_id, found.group)
        if correction is None:
            return PlaceOutcome(kf_id, bow, None, indexed.plus(LoopStats(loops_detected=1, loops_rejected=1)))
        self._detector.reset()
        self._last_loop_query = kf_id
        stats = LoopStats(keyframes_indexed=1, loops_detected=1, pose_graph_time_s=correction.time_s)
        return PlaceOutcome(kf_id, bow, correction, stats)

    def _inv_sigma(self, octave: np.ndarray) -> np.ndarray:
        return self.inv_sigma_levels[np.clip(octave, 0, len(self.inv_sigma_levels) - 1)]

    def _close_loop(self, snap: MapSnapshot, kf_id: int, cand_id: int, group: frozenset[int]) -> LoopCorrection | None:
        """Verify the loop ``kf_id`` -> ``cand_id`` and optimise the pose graph; None if it fails."""
        t0 = time.perf_counter()
        cfg = self.cfg
        # Only the old map is the loop's reference: recent keyframes covisible with the candidate
        # (they may already see a few start points) carry the drift the loop is to remove.
        group = frozenset(c for c in group if c <= kf_id - cfg.loop_min_keyframe_gap)
        if cand_id not in group:
            return None
        pids = snap.points_of(sorted(group))
        p_w, p_desc, _ = snap.point_arrays(pids)
        f = snap.kf_feats(kf_id)
        match = verify_loop(f, self._inv_sigma(f.octave), pids, p_w, p_desc, self.K, self.bf, self.image_size,
                            cfg.loop_min_inliers, cfg.max_descriptor_distance, cfg.ransac_reprojection_px,
                            iterations=cfg.ransac_iterations * 2)
        if match is None:
            return None
        ids = snap.kf_ids
        T_wc = invert_pose(snap.T_cw)
        # The current group (the query's covisible keyframes and newer ones) for loop fusion.
        own = snap.kf_points(kf_id)
        near = set(snap.covisible(own[own >= 0], _LOOP_GROUP, exclude=(kf_id,))) - set(group)
        cur_group = {k: snap.kf_feats(k) for k in ids.tolist() if k != kf_id and (k in near or k > kf_id)}
        index = {int(k): n for n, k in enumerate(ids.tolist())}
        ei, ej = self._graph_edges(snap)
        weights = [1.0] * len(ei)
        Z = [invert_pose(T_wc[a]) @ T_wc[b] for a, b in zip(ei, ej)]
        q = index[kf_id]
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
        logger.info("loop %d -> %d: %d inliers, pose graph %d keyframes %d edges in %.2f s, %d fused in %d keyframes",
                    kf_id, cand_id, match.n_inliers, len(ids), len(ei), dt, len(fuse_kf), len(cur_group))
        return LoopCorrection(ids.copy(), D, kf_id, cand_id, np.r_[match.kp_idx, fuse_kp],
                              np.r_[match.point_ids, fuse_pt], snap.layout_version, match.n_inliers, dt,
                              fuse_kf=np.r_[np.full(len(match.kp_idx), kf_id, np.int64), fuse_kf])

    def _graph_edges(self, snap: MapSnapshot) -> tuple[list[int], list[int]]:
        """Pose-graph edges (keyframe positions): consecutive keyframes (a spanning tree), plus pairs
        sharing at least ``loop_covisibility_edge_points`` points."""
        n = len(snap)
        ei, ej = list(range(n - 1)), list(range(1, n))
        table = snap.observations
        point_rank = np.unique(table.point, return_inverse=True)[1]
        o1, o2 = _obs_pairs(point_rank, int(point_rank.max(initial=-1)) + 1)
        a, b = table.kf_index[o1], table.kf_index[o2]
        keep = a < b
        pair, count = np.unique(a[keep] * n + b[keep], return_counts=True)
        strong = pair[(count >= self.cfg.loop_covisibility_edge_points) & (pair % n != pair // n + 1)]
        return ei + (strong // n).tolist(), ej + (strong % n).tolist()

    def _loop_fusion(self, cur_group: dict[int, FrameFeatures], index: dict[int, int], T_wc_new: np.ndarray,
                     p_h: np.ndarray, pids: np.ndarray, p_desc: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Matches of the loop group's points (ids [P], corrected homogeneous positions p_h [4, P],
        desc [P, 32]) in the current group's keyframes at their pose-graph poses: (keyframe [K],
        keypoint [K], point id [K]) to fuse at commit. One loop link per keyframe of the seam
        instead of the query's alone (ORB-SLAM's loop fusion), which the global BA then uses."""
        K, (width, height) = self.K, self.image_size
        out_kf, out_kp, out_pt = [], [], []
        for k, f in cur_group.items():
            T_cw = invert_pose(T_wc_new[index[k]])
            p_c = (T_cw @ p_h)[:3].T
            z = np.where(p_c[:, 2] > 1e-3, p_c[:, 2], 1.0)
            uv = np.column_stack([K[0, 0] * p_c[:, 0] / z + K[0, 2], K[1, 1] * p_c[:, 1] / z + K[1, 2]])
            vis = np.flatnonzero((p_c[:, 2] > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < width)
                                 & (uv[:, 1] >= 0) & (uv[:, 1] < height))
            if len(vis) == 0:
                continue
            pi, ki, _ = match_by_projection(uv[vis], p_desc[vis], f, 3.0, self.cfg.max_descriptor_distance, 0.9)
            # Depth must agree too: a wrong fusion would tie the seam to a wrong point.
            d = f.depth_m[ki]
            ok = ~np.isfinite(d) | (np.abs(d - p_c[vis[pi], 2]) < 0.05 + 0.03 * p_c[vis[pi], 2])
            out_kf.append(np.full(int(ok.sum()), k, np.int64))
            out_kp.append(ki[ok])
            out_pt.append(pids[vis[pi[ok]]])
        if not out_kf:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(out_kf), np.concatenate(out_kp), np.concatenate(out_pt)


__all__ = ["LoopStats", "PlaceOutcome", "PlaceRecognition"]
