"""merger node: the consolidated global map, built from the mapper's deltas (may run elsewhere).

Subscribes: ``memgs/map/delta`` (reliable; ``delta_topic`` names it, e.g. behind a radio bridge) and
``memgs/mapper/snapshot`` (latched) from the mapper,
``memgs/merger/view_pose`` (PoseStamped render requests). Publishes ``memgs/map/gaussians`` (latched
full map in the delta protocol's layout, on request and every ``publish_period_s``) and with it
``memgs/map/points`` (latched: the map as x, y, z, rgb, opacity points for RViz and Foxglove),
``memgs/merger/render/{color,depth,camera_info}`` and ``memgs/merger/stats``. Services: ``memgs/save_map``
(std_srvs/Trigger: write the PLY atomically, answers its path; with ``bundle_dir`` also a map bundle,
``nodes/merger/bundles.py``, whose path then comes first: a ``MapAnswer``) and
``memgs/merger/publish_map``.
Saves periodically and on shutdown.

A gap in the delta sequence, a late start or a count mismatch triggers a resync: deltas are
buffered, a snapshot is requested from the mapper (``memgs/mapper/publish_snapshot``), loaded, and
the buffered deltas newer than it are replayed.

A map message that cannot be decoded (missing fields, rows of the wrong size, a malformed META
row) is dropped and counted as ``problem.bad_map_message``; removals of ids the replica does not
hold are ignored and counted as ``problem.unknown_removal`` (one warning per kind).

The merger holds the map as numpy records (no training state) and loads torch and the rasterizer
only on its first view request, on a render thread of its own (:class:`ViewRenderer`: deltas keep
flowing while a view renders); its stats report ``map_bytes``, ``render_cache_bytes`` and
``buffered_deltas``. The deltas are followed by :class:`MapFollower`, as the Rerun bridge does.

A managed node (ros/lifecycle.py): inactive, it keeps following and serving the map, so a paused
graph's map stays saved and viewable; deactivating the tracker and mapper is what pauses mapping.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import ReentrantCallbackGroup
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.map_io.answers import MapAnswer
from memgs_ros.core.map_io.follower import DeltaOutcome, MapFollower, RequestPacer
from memgs_ros.core.map_io.map_delta import MessageKind
from memgs_ros.core.map_io.ply import save_ply
from memgs_ros.core.map_io.view_renderer import ViewRenderer
from memgs_ros.errors import MemgsError
from memgs_ros.nodes.merger.bundles import BundleAssembler
from memgs_ros.nodes.merger.outputs import ViewOutbox
from memgs_ros.nodes.merger.stats import MergerStats
from memgs_ros.nodes.params import NODE_CONFIGS, MergerParams
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import pose_to_matrix, stamp_to_ns
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.lifecycle import ManagedNode
from memgs_ros.ros.map_loading import GraphMapLoader
from memgs_ros.ros.map_messages import decode_map_message, full_map_message, viewer_cloud_message
from memgs_ros.ros.node_main import run_node
from memgs_ros.ros.service_calls import PacedRequests

CONFIGS = NODE_CONFIGS["merger"]
START_ASK_AFTER_S = 2.0  # a merger that heard no delta this long after its start asks for the map


class MergerNode(ManagedNode):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("merger", **node_kwargs)
        self.params = v = declare_config(self, MergerParams, "")
        self.niceness = v.niceness  # applied by run_node to this node's process
        self.start_lifecycle(v.autostart)

    def configure_node(self) -> None:
        v = self.params
        self.map_path, self.world_frame = Path(v.map_path), v.world_frame
        self.map = MapFollower(v.max_buffered_deltas)
        render_camera = PinholeCamera(v.render_width, v.render_height, v.render_fx, v.render_fy, v.render_cx,
                                      v.render_cy)
        self.renderer = ViewRenderer(render_camera, sh_degree=3)
        self.stats = MergerStats(self)
        # The map's deltas need no compiled code; the renders on request load theirs when first asked.
        self.stats.kernels_warm = 1
        self._saved_version: tuple[int, int] | None = None  # (epoch, seq) of the map saved and published
        self._published_version: tuple[int, int] | None = self._saved_version
        self.pub_map = self.create_publisher(PointCloud2, "memgs/map/gaussians", qos.latched())
        self.pub_points = self.create_publisher(PointCloud2, "memgs/map/points", qos.latched())
        self.views = ViewOutbox(self, self.stats, "memgs/merger/render", render_camera)
        self.create_subscription(PointCloud2, v.delta_topic, self.on_delta, qos.reliable(50))
        self.create_subscription(PointCloud2, "memgs/mapper/snapshot", self.on_snapshot, qos.latched())
        self.create_subscription(PoseStamped, "memgs/merger/view_pose", self.on_view_request, qos.reliable(5))
        pacer = RequestPacer(v.resync_interval_s, max_backoff=8, start_after_s=START_ASK_AFTER_S,
                             started_s=time.monotonic())
        self.snapshots = PacedRequests(self, "memgs/mapper/publish_snapshot", self.stats, pacer,
                                       MergerStats.snapshot_requests, "snapshot_request",
                                       "the mapper did not take a snapshot request")
        self.bundles, _ = BundleAssembler(self, v, self.stats), GraphMapLoader(self)  # save and load bundles
        self.create_service(Trigger, "memgs/save_map", self.on_save, callback_group=ReentrantCallbackGroup())
        self.create_service(Trigger, "memgs/merger/publish_map", self.on_publish_map)
        if v.save_period_s > 0:
            self.create_timer(v.save_period_s, self._save_periodic)
        if v.publish_period_s > 0:
            self.create_timer(v.publish_period_s, lambda: self.publish_map(force=False))
        self.create_timer(0.5, self._ask_snapshot)  # while out of step, or once at a start that heard no delta

    # ------------------------------------------------------------------ sync
    def on_delta(self, msg: PointCloud2) -> None:
        m = decode_map_message(msg, self.stats)
        if m is None:
            return
        self.stats.deltas += 1
        self.stats.delta_bytes += len(msg.data)
        self.snapshots.pacer.heard()
        self._report(self.map.on_delta(m))

    def on_snapshot(self, msg: PointCloud2) -> None:
        m = decode_map_message(msg, self.stats)
        if m is None or m.kind is not MessageKind.SNAPSHOT:
            return
        self.stats.snapshots += 1
        replayed = self.map.on_full_map(m)
        if replayed is not None:
            self.snapshots.pacer.answered()
            for outcome in replayed:
                self._report(outcome)
        self._gauges()

    def _report(self, outcome: DeltaOutcome) -> None:
        """Count what a delta did; one that put the replica out of step asks for a snapshot."""
        self._gauges()
        if outcome.unknown_removals:
            # The sender removed Gaussians this replica never had: harmless if the counts still
            # agree (a mismatch resyncs), but it means the two maps drifted apart once.
            self.stats.problem("unknown_removal", f"delta {outcome.seq} removes {outcome.unknown_removals} "
                                                  "id(s) the replica does not hold; ignored")
        if outcome.lost_step and outcome.status is not None:
            self.stats.resync[outcome.status.value] += 1
            self.get_logger().warning(f"delta {outcome.seq}: {outcome.status.value} at replica seq "
                                      f"{self.map.replica.seq}; resynchronising")
            self._ask_snapshot()

    def _ask_snapshot(self) -> None:  # the snapshot arrives on its topic
        self.snapshots.ask(self.map.resyncing)

    def _gauges(self) -> None:
        self.stats.replica(self.map.replica, self.map.resyncing, self.map.buffered, self.renderer.cache_bytes)

    # ------------------------------------------------------------------ outputs
    def save(self) -> Path | None:
        """Write the PLY atomically if the map changed since the last save."""
        if not self.map.replica.synced:
            return None
        version = (self.map.replica.seq, len(self.map.replica))
        if version != self._saved_version or not self.map_path.exists():
            save_ply(self.map.replica.records, self.map_path)
            self._saved_version = version
            self.stats.saves += 1
        return self.map_path

    def _save_periodic(self) -> None:
        """The timer's save; a full disk is counted and retried, never ends the node (the last PLY stays)."""
        try:
            self.save()
        except (MemgsError, OSError) as err:
            self.stats.problem("save_failed", f"could not save {self.map_path}: {err}; the previous file stays")

    async def on_save(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        try:
            path = self.save()
        except (MemgsError, OSError) as err:
            res.success, res.message = False, f"could not save {self.map_path}: {err}"
            return res
        bundle = await self.bundles.save(self.map.replica.records, self.world_frame) if path is not None else None
        res.success = path is not None
        res.message = (MapAnswer(self.map.replica.seq, len(self.map.replica), ply=str(path.resolve()),
                                 bundle=None if bundle is None else str(bundle)).message()
                       if path else "no map received yet")
        return res

    def publish_map(self, force: bool = True) -> None:
        """Publish the whole map (latched); the periodic call skips an unchanged map."""
        version = (self.map.replica.seq, len(self.map.replica))
        if not self.map.replica.synced or (not force and version == self._published_version):
            return
        self._published_version = version
        now_ns = self.get_clock().now().nanoseconds
        self.pub_map.publish(full_map_message(self.map.replica, now_ns, self.world_frame))
        self.pub_points.publish(viewer_cloud_message(self.map.replica, now_ns, self.world_frame))

    def on_publish_map(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        self.publish_map()
        res.success, res.message = True, MapAnswer(self.map.replica.seq, len(self.map.replica)).message()
        return res

    def on_view_request(self, msg: PoseStamped) -> None:
        """Render on the renderer's thread (torch loads there on the first request: ~200 MB not taken before)."""
        if len(self.map.replica) == 0:
            return
        self.views.when_done(self.renderer.render(self.map.replica.records, self.map.version,
                                                  pose_to_matrix(msg.pose), stamp_to_ns(msg.header.stamp)))

    def close_node(self) -> None:
        self.renderer.close(timeout_s=5.0)
        path = self.save()
        if path is not None:
            self.get_logger().info(f"map saved to {path} ({len(self.map.replica)} Gaussians)")


def main(args: list[str] | None = None) -> int:
    return run_node(MergerNode, "merger", args)


if __name__ == "__main__":
    sys.exit(main())
