"""Optional ORB-SLAM3 front-end through a ``pyorbslam3`` binding (the paper's tracker).

Not the default and not tested here (no binding or vocabulary on these machines): this is
a thin adapter with the same interface as the feature tracker. Bindings differ; this one
expects ``pyorbslam3.System(vocabulary, settings, sensor, use_viewer)`` with
``track_rgbd(rgb, depth_m, t_s)`` / ``track_monocular(rgb, t_s)`` (or the C++ names
``TrackRGBD`` / ``TrackMonocular``) returning T_cw as a 4x4 array, empty when lost.
Keyframes are not exposed by those bindings, so this adapter declares one every
``keyframe_max_frames`` tracked frames, with keypoints from our own ORB extractor.
"""
from __future__ import annotations

import importlib
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking.config import KeyframeInfo, TrackerConfig, TrackingState, TrackResult
from memgs_ros.core.tracking.features import OrbExtractor
from memgs_ros.core.tracking.protocol import SparseMapStats, Tracker
from memgs_ros.errors import ConfigError


def _method(obj: Any, *names: str) -> Any:
    for n in names:
        if hasattr(obj, n):
            return getattr(obj, n)
    raise ConfigError(f"pyorbslam3.System has none of {names}; this binding is not supported")


class OrbSlam3Tracker(Tracker):
    """The :class:`Tracker` interface over ORB-SLAM3 (see module docstring)."""

    def __init__(self, cfg: TrackerConfig, camera: PinholeCamera) -> None:
        try:
            mod = importlib.import_module("pyorbslam3")
        except ImportError as err:
            raise ConfigError("backend 'orbslam3' needs the pyorbslam3 module (not installed); "
                              "use backend='feature'") from err
        for field, path in (("orbslam3_vocabulary", cfg.orbslam3_vocabulary),
                            ("orbslam3_settings", cfg.orbslam3_settings)):
            if not path or not Path(path).is_file():
                raise ConfigError(f"TrackerConfig.{field} must name an existing file, got {path!r}")
        sensors = getattr(mod.System, "eSensor", None) or getattr(mod, "Sensor", None)
        if sensors is None:
            raise ConfigError("pyorbslam3 exposes no sensor enum (System.eSensor or Sensor)")
        sensor = getattr(sensors, "RGBD" if cfg.mode == "rgbd" else "MONOCULAR")
        self.cfg = cfg
        self.camera = camera
        self._system = mod.System(cfg.orbslam3_vocabulary, cfg.orbslam3_settings, sensor, False)
        self._track = _method(self._system, *(("track_rgbd", "TrackRGBD") if cfg.mode == "rgbd"
                                              else ("track_monocular", "TrackMonocular")))
        self._extractor = OrbExtractor(cfg)
        self._since_kf = cfg.keyframe_max_frames
        self._next_kf_id = 0
        self._closed = False
        self.ba_time_s = 0.0  # ORB-SLAM3 runs its BA inside the binding, out of our sight

    def track(self, frame: Frame) -> TrackResult:
        t0 = time.perf_counter()
        depth = frame.depth_m if self.cfg.mode == "rgbd" else None
        if self.cfg.mode == "rgbd":
            d = np.nan_to_num(frame.depth_m, nan=0.0) if frame.depth_m is not None else None
            out = self._track(frame.rgb, d, frame.stamp_s)
        else:
            out = self._track(frame.rgb, frame.stamp_s)
        T_cw = np.asarray(out, dtype=np.float64)
        if T_cw.shape != (4, 4) or not np.all(np.isfinite(T_cw)):
            return TrackResult(frame.stamp_ns, None, TrackingState.LOST, None, 0, 0, time.perf_counter() - t0)
        T_wc = invert_pose(T_cw)
        kf = None
        self._since_kf += 1
        if self._since_kf >= self.cfg.keyframe_max_frames:
            gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
            f = self._extractor.extract(gray, self.camera, depth)
            depth_kp = f.depth_m.astype(np.float32)
            kf = KeyframeInfo(self._next_kf_id, frame.stamp_ns, T_wc, f.uv.astype(np.float32), depth_kp,
                              np.isfinite(depth_kp))
            self._next_kf_id += 1
            self._since_kf = 0
        return TrackResult(frame.stamp_ns, T_wc, TrackingState.OK, kf, 0, 0, time.perf_counter() - t0)

    def poll_refined_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """ORB-SLAM3 refines internally; the bindings do not report which keyframes moved."""
        return []

    def map_stats(self) -> SparseMapStats | None:
        """The bindings expose no map."""
        return None

    def close(self) -> None:
        if not self._closed:
            _method(self._system, "shutdown", "Shutdown")()
            self._closed = True
