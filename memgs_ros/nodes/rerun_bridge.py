"""rerun_bridge node: stream the graph's outputs to a Rerun viewer or an ``.rrd`` file.

The view of ``memgs run --rerun`` and, alone, a ground station's live view of a robot's map
(``ros2 run memgs_ros rerun_bridge --ros-args -p connect_url:=rerun+http://HOST:9876/proxy``).
Needs the ``[viz]`` extra (rerun-sdk); without it the node stops at start with one line saying so.

Subscribes: ``memgs/pose`` (camera pose each frame), ``memgs/path`` (the tracker's corrected
trajectory, 1 Hz), ``memgs/keyframe/{pose,camera_info}`` (frusta),
``memgs/keyframe/{refined,loop_corrected}_poses`` (keyframes moved by BA and loop closure),
``color_topic`` (the source frames, kept briefly to pair with renders), ``memgs/render/color``
(the mapper's live render at the latest pose), ``memgs/map/delta`` and ``memgs/mapper/snapshot``
(the mapper's map deltas and snapshots), ``memgs/map/gaussians`` (the merger's full map, latched)
and ``memgs/<node>/stats``. Publishes ``memgs/rerun_bridge/stats`` (``map_seq``,
``map_epoch``, ``map_gaussians`` of the last map logged; ``log_us_total``, the time spent in
Rerun's log calls; and, as every node, ``cpu_s``, its process's CPU time).

The map: the node follows the deltas as the merger does (:class:`MapFollower`) and logs its copy
every ``map_period_s`` when it changed, so the view costs the robot no extra traffic. It asks the
merger for the full map (``memgs/merger/publish_map``) only to start late or repair a gap, and
logs every full map the merger publishes at once (the run's final map among them).
"""
from __future__ import annotations

import sys
import time
from collections import OrderedDict
from pathlib import Path as FsPath
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.maps.follower import MapFollower, RequestPacer
from memgs_ros.errors import ConfigError, DataError, MessageError
from memgs_ros.io.image_decoding import decode_camera_info, decode_rgb
from memgs_ros.nodes.params import NODE_CONFIGS, RerunBridgeParams
from memgs_ros.nodes.registry import GRAPH
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import pose_to_matrix, stamp_to_ns
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats, stats_values
from memgs_ros.ros.map_messages import decode_map_message
from memgs_ros.ros.node_main import run_node
from memgs_ros.ros.service_calls import call_trigger
from memgs_ros.viz import RerunTarget

# The stats plotted by default: map size and training progress, tracking speed, memory.
STATS_NODES = GRAPH
_FRAMES_KEPT = 30  # source frames held to pair with a render of the same stamp (renders lag < 1 s)
_RESYNC_INTERVAL_S = 2.0  # least time between full-map requests while out of step


CONFIGS = NODE_CONFIGS["rerun_bridge"]


class RerunBridgeNode(Node):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("rerun_bridge", **node_kwargs)
        v = declare_config(self, RerunBridgeParams, "")
        spawn, url, save, app, name = v.spawn, v.connect_url, v.save_path, v.application_id, v.recording_name
        self.map_period, self.log_sh, self.jpeg_quality = v.map_period_s, v.log_sh, v.jpeg_quality
        self.log_frames, color_topic, keys = v.log_frames, v.color_topic, v.stats_keys
        self.stats_keys: set[str] | None = (None if keys.strip() == "*"
                                            else {k.strip() for k in keys.split(",") if k.strip()})
        self.plane_m = v.frustum_size_m
        try:
            target = RerunTarget(spawn=spawn, connect_url=url, save_path=FsPath(save) if save else None)
        except ConfigError as err:
            raise ConfigError(f"rerun_bridge: {err} (parameters spawn, connect_url, save_path)") from err
        target.check()
        from memgs_ros.viz import rerun_log  # imports rerun: only after the check above

        self.log = rerun_log
        self.rec = target.open(app, recording_name=name or self.get_namespace().strip("/") or "memgs")
        self.log.log_world(self.rec)
        self.log.send_blueprint(self.rec, with_views=True)

        self.frame_index = -1
        self.stamp_ns = 0
        self.frame_of_stamp: OrderedDict[int, int] = OrderedDict()
        self.frames: OrderedDict[int, Image] = OrderedDict()  # stamp -> source colour message
        self.camera: PinholeCamera | None = None
        self._camera_logged: PinholeCamera | None = None  # the camera of the last frustum at world/camera
        self.keyframes: dict[int, int] = {}  # stamp -> keyframe index
        self.keyframe_poses: dict[int, np.ndarray] = {}  # keyframe index -> T_wc [4, 4] as last logged
        self.map = MapFollower()
        self.logged_version: tuple[int, int, int] | None = None  # MapFollower.version of the last map logged
        self.pacer = RequestPacer(_RESYNC_INTERVAL_S)  # full-map requests while out of step
        self._map_request: Future | None = None
        self._closing = False

        self.create_subscription(PoseStamped, "memgs/pose", self.on_pose, qos.reliable(100))
        self.create_subscription(Path, "memgs/path", self.on_path, qos.reliable(5))
        kf = qos.keyframes()  # TRANSIENT_LOCAL as the tracker publishes them: a late bridge gets the latest
        self.create_subscription(CameraInfo, "memgs/keyframe/camera_info", self.on_camera_info, kf)
        self.create_subscription(PoseStamped, "memgs/keyframe/pose", self.on_keyframe, kf)
        for topic in ("memgs/keyframe/refined_poses", "memgs/keyframe/loop_corrected_poses"):
            self.create_subscription(Path, topic, self.on_keyframes_moved, qos.reliable(20))
        if self.log_frames:
            self.create_subscription(Image, color_topic, self.on_frame, qos.sensor())
        self.create_subscription(Image, "memgs/render/color", self.on_render, qos.reliable(2))
        self.create_subscription(PointCloud2, "memgs/map/delta", self.on_delta, qos.reliable(50))
        # Full maps: the mapper's snapshots take sequence numbers of their own (a delta stream
        # with a snapshot in it has a gap without it); the merger's map repairs anything else.
        self.create_subscription(PointCloud2, "memgs/mapper/snapshot", self.on_full_map, qos.latched())
        self.create_subscription(PointCloud2, "memgs/map/gaussians", self.on_full_map, qos.latched())
        for node in STATS_NODES:
            self.create_subscription(DiagnosticArray, f"memgs/{node}/stats",
                                     lambda m, n=node: self.on_stats(n, m), qos.reliable(5))
        self.publish_map_client = self.create_client(Trigger, "memgs/merger/publish_map")
        # Last: the runner takes memgs/rerun_bridge/stats appearing to mean the node listens.
        self.stats = NodeStats(self, "rerun_bridge")
        if self.map_period > 0:
            self.create_timer(self.map_period, self.log_map)
        sinks = ", ".join(s for s in (spawn and "spawned viewer", url, save) if s)
        self.get_logger().info(f"logging to Rerun: {sinks}")

    # ------------------------------------------------------------------ helpers
    def _now(self, stamp_ns: int | None = None) -> Any:
        """The LogTime of ``stamp_ns`` (its frame index when seen) or of the latest frame."""
        if stamp_ns is not None and stamp_ns in self.frame_of_stamp:
            return self.log.LogTime(self.frame_of_stamp[stamp_ns], stamp_ns)
        return self.log.LogTime(max(self.frame_index, 0), self.stamp_ns)

    def _timed(self, what: str, fn: Any, *args: Any) -> Any:
        if self._closing:
            return None  # the recording is being closed: nothing more goes into it
        t0 = time.perf_counter()
        out = fn(*args)
        us = int((time.perf_counter() - t0) * 1e6)
        self.stats.counters["log_us_total"] += us
        self.stats.counters[f"log_us.{what}"] += us
        self.stats.counters[f"logged.{what}"] += 1
        return out

    # ------------------------------------------------------------------ callbacks
    def on_pose(self, msg: PoseStamped) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.frame_index += 1
        self.stamp_ns = stamp
        self.frame_of_stamp[stamp] = self.frame_index
        while len(self.frame_of_stamp) > 4 * _FRAMES_KEPT:
            self.frame_of_stamp.popitem(last=False)
        # The frustum once per camera (the viewer keeps the latest); the transform every frame.
        camera = self.camera if self.camera != self._camera_logged else None
        self._camera_logged = self.camera
        self._timed("pose", self.log.log_camera, self.rec, pose_to_matrix(msg.pose), self._now(stamp), camera)

    def on_path(self, msg: Path) -> None:
        if len(msg.poses) >= 2:
            T = np.stack([pose_to_matrix(p.pose) for p in msg.poses])
            self._timed("trajectory", self.log.log_trajectory, self.rec, T, self._now())

    def on_camera_info(self, msg: CameraInfo) -> None:
        try:
            camera = decode_camera_info(msg)
        except (MessageError, DataError) as err:
            self.stats.problem("bad_camera_info", f"camera_info ignored: {err}")
            return
        first = self.camera is None
        self.camera = camera
        if first:  # keyframes that came before their camera_info get their frusta now
            for index, T in self.keyframe_poses.items():
                self._timed("keyframe", self.log.log_keyframe, self.rec, index, T, self._now(), self.camera,
                            self.plane_m)

    def on_keyframe(self, msg: PoseStamped) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        if stamp in self.keyframes:
            return  # a TRANSIENT_LOCAL copy of one already logged
        index = self.keyframes[stamp] = len(self.keyframes)
        T = self.keyframe_poses[index] = pose_to_matrix(msg.pose)
        self._timed("keyframe", self.log.log_keyframe, self.rec, index, T, self._now(stamp), self.camera, self.plane_m)

    def on_keyframes_moved(self, msg: Path) -> None:
        """Move the keyframes that BA or a loop closure moved by more than 1 mm or ~0.06 degrees
        (BA sends its whole window after every run; most of it barely moves)."""
        for p in msg.poses:
            index = self.keyframes.get(stamp_to_ns(p.header.stamp))
            if index is None:
                continue
            T = pose_to_matrix(p.pose)
            if np.abs(T[:3] - self.keyframe_poses[index][:3]).max() > 1e-3:
                self.keyframe_poses[index] = T
                self._timed("keyframe_moved", self.log.log_keyframe, self.rec, index, T, self._now())

    def on_frame(self, msg: Image) -> None:
        self.frames[stamp_to_ns(msg.header.stamp)] = msg  # decoded only if a render pairs with it
        while len(self.frames) > _FRAMES_KEPT:
            self.frames.popitem(last=False)

    def on_render(self, msg: Image) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            render = decode_rgb(msg)
            frame_msg = self.frames.get(stamp)
            frame = decode_rgb(frame_msg) if frame_msg is not None else None
        except MessageError as err:
            self.stats.problem("bad_image", f"image not logged: {err}")
            return
        value = self._timed("views", self.log.log_views, self.rec, render, frame, self._now(stamp), self.jpeg_quality)
        if value is not None:
            self.stats.gauges["psnr_db"] = round(value, 2)

    def on_delta(self, msg: PointCloud2) -> None:
        m = decode_map_message(msg, self.stats)
        if m is None:
            return
        self.map.on_delta(m)
        if self.map.resyncing:
            self.request_full_map()

    def on_full_map(self, msg: PointCloud2) -> None:
        m = decode_map_message(msg, self.stats)
        if m is not None and self.map.on_full_map(m) is not None:
            self.pacer.answered()
            self.log_map()  # rare (on request, the merger's period, the end of a run): show it now
        if self.map.resyncing:
            self.request_full_map()

    def log_map(self) -> None:
        """Log the followed map if it changed since the last one logged."""
        if self.map.resyncing:
            self.request_full_map()
        if not self.map.in_step or self.map.version == self.logged_version:
            return
        records = self.map.replica.records
        self._timed("map", self.log.log_map, self.rec, records, self._now(), self.log_sh)
        self.logged_version = epoch, seq, n = self.map.version
        self.stats.gauges.update(map_epoch=epoch, map_seq=seq, map_gaussians=n)

    def request_full_map(self) -> None:
        """Ask the merger for its full map, at most every few seconds and one request at a time."""
        pending = self._map_request is not None and not self._map_request.done()
        if (pending or not self.publish_map_client.service_is_ready()
                or not self.pacer.ask(time.monotonic(), out_of_step=True)):
            return
        self._map_request = call_trigger(self.publish_map_client, self.stats, "map_request",
                                         "the merger did not take a full-map request")
        self.stats.counters["map_requests"] += 1

    def on_stats(self, node: str, msg: DiagnosticArray) -> None:
        numbers = self.log.numeric_values(stats_values(msg), self.stats_keys)
        if numbers:
            self._timed("stats", self.log.log_scalars, self.rec, node, numbers, self._now())

    def on_shutdown(self) -> None:
        # The file sink and the gRPC stream are written by rerun's own threads: wait for them.
        self._closing = True
        self.log.finish(self.rec)


def main(args: list[str] | None = None) -> int:
    return run_node(RerunBridgeNode, "rerun_bridge", args)


if __name__ == "__main__":
    sys.exit(main())
