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

What is logged, and when, is :class:`memgs_ros.viz.live_view.LiveView`'s; this node decodes.
The map: the node follows the deltas as the merger does (:class:`MapFollower`) and logs its copy
every ``map_period_s`` when it changed, so the view costs the robot no extra traffic. It asks the
merger for the full map (``memgs/merger/publish_map``) only to start late or repair a gap, and
logs every full map the merger publishes at once (the run's final map among them).
"""
from __future__ import annotations

import sys
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path as FsPath
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from memgs_ros.core.map_io.follower import MapFollower, RequestPacer
from memgs_ros.core.runtime.telemetry_fields import ViewFields
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
from memgs_ros.ros.service_calls import PacedRequests
from memgs_ros.viz import RerunTarget
from memgs_ros.viz.live_view import LiveView

# The stats plotted by default: map size and training progress, tracking speed, memory.
STATS_NODES = GRAPH
_FRAMES_KEPT = 30  # source frames held to pair with a render of the same stamp (renders lag < 1 s)
_RESYNC_INTERVAL_S = 2.0  # least time between full-map requests while out of step


CONFIGS = NODE_CONFIGS["rerun_bridge"]


class ViewStats(NodeStats, ViewFields):
    stats_name = "rerun_bridge"


class RerunBridgeNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:  # rclpy Node's keyword arguments
        super().__init__("rerun_bridge", **node_kwargs)
        v = declare_config(self, RerunBridgeParams, "")
        self.stats_keys: set[str] | None = (None if v.stats_keys.strip() == "*"
                                            else {k.strip() for k in v.stats_keys.split(",") if k.strip()})
        try:
            target = RerunTarget(spawn=v.spawn, connect_url=v.connect_url,
                                 save_path=FsPath(v.save_path) if v.save_path else None)
        except ConfigError as err:
            raise ConfigError(f"rerun_bridge: {err} (parameters spawn, connect_url, save_path)") from err
        target.check()
        from memgs_ros.viz import rerun_log  # imports rerun: only after the check above

        rec = target.open(v.application_id, recording_name=v.recording_name or self.get_namespace().strip("/")
                          or "memgs")
        rerun_log.log_world(rec)
        rerun_log.send_blueprint(rec, with_views=True)
        self.frames: OrderedDict[int, Image] = OrderedDict()  # stamp -> source colour message
        self.map = MapFollower()
        self.logged_version: tuple[int, int, int] | None = None  # MapFollower.version of the last map logged

        self.create_subscription(PoseStamped, "memgs/pose", self.on_pose, qos.reliable(100))
        self.create_subscription(Path, "memgs/path", self.on_path, qos.reliable(5))
        kf = qos.keyframes()  # TRANSIENT_LOCAL as the tracker publishes them: a late bridge gets the latest
        self.create_subscription(CameraInfo, "memgs/keyframe/camera_info", self.on_camera_info, kf)
        self.create_subscription(PoseStamped, "memgs/keyframe/pose", self.on_keyframe, kf)
        for topic in ("memgs/keyframe/refined_poses", "memgs/keyframe/loop_corrected_poses"):
            self.create_subscription(Path, topic, self.on_keyframes_moved, qos.reliable(20))
        if v.log_frames:
            self.create_subscription(Image, v.color_topic, self.on_frame, qos.sensor())
        self.create_subscription(Image, "memgs/render/color", self.on_render, qos.reliable(2))
        self.create_subscription(PointCloud2, "memgs/map/delta", self.on_delta, qos.reliable(50))
        # Full maps: the mapper's snapshots take sequence numbers of their own (a delta stream
        # with a snapshot in it has a gap without it); the merger's map repairs anything else.
        self.create_subscription(PointCloud2, "memgs/mapper/snapshot", self.on_full_map, qos.latched())
        self.create_subscription(PointCloud2, "memgs/map/gaussians", self.on_full_map, qos.latched())
        for node in STATS_NODES:
            self.create_subscription(DiagnosticArray, f"memgs/{node}/stats", self._stats_of(node), qos.reliable(5))
        # Last: the runner takes memgs/rerun_bridge/stats appearing to mean the node listens.
        self.stats = ViewStats(self)
        self.view = LiveView(rerun_log, rec, self.stats, v.frustum_size_m, v.jpeg_quality, v.log_sh,
                             stamps_kept=4 * _FRAMES_KEPT)
        self.full_maps = PacedRequests(self, "memgs/merger/publish_map", self.stats, RequestPacer(_RESYNC_INTERVAL_S),
                                       ViewStats.map_requests, "map_request",
                                       "the merger did not take a full-map request", one_at_a_time=True)
        if v.map_period_s > 0:
            self.create_timer(v.map_period_s, self.log_map)
        sinks = ", ".join(s for s in (v.spawn and "spawned viewer", v.connect_url, v.save_path) if s)
        self.get_logger().info(f"logging to Rerun: {sinks}")

    # ------------------------------------------------------------------ callbacks
    def on_pose(self, msg: PoseStamped) -> None:
        self.view.pose(stamp_to_ns(msg.header.stamp), pose_to_matrix(msg.pose))

    def on_path(self, msg: Path) -> None:
        if len(msg.poses) >= 2:
            self.view.trajectory(np.stack([pose_to_matrix(p.pose) for p in msg.poses]))

    def on_camera_info(self, msg: CameraInfo) -> None:
        try:
            self.view.set_camera(decode_camera_info(msg))
        except (MessageError, DataError) as err:
            self.stats.problem("bad_camera_info", f"camera_info ignored: {err}")

    def on_keyframe(self, msg: PoseStamped) -> None:
        self.view.keyframe(stamp_to_ns(msg.header.stamp), pose_to_matrix(msg.pose))

    def on_keyframes_moved(self, msg: Path) -> None:
        self.view.keyframes_moved([(stamp_to_ns(p.header.stamp), pose_to_matrix(p.pose)) for p in msg.poses])

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
        value = self.view.views(stamp, render, frame)
        if value is not None:
            self.stats.psnr_db = round(value, 2)

    def on_delta(self, msg: PointCloud2) -> None:
        m = decode_map_message(msg, self.stats)
        if m is None:
            return
        self.map.on_delta(m)
        if self.map.resyncing:
            self.full_maps.ask(out_of_step=True)

    def on_full_map(self, msg: PointCloud2) -> None:
        m = decode_map_message(msg, self.stats)
        if m is not None and self.map.on_full_map(m) is not None:
            self.full_maps.pacer.answered()
            self.log_map()  # rare (on request, the merger's period, the end of a run): show it now
        if self.map.resyncing:
            self.full_maps.ask(out_of_step=True)

    def log_map(self) -> None:
        """Log the followed map if it changed since the last one logged."""
        if self.map.resyncing:
            self.full_maps.ask(out_of_step=True)
        if not self.map.in_step or self.map.version == self.logged_version:
            return
        self.view.map(self.map.replica.records)
        self.logged_version = epoch, seq, n = self.map.version
        self.stats.map_epoch, self.stats.map_seq, self.stats.map_gaussians = epoch, seq, n

    def _stats_of(self, node: str) -> Callable[[DiagnosticArray], None]:
        return lambda m: self.on_stats(node, m)

    def on_stats(self, node: str, msg: DiagnosticArray) -> None:
        numbers = self.view.log.numeric_values(stats_values(msg), self.stats_keys)
        if numbers:
            self.view.scalars(node, numbers)

    def close(self) -> None:
        self.view.close()


def main(args: list[str] | None = None) -> int:
    return run_node(RerunBridgeNode, "rerun_bridge", args)


if __name__ == "__main__":
    sys.exit(main())
