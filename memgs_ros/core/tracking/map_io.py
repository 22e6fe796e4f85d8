"""The tracker's map as a file: keyframes, map points and the place-recognition vectors, saved
from one session and loaded into the next (the tracker's part of a map bundle,
``core/map_io/bundle.py``).

What is kept: every keyframe (id, stamp, T_cw, segment, its ORB features: raw and undistorted
keypoints, octaves, descriptors, depth at the keypoints, and the map point of each keypoint),
the good map points (position, descriptor, octave, visible / found counts, creating keyframe;
renumbered 0..P-1) and each keyframe's bag-of-words vector. Observations and covisibility are
the keyframes' point ids read the other way, so they are rebuilt on load rather than stored.

A NumPy ``.npz`` (``allow_pickle=False``: nothing in it executes) with a JSON header: format
version, camera, tracker mode, depth scale, keyframe and point counts. Written atomically.

``export_map`` copies on the tracking thread (milliseconds: arrays, no features recomputed), so
the file can be written on another thread while tracking goes on.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.runtime.npz_file import read_npz, write_npz
from memgs_ros.core.tracking.features.features import FrameFeatures
from memgs_ros.core.tracking.features.vocabulary import BowVector, KeyframeDatabase
from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap
from memgs_ros.errors import DataError

__all__ = ["TRACKER_MAP_VERSION", "TrackerMap", "export_map", "read_tracker_map", "restore_map", "write_tracker_map"]

TRACKER_MAP_VERSION = 1
_FEATURE_ARRAYS = ("uv_raw", "uv", "octave", "desc", "depth_m")
_POINT_ARRAYS = ("pos", "desc", "octave", "n_visible", "n_found", "first_kf")


@dataclass(frozen=True, eq=False)
class TrackerMap:
    """A tracker's map, detached from any tracker. ``header``: version, camera, mode, counts;
    ``arrays``: the keyframes' (``kf_*``, features back to back at ``kf_offsets``), the points'
    (``pt_*``) and the BoW vectors' (``bow_*``, words back to back at ``bow_offsets``)."""

    header: dict[str, Any]
    arrays: dict[str, np.ndarray]

    @property
    def camera(self) -> PinholeCamera:
        return PinholeCamera.from_dict(self.header["camera"])

    @property
    def n_keyframes(self) -> int:
        return int(self.header["keyframes"])


def export_map(smap: SparseMap, keyframe_db: KeyframeDatabase, camera: PinholeCamera, mode: str,
               segment_id: int, extra: dict[str, Any] | None = None) -> TrackerMap:
    """Copy ``smap`` (good points only, renumbered) and the BoW vectors of its keyframes."""
    kfs = [smap.keyframes[k] for k in sorted(smap.keyframes)]
    pts, good = smap.export_points()
    new_id = np.full(len(good), -1, np.int64)
    new_id[good] = np.arange(int(good.sum()))
    a: dict[str, np.ndarray] = {
        "kf_ids": np.array([k.keyframe_id for k in kfs], np.int64),
        "kf_stamps": np.array([k.stamp_ns for k in kfs], np.int64),
        "kf_T_cw": np.stack([k.T_cw for k in kfs]) if kfs else np.zeros((0, 4, 4)),
        "kf_segment": np.array([k.segment_id for k in kfs], np.int64),
        "kf_offsets": np.r_[0, np.cumsum([len(k.point_ids) for k in kfs])].astype(np.int64),
    }
    for name in _FEATURE_ARRAYS:
        parts = [getattr(k.feats, name) for k in kfs]
        a[f"kf_{name}"] = np.concatenate(parts) if parts else np.zeros(0)
    pid = np.concatenate([k.point_ids for k in kfs]) if kfs else np.zeros(0, np.int64)
    a["kf_point_ids"] = np.where(pid >= 0, new_id[np.maximum(pid, 0)], -1) if len(new_id) else np.full_like(pid, -1)
    for name, arr in zip(_POINT_ARRAYS, pts):
        a[f"pt_{name}"] = arr[good]
    vectors = [(k.keyframe_id, v) for k in kfs if (v := keyframe_db.vector(k.keyframe_id)) is not None]
    a["bow_kf"] = np.array([k for k, _ in vectors], np.int64)
    a["bow_offsets"] = np.r_[0, np.cumsum([len(v) for _, v in vectors])].astype(np.int64)
    a["bow_words"] = np.concatenate([v.words for _, v in vectors]) if vectors else np.zeros(0, np.int64)
    a["bow_weights"] = np.concatenate([v.weights for _, v in vectors]) if vectors else np.zeros(0)
    header = {"format": TRACKER_MAP_VERSION, "camera": camera.as_dict(), "mode": mode,
              "segment_id": int(segment_id), "next_keyframe_id": int(smap.next_keyframe_id),
              "keyframes": len(kfs), "points": int(good.sum()), **(extra or {})}
    return TrackerMap(header, a)


def write_tracker_map(m: TrackerMap, path: str | os.PathLike[str]) -> Path:
    """Write ``m`` to ``path`` atomically; returns the path."""
    return write_npz(path, m.header, m.arrays)


def read_tracker_map(path: str | os.PathLike[str]) -> TrackerMap:
    """Read and check a file of :func:`write_tracker_map`; DataError naming the file and what is wrong."""
    path = Path(path)
    header, arrays = read_npz(path, "tracker map")
    if header.get("format") != TRACKER_MAP_VERSION:
        got = header.get("format")
        raise DataError(f"{path}: tracker map format {got!r}, expected {TRACKER_MAP_VERSION}")
    m = TrackerMap(header, arrays)
    _check(path, m)
    return m


def _check(path: Path, m: TrackerMap) -> None:
    a = m.arrays
    need = {"kf_ids", "kf_stamps", "kf_T_cw", "kf_segment", "kf_offsets", "kf_point_ids", "bow_kf", "bow_offsets",
            "bow_words", "bow_weights", *(f"kf_{n}" for n in _FEATURE_ARRAYS), *(f"pt_{n}" for n in _POINT_ARRAYS)}
    if missing := sorted(need - set(a)):
        raise DataError(f"{path}: tracker map lacks {', '.join(missing)}")
    k, off = len(a["kf_ids"]), a["kf_offsets"]
    m_total, p = int(off[-1]) if len(off) else 0, len(a["pt_pos"])
    problems = []
    if k != m.n_keyframes or a["kf_T_cw"].shape != (k, 4, 4) or len(off) != k + 1:
        problems.append(f"{k} keyframes but the header says {m.n_keyframes} (or poses / offsets disagree)")
    if any(len(a[f"kf_{n}"]) != m_total for n in _FEATURE_ARRAYS) or len(a["kf_point_ids"]) != m_total:
        problems.append("keyframe features of different lengths")
    if a["pt_desc"].shape != (p, 32) or any(len(a[f"pt_{n}"]) != p for n in _POINT_ARRAYS):
        problems.append("point arrays of different lengths")
    if len(a["kf_point_ids"]) and int(a["kf_point_ids"].max(initial=-1)) >= p:
        problems.append("a keypoint names a point past the store")
    if not np.all(np.isfinite(a["kf_T_cw"])) or not np.all(np.isfinite(a["pt_pos"])):
        problems.append("non-finite poses or points")
    if len(a["bow_offsets"]) != len(a["bow_kf"]) + 1 or len(a["bow_words"]) != len(a["bow_weights"]):
        problems.append("bag-of-words vectors do not match their offsets")
    if problems:
        raise DataError(f"{path}: corrupt tracker map: {problems[0]}")


def restore_map(m: TrackerMap) -> tuple[SparseMap, list[tuple[int, BowVector]]]:
    """A SparseMap holding ``m``'s keyframes and points (observations rebuilt from the keyframes'
    point ids; new keyframes numbered from the saved ``next_keyframe_id``) and its BoW vectors."""
    a = m.arrays
    smap = SparseMap(int(m.header["next_keyframe_id"]))
    off = a["kf_offsets"]
    for i, kf_id in enumerate(a["kf_ids"].tolist()):
        s = slice(int(off[i]), int(off[i + 1]))
        feats = FrameFeatures(*(a[f"kf_{n}"][s].copy() for n in _FEATURE_ARRAYS))
        smap.add_keyframe(SparseKeyframe(int(kf_id), int(a["kf_stamps"][i]), a["kf_T_cw"][i].astype(np.float64),
                                         feats, a["kf_point_ids"][s].astype(np.int64), int(a["kf_segment"][i])))
    smap.restore_points(*(a[f"pt_{n}"] for n in _POINT_ARRAYS))
    bo = a["bow_offsets"]
    vectors = [(int(k), BowVector(a["bow_words"][bo[i]:bo[i + 1]].astype(np.int64),
                                  a["bow_weights"][bo[i]:bo[i + 1]].astype(np.float64)))
               for i, k in enumerate(a["bow_kf"].tolist())]
    return smap, vectors


def load_bundle_map(tracker: Any, path: Path | None, map_mode: str) -> TrackerMap | None:  # noqa: ANN401 - a Tracker
    """Start ``tracker`` (before its first frame) in ``map_mode`` ("localize": the map is not
    changed) from the tracker map at ``path`` (a bundle's ``tracker.npz``; None: none). Returns
    the map loaded. A map it cannot take raises DataError and leaves the tracker LOST in an empty
    map: no pose, and no new world started."""
    from memgs_ros.core.tracking.config import TrackingState

    tracker.localize_only = map_mode == "localize"
    if path is None:
        return None
    try:
        m = read_tracker_map(path)
        tracker.load_map(m)
    except DataError:
        tracker.state = TrackingState.LOST  # no map, no pose: nothing to relocalise in
        raise
    return m
