"""Log a run to a Rerun recording: the Gaussian map as splats, poses, keyframe frusta, images, scalars.

Every function takes the ``rerun.RecordingStream`` to log to (no global recording) and a
:class:`LogTime`, or None for static data (a saved map). Rerun keeps the time per thread, so
each function sets it right before it logs: callers on several threads stay correct.

Entities (the blueprint of :func:`send_blueprint` lays them out)::

    world                    view coordinates RDF (the tracker's world is a camera frame: y down)
    world/map                GaussianSplats3D
    world/trajectory         LineStrips3D of the tracked camera centres
    world/camera             Transform3D + Pinhole of the latest tracked pose
    world/keyframes/<n>      Transform3D + Pinhole of keyframe n
    views/frame, views/render   the source frame and the live render at the same pose
    quality/psnr_db          PSNR of that render against that frame
    stats/<key>/<node>       Scalars from the nodes' stats (one plot a key, one series a node)

Import this module only after :func:`memgs_ros.viz.require_rerun` (it imports rerun).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import NamedTuple

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from memgs_ros.core.gaussians.records import GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import rotmat_to_quat_xyzw
from memgs_ros.viz.splats import psnr_db, splat_arrays

__all__ = [
    "CAMERA",
    "FRAME_VIEW",
    "KEYFRAMES",
    "MAP",
    "PSNR",
    "RENDER_VIEW",
    "STATS",
    "TRAJECTORY",
    "LogTime",
    "finish",
    "keyframe_path",
    "log_camera",
    "log_keyframe",
    "log_map",
    "log_scalars",
    "log_stats_rows",
    "log_trajectory",
    "log_views",
    "log_world",
    "numeric_values",
    "send_blueprint",
]

MAP = "world/map"
TRAJECTORY = "world/trajectory"
CAMERA = "world/camera"
KEYFRAMES = "world/keyframes"
FRAME_VIEW = "views/frame"
RENDER_VIEW = "views/render"
PSNR = "quality/psnr_db"
STATS = "stats"

FRAME_TIMELINE = "frame"  # sequence: index of the latest tracked frame
STAMP_TIMELINE = "stamp"  # timestamp: the sensor stamp of that frame
RUN_TIMELINE = "run_time"  # duration: seconds since the run started (a saved run's stats)


class LogTime(NamedTuple):
    """When something is logged: the frame index and, when known (> 0), its sensor stamp (ns)."""

    frame: int
    stamp_ns: int = 0


def _set_time(rec: rr.RecordingStream, t: LogTime) -> None:
    rec.reset_time()  # a stamp set for an earlier call must not stick to this one
    rec.set_time(FRAME_TIMELINE, sequence=int(t.frame))
    if t.stamp_ns > 0:
        rec.set_time(STAMP_TIMELINE, timestamp=np.datetime64(int(t.stamp_ns), "ns"))


def _log(rec: rr.RecordingStream, path: str, t: LogTime | None, *archetypes: rr.AsComponents) -> None:
    if t is None:
        rec.log(path, *archetypes, static=True)
    else:
        _set_time(rec, t)
        rec.log(path, *archetypes)


def log_world(rec: rr.RecordingStream) -> None:
    """The world's axes (static): the tracker's world is its first camera's optical frame
    (x right, y down, z forward), so the viewer's "up" is -y."""
    rec.log("world", rr.ViewCoordinates.RDF, static=True)


def log_map(rec: rr.RecordingStream, records: GaussianRecords, t: LogTime | None, sh: bool = True,
            path: str = MAP) -> int:
    """Log the map (N Gaussians) as splats at ``path``; returns N.

    sh: also send the degree 1..3 SH coefficients (90 B a Gaussian more; the viewer then shows
    view-dependent colour), when the map has any.
    """
    s = splat_arrays(records, sh=sh)
    _log(rec, path, t, rr.GaussianSplats3D(s.centers, scales=s.scales, quaternions=s.quaternions_xyzw,
                                           colors=s.colors_rgba, sh_coefficients=s.sh_rest))
    return len(records)


def log_trajectory(rec: rr.RecordingStream, T_wc: np.ndarray, t: LogTime | None,  # [M, 4, 4]
                   path: str = TRAJECTORY, color: tuple[int, int, int] = (255, 140, 0)) -> None:
    """The camera centres of ``T_wc`` [M, 4, 4] (camera-to-world) as one line strip."""
    T_wc = np.asarray(T_wc, dtype=np.float64).reshape(-1, 4, 4)
    if len(T_wc) < 2:
        return
    _log(rec, path, t, rr.LineStrips3D([T_wc[:, :3, 3].astype(np.float32)], colors=[color], radii=[0.004]))


def _transform(T_wc: np.ndarray) -> rr.Transform3D:
    """A camera-to-world pose [4, 4] as the Transform3D from the camera entity to its parent."""
    T = np.asarray(T_wc, dtype=np.float64)
    return rr.Transform3D(translation=T[:3, 3], quaternion=rr.Quaternion(xyzw=rotmat_to_quat_xyzw(T[:3, :3])))


def _pinhole(camera: PinholeCamera, image_plane_distance_m: float) -> rr.Pinhole:
    # Rerun's default camera axes are RDF, the optical frame of the tracker's poses.
    return rr.Pinhole(image_from_camera=camera.K, resolution=[camera.width, camera.height],
                      image_plane_distance=image_plane_distance_m)


def log_camera(rec: rr.RecordingStream, T_wc: np.ndarray, t: LogTime | None,  # [4, 4]
               camera: PinholeCamera | None = None, path: str = CAMERA, image_plane_distance_m: float = 0.15) -> None:
    """The tracked camera pose ``T_wc`` [4, 4] at ``path``; with ``camera``, its frustum too."""
    parts: list[rr.AsComponents] = [_transform(T_wc)]
    if camera is not None:
        parts.append(_pinhole(camera, image_plane_distance_m))
    _log(rec, path, t, *parts)


def keyframe_path(index: int) -> str:
    """The entity of keyframe ``index`` (zero-padded, so the viewer lists them in order)."""
    return f"{KEYFRAMES}/{index:05d}"


def log_keyframe(rec: rr.RecordingStream, index: int, T_wc: np.ndarray, t: LogTime | None,  # [4, 4]
                 camera: PinholeCamera | None = None, image_plane_distance_m: float = 0.08) -> None:
    """Keyframe ``index`` at pose ``T_wc`` [4, 4]: a transform and, with ``camera``, a frustum.
    Logging it again (after bundle adjustment or a loop closure) moves it; the frustum stays
    (leave ``camera`` out then)."""
    log_camera(rec, T_wc, t, camera, keyframe_path(index), image_plane_distance_m)


def _image(rgb: np.ndarray, jpeg_quality: int) -> rr.AsComponents:  # [H, W, 3] uint8
    if jpeg_quality <= 0:
        return rr.Image(rgb, color_model="RGB")
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:  # cv2 cannot fail on a valid uint8 image; keep the raw pixels if it ever does
        return rr.Image(rgb, color_model="RGB")
    return rr.EncodedImage(contents=data.tobytes(), media_type="image/jpeg")


def log_views(rec: rr.RecordingStream, render_rgb: np.ndarray, frame_rgb: np.ndarray | None,  # [h, w, 3], [H, W, 3]
              t: LogTime, jpeg_quality: int = 85) -> float | None:
    """The live render and the source frame at the same pose, side by side, and the render's PSNR.

    render_rgb: [h, w, 3] uint8. frame_rgb: [H, W, 3] uint8 or None (only the render is logged);
    resized to the render's size (the mapping resolution) first. jpeg_quality: 1..100 sends JPEG
    (an image is ~1/10 the bytes), 0 raw pixels. Returns the PSNR (dB) or None without a frame.
    The frame is the camera's raw image: where the camera has lens distortion the PSNR is a
    little lower than the evaluation's, which renders at undistorted views.
    """
    _log(rec, RENDER_VIEW, t, _image(np.ascontiguousarray(render_rgb), jpeg_quality))
    if frame_rgb is None:
        return None
    h, w = render_rgb.shape[:2]
    small = frame_rgb if frame_rgb.shape[:2] == (h, w) else cv2.resize(frame_rgb, (w, h), interpolation=cv2.INTER_AREA)
    _log(rec, FRAME_VIEW, t, _image(np.ascontiguousarray(small), jpeg_quality))
    value = psnr_db(small, render_rgb)
    if np.isfinite(value):
        _log(rec, PSNR, t, rr.Scalars(value))
    return value


def log_scalars(rec: rr.RecordingStream, node: str, values: Mapping[str, float], t: LogTime) -> None:
    """One time series point per value, at ``stats/<key>/<node>`` (a key's plot shows every node)."""
    _set_time(rec, t)
    for key, value in values.items():
        rec.log(f"{STATS}/{key}/{node}", rr.Scalars(float(value)))


def log_stats_rows(rec: rr.RecordingStream, rows: Iterable[Mapping[str, object]], keys: Iterable[str]) -> int:
    """A saved run's stats timeline (``stats_timeline.jsonl`` rows: {"t_s", "node", key: value}) as
    scalars on the ``run_time`` timeline; only ``keys``, only values that are numbers. Returns the
    number of points logged."""
    wanted = set(keys)
    n = 0
    for row in rows:
        rec.reset_time()
        rec.set_time(RUN_TIMELINE, duration=float(row["t_s"]))  # type: ignore[arg-type]
        for key, value in numeric_values(row, wanted).items():
            rec.log(f"{STATS}/{key}/{row['node']}", rr.Scalars(value))
            n += 1
    return n


def numeric_values(values: Mapping[str, object], keys: set[str] | None) -> dict[str, float]:
    """The entries of a stats message whose key is in ``keys`` (None: all) and whose value is a
    finite number (stats travel as strings)."""
    out: dict[str, float] = {}
    for key, value in values.items():
        if key in ("t_s", "node") or (keys is not None and key not in keys):
            continue
        try:
            v = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            continue
        if np.isfinite(v):
            out[key] = v
    return out


def finish(rec: rr.RecordingStream, timeout_s: float = 10.0) -> None:
    """Flush what rerun's threads still hold and close the sinks: an ``.rrd`` file gets its footer
    (without it, readers fall back to scanning the whole file)."""
    rec.flush(timeout_sec=timeout_s)
    rec.disconnect()


# The stats plotted side by side (tabs) in the default layout; others are logged, not laid out.
PLOTTED_STATS = ("gaussians", "rss_mb", "track_ms", "iteration", "loss", "keyframes", "delta_bytes", "map_bytes")


def send_blueprint(rec: rr.RecordingStream, with_views: bool = True) -> None:
    """The default layout: the 3D world on the left; on the right the frame and the render side by
    side (``with_views``), the PSNR, and the stats in tabs, one plot a key."""
    plots = rrb.Tabs(*(rrb.TimeSeriesView(origin=f"{STATS}/{key}", name=key) for key in PLOTTED_STATS))
    right: list[rrb.Container | rrb.View] = [plots]
    if with_views:
        right = [rrb.Horizontal(rrb.Spatial2DView(origin=FRAME_VIEW, name="frame"),
                                rrb.Spatial2DView(origin=RENDER_VIEW, name="render")),
                 rrb.TimeSeriesView(origin="quality", name="PSNR (dB)"), plots]
    rec.send_blueprint(rrb.Blueprint(
        rrb.Horizontal(rrb.Spatial3DView(origin="world", name="map"), rrb.Vertical(*right), column_shares=[3, 2]),
        collapse_panels=True))
