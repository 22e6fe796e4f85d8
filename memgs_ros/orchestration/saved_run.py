"""A saved map with what lies beside it (trajectory, keyframes, stats, camera), for ``memgs view``.

:func:`load_saved_run` reads the files (no rerun); :func:`log_saved_run` logs them to a recording.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from memgs_ros.core.gaussians.records import GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.map_io.bundle import LATEST, MANIFEST, PLY_FILE, TRACKER_FILE, check_bundle, resolve_bundle
from memgs_ros.core.map_io.ply import load_ply
from memgs_ros.errors import DataError
from memgs_ros.io.tum import read_trajectory
from memgs_ros.orchestration.run_files import (
    KEYFRAMES_FILE,
    MAP_FILE,
    PARAMS_FILE,
    STATS_TIMELINE_FILE,
    TRAJECTORY_FILE,
    configured_camera,
    read_params,
    read_stats_timeline,
)

__all__ = ["NOMINAL_CAMERA", "SavedRun", "load_saved_run", "log_saved_run"]

# Frusta of a run whose parameters name no calibration: a 4:3 camera with a 63 degree field of view.
# They show where the camera was and where it looked, not its true field of view.
NOMINAL_CAMERA = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
STATS_KEYS = ("gaussians", "iteration", "keyframes", "poses_out", "track_ms", "rss_mb", "map_bytes")


@dataclass(frozen=True)
class SavedRun:
    """What ``memgs view`` shows.

    trajectory, keyframes: (stamps_ns [M] int64, T_wc [M, 4, 4]) or None.
    camera: the run's calibration, or :data:`NOMINAL_CAMERA` when it names none.
    stats: the run's stats timeline rows (``stats_timeline.jsonl``), [] when absent.
    """

    map_path: Path
    records: GaussianRecords
    trajectory: tuple[np.ndarray, np.ndarray] | None = None
    keyframes: tuple[np.ndarray, np.ndarray] | None = None
    camera: PinholeCamera = NOMINAL_CAMERA
    stats: list[dict[str, Any]] = field(default_factory=list)
    sources: dict[str, Path] = field(default_factory=dict)  # what was read: "trajectory" -> path, ...


def load_saved_run(path: str | os.PathLike[str], trajectory: str | os.PathLike[str] | None = None,
                   keyframes: str | os.PathLike[str] | None = None) -> SavedRun:
    """Read a map (a PLY, a run folder holding ``map.ply``, or a map bundle) and the run files beside it.

    trajectory / keyframes: TUM files; None takes ``trajectory.txt`` / ``keyframes.txt`` from the
    map's folder when they are there. A file given explicitly must exist; files found beside the
    map that cannot be read raise DataError too (a half-written run is worth knowing about).
    """
    map_path = Path(path)
    if map_path.is_dir() and ((map_path / MANIFEST).is_file() or (map_path / LATEST).exists()):
        return _saved_bundle(resolve_bundle(map_path), trajectory)
    if map_path.is_dir():
        map_path = map_path / MAP_FILE
    if not map_path.exists():
        raise DataError(f"{map_path}: no such map (give a .ply or a run folder holding {MAP_FILE})")
    folder = map_path.parent
    records = load_ply(map_path)
    sources = {"map": map_path}

    def poses(given: str | os.PathLike[str] | None, name: str, key: str) -> tuple[np.ndarray, np.ndarray] | None:
        p = Path(given) if given is not None else folder / name
        if given is None and not p.is_file():
            return None
        sources[key] = p
        return read_trajectory(p)

    camera = NOMINAL_CAMERA
    if (folder / PARAMS_FILE).is_file():
        found = configured_camera(read_params(folder)).camera
        if found is not None:
            camera, sources["camera"] = found, folder / PARAMS_FILE
    stats = read_stats_timeline(folder)
    if stats:
        sources["stats"] = folder / STATS_TIMELINE_FILE
    return SavedRun(map_path, records, poses(trajectory, TRAJECTORY_FILE, "trajectory"),
                    poses(keyframes, KEYFRAMES_FILE, "keyframes"), camera, stats, sources)


def _saved_bundle(bundle: Path, trajectory: str | os.PathLike[str] | None) -> SavedRun:
    """A map bundle (core/map_io/bundle.py): its map, its tracker's keyframes and its camera."""
    _, m = check_bundle(bundle, verify_files=False)
    try:
        with np.load(bundle / TRACKER_FILE, allow_pickle=False) as z:
            keyframes = (z["kf_stamps"].astype(np.int64), invert_pose(z["kf_T_cw"].astype(np.float64)))
    except (OSError, KeyError, ValueError) as err:
        raise DataError(f"{bundle / TRACKER_FILE}: not a readable tracker map ({err})") from err
    camera = PinholeCamera.from_dict(m.camera)
    sources = {"map": bundle / PLY_FILE, "keyframes": bundle / TRACKER_FILE, "camera": bundle / MANIFEST}
    traj = None
    if trajectory is not None:
        traj, sources["trajectory"] = read_trajectory(trajectory), Path(trajectory)
    return SavedRun(bundle / PLY_FILE, load_ply(bundle / PLY_FILE), traj, keyframes, camera, [], sources)


def log_saved_run(rec: Any, run: SavedRun, sh: bool = True) -> None:
    """Log ``run`` to the rerun.RecordingStream ``rec``: the map, trajectory and keyframe frusta as
    static data, the camera along the trajectory on the ``frame`` timeline, the stats on ``run_time``."""
    from memgs_ros.viz import rerun_log as rl  # imports rerun: callers checked it is there

    rl.log_world(rec)
    rl.send_blueprint(rec, with_views=False)
    rl.log_map(rec, run.records, None, sh=sh)
    if run.trajectory is not None:
        stamps, T_wc = run.trajectory
        rl.log_trajectory(rec, T_wc, None)
        for i, (stamp, T) in enumerate(zip(stamps.tolist(), T_wc)):
            rl.log_camera(rec, T, rl.LogTime(i, int(stamp)), run.camera if i == 0 else None)
    if run.keyframes is not None:
        for i, T in enumerate(run.keyframes[1]):
            rl.log_keyframe(rec, i, T, None, run.camera)
    if run.stats:
        rl.log_stats_rows(rec, run.stats, STATS_KEYS)
