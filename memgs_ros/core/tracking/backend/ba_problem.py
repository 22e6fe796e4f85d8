"""Bundle adjustment problems from a map snapshot: one builder for local, global and two-view BA.

``build_problem`` gathers every observation of the chosen points by the chosen keyframes (at most
``max_obs_per_point`` per point, evenly spread over its keyframes) into a ``BAProblem``;
``local_problem`` picks ORB-SLAM's window (the new keyframe, its covisible keyframes, fixed
keyframes outside that see the same points) and ``global_problem`` the whole map.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from memgs_ros.core.tracking.backend.bundle_adjustment import BAProblem
from memgs_ros.core.tracking.frontend.map_snapshot import MapSnapshot

_MIN_OBSERVATIONS = 20  # fewer: nothing worth adjusting
_OUTSIDE_FIXED = 3  # keyframes outside the local window held fixed (they see its points)
_GLOBAL_BA_MAX_PAIRS = 250_000  # observation pairs of one global BA (~150 MB of blocks and indices)


@dataclass(frozen=True, eq=False)
class SnapshotProblem:
    """A BA problem and what maps it back to the map: cams [C] keyframe id per camera, point_ids
    [P] per point, obs_kf [O] keyframe id per observation (for outliers); taken at
    ``layout_version`` / ``pose_epoch``."""

    problem: BAProblem
    cams: tuple[int, ...]
    point_ids: np.ndarray
    obs_kf: np.ndarray
    layout_version: int
    pose_epoch: int

    def outliers(self, inlier: np.ndarray) -> tuple[tuple[int, int], ...]:
        """(point id, keyframe id) of the observations not in ``inlier`` [O]."""
        bad = np.flatnonzero(~inlier)
        return tuple(zip(self.point_ids[self.problem.obs_point[bad]].tolist(), self.obs_kf[bad].tolist()))


def build_problem(snap: MapSnapshot, cams: Sequence[int], fixed: np.ndarray, point_ids: np.ndarray,
                  inv_sigma_levels: np.ndarray, max_obs_per_point: int = 0) -> SnapshotProblem:
    """Observations of ``point_ids`` [P] by the keyframes ``cams`` [C] (``fixed`` [C] held constant),
    point by point, each point's by keyframe id; 0 = no cap per point."""
    table = snap.observations
    rows = table.rows_of(point_ids)
    cam_of = np.full(len(snap), -1, np.int64)
    cam_of[[snap.position(c) for c in cams]] = np.arange(len(cams))
    j = np.repeat(np.arange(len(point_ids)), snap.n_observations(point_ids))
    keep = cam_of[table.kf_index[rows]] >= 0
    rows, j = rows[keep], j[keep]
    if max_obs_per_point > 0:
        rows, j = _spread(rows, j, max_obs_per_point)
    kf_index, kp = table.kf_index[rows], table.kp[rows]
    uv, depth, octave = snap.keypoints
    at = snap.kf_offset[kf_index] + kp
    levels = np.clip(octave[at], 0, len(inv_sigma_levels) - 1)
    prob = BAProblem(np.stack([snap.kf_T_cw(c) for c in cams]), np.asarray(fixed, bool),
                     snap.points_w[point_ids].copy(), cam_of[kf_index], j, uv[at], depth[at],
                     inv_sigma_levels[levels])
    return SnapshotProblem(prob, tuple(cams), np.asarray(point_ids, np.int64), snap.kf_ids[kf_index],
                           snap.layout_version, snap.pose_epoch)


def local_problem(snap: MapSnapshot, kf_id: int, window: int, n_fixed: int,
                  inv_sigma_levels: np.ndarray) -> SnapshotProblem | None:
    """Local BA around keyframe ``kf_id``: it and its ``window - 1`` most covisible keyframes are
    free, up to three keyframes outside that see their points are fixed (else the ``n_fixed``
    oldest of the window: 2 pin a monocular map's scale too). None when there is nothing to do."""
    if kf_id not in snap:
        return None  # removed by the keyframe cap before its turn
    own = snap.kf_points(kf_id)
    cams = [kf_id] + snap.covisible(own[own >= 0], window - 1, exclude=(kf_id,))
    pids = snap.points_of(cams)
    outside = snap.covisible(pids, _OUTSIDE_FIXED, exclude=cams)
    fixed = np.r_[np.zeros(len(cams), bool), np.ones(len(outside), bool)]
    if not fixed.any():
        for c in sorted(cams)[:n_fixed]:
            fixed[cams.index(c)] = True
    if fixed.all():
        return None
    sp = build_problem(snap, cams + outside, fixed, pids, inv_sigma_levels)
    return sp if len(sp.problem.obs_cam) >= _MIN_OBSERVATIONS else None


def global_problem(snap: MapSnapshot, inv_sigma_levels: np.ndarray) -> SnapshotProblem | None:
    """Global BA: every keyframe but the oldest (the gauge), every point seen by two keyframes,
    at most ``_max_observations_per_point`` observations each. None for a map too small."""
    if len(snap) < 3:
        return None
    ids = snap.kf_ids.tolist()
    pids = snap.points_of(ids)
    n_obs = snap.n_observations(pids)
    pids, n_obs = pids[n_obs >= 2], n_obs[n_obs >= 2]
    fixed = np.zeros(len(ids), bool)
    fixed[0] = True
    sp = build_problem(snap, ids, fixed, pids, inv_sigma_levels, _max_observations_per_point(n_obs.tolist()))
    return sp if len(sp.problem.obs_cam) >= _MIN_OBSERVATIONS else None


def _spread(rows: np.ndarray, j: np.ndarray, cap: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep at most ``cap`` rows per point (rows grouped by point j), evenly spread over the group."""
    starts = np.flatnonzero(np.r_[True, j[1:] != j[:-1]]) if len(j) else np.zeros(0, np.int64)
    sizes = np.diff(np.r_[starts, len(j)])
    keep = np.ones(len(j), bool)
    for s, n in zip(starts[sizes > cap].tolist(), sizes[sizes > cap].tolist()):
        keep[s:s + n] = False
        keep[s + np.linspace(0, n - 1, cap).round().astype(np.int64)] = True
    return rows[keep], j[keep]


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


__all__ = ["SnapshotProblem", "build_problem", "global_problem", "local_problem"]
