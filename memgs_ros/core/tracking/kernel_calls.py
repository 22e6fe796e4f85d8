"""The tracking kernels' entry points (bodies: ``_compiled``): each fixes the one array layout its
kernel is compiled for and passes plain scalars, so that no call compiles a second signature.
The numpy twins are the reference (named in each docstring); ``warm_up`` compiles or loads them all.
"""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry.view import load_kernels as load_view_kernels
from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.core.tracking._compiled import _count_seen, _match, _optimize, _track_pass, _unroll, _words
from memgs_ros.core.tracking.features import orb

__all__ = ["View", "count_seen_kernel", "match_by_projection_kernel", "numba_available", "optimize_pose_kernel",
           "track_pass_kernel", "unroll_kernel", "warm_up", "words_kernel"]


def _arg(a: np.ndarray, dtype: type) -> np.ndarray:
    """The one array layout the kernels are compiled for: C-contiguous, writable, ``dtype``. numba
    compiles a signature per layout, and a read-only array (a view a caller kept read-only) made a
    live run's first frame compile a second one for 1.7 s."""
    out: np.ndarray = np.ascontiguousarray(a, dtype)
    return out if out.flags.writeable else out.copy()


def match_by_projection_kernel(proj_uv: np.ndarray, radius: np.ndarray, point_desc: np.ndarray,
                               kp_uv: np.ndarray, kp_desc: np.ndarray, available: np.ndarray,
                               max_distance: int, ratio: float, max_candidates: int, cell_px: float,
                               width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compiled ``_match_by_projection``. proj_uv: [P, 2] float64; radius: [P] float64;
    point_desc: [P, 32] uint8; kp_uv: [M, 2] float64; kp_desc: [M, 32] uint8; available: [M] bool;
    cell_px: grid cell size; width/height: the image the keypoints lie in (cells outside are clamped).
    Returns (point_index [K], keypoint_index [K], hamming [K]) int64, sorted by keypoint index."""
    return _match(_arg(proj_uv, np.float64), _arg(radius, np.float64), _arg(point_desc, np.uint8),
                  _arg(kp_uv, np.float64), _arg(kp_desc, np.uint8), _arg(available, np.bool_),
                  int(max_distance), float(ratio), int(max_candidates), float(cell_px), int(width), int(height))


def optimize_pose_kernel(T_cw: np.ndarray, p_w: np.ndarray, obs_uvr: np.ndarray, has_depth: np.ndarray,
                         w2: np.ndarray, K: np.ndarray, bf: float, th_mono: float, th_stereo: float,
                         rounds: int, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Compiled core of ``_optimize_pose``. T_cw: [4, 4]; p_w: [N, 3]; obs_uvr: [N, 3] (u, v, u - bf/z);
    has_depth: [N] bool; w2: [N] squared 1/sigma. Returns (T_cw [4, 4] not re-orthonormalised, inlier [N])."""
    return _optimize(_arg(T_cw, np.float64), _arg(p_w, np.float64), _arg(obs_uvr, np.float64),
                     _arg(has_depth, np.bool_), _arg(w2, np.float64), float(K[0, 0]), float(K[1, 1]),
                     float(K[0, 2]), float(K[1, 2]), float(bf), float(th_mono), float(th_stereo),
                     int(rounds), int(iterations))


# A pinhole view for the kernels: (fx, fy, cx, cy, width, height, least depth in view).
View = tuple[float, float, float, float, float, float, float]


def track_pass_kernel(pos: np.ndarray, desc: np.ndarray, octave: np.ndarray, pids: np.ndarray,
                      T_init: np.ndarray, view: View, radius_px: float, inv_sigma_levels: np.ndarray,
                      kp_uv: np.ndarray, kp_desc: np.ndarray, kp_obs: np.ndarray, kp_has_depth: np.ndarray,
                      kp_w2: np.ndarray, max_distance: int, ratio: float, max_candidates: int, cell_px: float,
                      bf: float, th_mono: float, th_stereo: float, rounds: int, iterations: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One projection pass over the local map in one call; twin of ``LocalMapMatcher`` projecting,
    ``match_by_projection`` and ``optimize_pose`` in turn (``_match_and_optimise_reference``).

    The points ``pids`` [P] of the map's store (pos [N, 3], desc [N, 32], octave [N], read in
    place) are projected at ``T_init`` into ``view``; those in view are matched to the keypoints
    (kp_uv [M, 2], kp_desc [M, 32]) within ``radius_px / inv_sigma_levels[octave]``; the pose is
    then optimised on the matches with the keypoints' observations (kp_obs [M, 3] u, v, u - bf/z;
    kp_has_depth [M]; kp_w2 [M] squared 1/sigma). Returns (T_cw [4, 4] not re-orthonormalised,
    pi [K] indices into pids, ki [K] keypoints, inlier [K]); T_init and no inliers below 4 matches.
    """
    return _track_pass(_arg(pos, np.float64), _arg(desc, np.uint8), _arg(octave, np.int64), _arg(pids, np.int64),
                       _arg(T_init, np.float64), tuple(float(x) for x in view), float(radius_px),
                       _arg(inv_sigma_levels, np.float64), _arg(kp_uv, np.float64), _arg(kp_desc, np.uint8),
                       _arg(kp_obs, np.float64), _arg(kp_has_depth, np.bool_), _arg(kp_w2, np.float64),
                       int(max_distance), float(ratio), int(max_candidates), float(cell_px), float(bf),
                       float(th_mono), float(th_stereo), int(rounds), int(iterations))


def count_seen_kernel(pos: np.ndarray, pids: np.ndarray, T_cw: np.ndarray, view: View, found: np.ndarray,
                      n_visible: np.ndarray, n_found: np.ndarray) -> None:
    """The visible / found statistics in place: n_visible [N] of the points ``pids`` [P] in view at
    T_cw, and n_found [N] of ``found`` [K] (point ids), each plus one."""
    if n_visible.dtype != np.int64 or n_found.dtype != np.int64 or not (
            n_visible.flags.c_contiguous and n_found.flags.c_contiguous):
        raise TypeError("the counters must be contiguous int64 arrays (they are updated in place)")
    _count_seen(_arg(pos, np.float64), _arg(pids, np.int64), _arg(T_cw, np.float64), tuple(float(x) for x in view),
                _arg(found, np.int64), n_visible, n_found)


def unroll_kernel(uv_raw: np.ndarray, uv: np.ndarray, K: np.ndarray, omega_c: np.ndarray, readout_s: float,
                  height: int) -> np.ndarray:
    """Compiled core of ``features.unroll_rolling_shutter``: corrected uv [M, 2] from uv_raw [M, 2]
    (float32, rows give the exposure time) and uv [M, 2]."""
    return _unroll(_arg(uv_raw, np.float32), _arg(uv, np.float64), _arg(K, np.float64), _arg(omega_c, np.float64),
                   float(readout_s), int(height))


def words_kernel(desc: np.ndarray, centres: np.ndarray, branching: int, depth: int) -> np.ndarray:
    """Compiled ``Vocabulary._words_reference``: word ids [M] of descriptors [M, 32] uint8 in the
    tree of ``centres`` [N, 32] uint8 (its levels one after another)."""
    return _words(_arg(desc, np.uint8).view(np.uint64), _arg(centres, np.uint8).view(np.uint64), int(branching),
                  int(depth))


def warm_up() -> None:
    """Compile (or load from the disk cache) the tracking kernels, and ORB's (``orb.warm_up``), on
    tiny inputs, so that the first tracked frame does not pay for it (~20 s of compilation on first
    use, ~0.3 s from the cache)."""
    if not numba_available():
        return
    orb.warm_up()
    uv = np.array([[10.0, 10.0], [20.0, 20.0]])
    desc = np.zeros((2, 32), np.uint8)
    match_by_projection_kernel(uv, np.full(2, 5.0), desc, uv, desc, np.ones(2, bool), 80, 0.85, 2, 16.0, 32, 32)
    p_w = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0], [1.0, 1.0, 3.0]])
    obs = np.column_stack([p_w[:, :2] / p_w[:, 2:] * 500.0 + 320.0, np.zeros(4)])
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 320.0], [0.0, 0.0, 1.0]])
    optimize_pose_kernel(np.eye(4), p_w, obs, np.zeros(4, bool), np.ones(4), K, 40.0, 5.991, 7.815, 1, 1)
    view = (500.0, 500.0, 320.0, 320.0, 640.0, 640.0, 0.05)
    pids = np.arange(4)
    desc4 = np.zeros((4, 32), np.uint8)
    track_pass_kernel(p_w, desc4, np.zeros(4, np.int64), pids, np.eye(4), view, 5.0, np.ones(2), obs[:, :2], desc4,
                      obs, np.zeros(4, bool), np.ones(4), 80, 0.85, 4, 16.0, 40.0, 5.991, 7.815, 1, 1)
    count_seen_kernel(p_w, pids, np.eye(4), view, pids, np.zeros(4, np.int64), np.zeros(4, np.int64))
    unroll_kernel(obs[:, :2].astype(np.float32), obs[:, :2], K, np.ones(3), 0.02, 640)
    load_view_kernels()  # the frame's depth, both encodings
    words_kernel(desc, np.zeros((6, 32), np.uint8), 2, 2)  # place recognition, on the back-end
