"""merger node: the consolidated global map, built from the mapper's deltas (may run elsewhere).

Subscribes: ``memgs/map/delta`` (reliable) and ``memgs/mapper/snapshot`` (latched) from the mapper,
``memgs/merger/view_pose`` (PoseStamped render requests). Publishes ``memgs/map/gaussians`` (latched
full map with a packed ``rgb`` colour field for viewers, on request and every ``publish_period_s``),
``memgs/merger/render/{color,depth}`` and ``memgs/merger/stats``. Services: ``memgs/save_map``
(std_srvs/Trigger: write the PLY atomically, answers its path) and ``memgs/merger/publish_map``.
Saves periodically and on shutdown.

A gap in the delta sequence, a late start or a count mismatch triggers a resync: deltas are
buffered, a snapshot is requested from the mapper (``memgs/mapper/publish_snapshot``), loaded, and
the buffered deltas newer than it are replayed.

A map message that cannot be decoded (missing fields, rows of the wrong size, a malformed META
row) is dropped and counted as ``problem.bad_map_message``; removals of ids the replica does not
hold are ignored and counted as ``problem.unknown_removal`` (one warning per kind).

The merger holds the map as numpy records (no training state) and loads torch and the rasterizer
only on its first view request; its stats report ``map_bytes``, ``render_cache_bytes`` and
``buffered_deltas``.
"""
from __future__ import annotations

import sys
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import Image, PointCloud2
from std_srvs.srv import Trigger

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.maps.map_delta import ApplyStatus, MapMessage, MapReplica, MessageKind, decode, encode
from memgs_ros.core.maps.ply import save_ply
from memgs_ros.errors import MemgsError, MessageError
from memgs_ros.nodes.params import NODE_CONFIGS, MergerParams
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import (
    depth_to_image,
    numpy_to_image,
    pointcloud2_to_structured,
    pose_to_matrix,
    stamp_to_ns,
    structured_to_pointcloud2,
)
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats
from memgs_ros.ros.node_main import run_node

if TYPE_CHECKING:
    from memgs_ros.core.raster import Gaussians


CONFIGS = NODE_CONFIGS["merger"]


class MergerNode(Node):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("merger", **node_kwargs)
        v = declare_config(self, MergerParams, "")
        self.niceness = v.niceness  # applied by run_node to this node's process
        self.map_path = Path(v.map_path)
        self.save_period, self.publish_period = v.save_period_s, v.publish_period_s
        self.resync_interval, self.max_buffered = v.resync_interval_s, v.max_buffered_deltas
        self.world_frame, self.drop_every = v.world_frame, v.fault_drop_every_nth_delta
        self.render_camera = PinholeCamera(v.render_width, v.render_height, v.render_fx, v.render_fy,
                                           v.render_cx, v.render_cy)

        self.replica = MapReplica()
        self.stats = NodeStats(self, "merger")
        # The map's deltas need no compiled code; the renders on request load theirs when first asked.
        self.stats.gauges["kernels_warm"] = 1
        self.buffer: deque[MapMessage] = deque(maxlen=self.max_buffered)
        self.resyncing = False
        self._last_request = 0.0
        self._requests_unanswered = 0  # snapshot requests since the last snapshot applied (backoff)
        self._started = time.monotonic()
        self._heard_delta = False
        self._asked_at_start = False
        # (seq, size, tensors to render): the map's rows as rasterizer inputs, no training state
        self._render_cache: tuple[int, int, Gaussians] | None = None  # torch: loaded lazily
        self._saved_version: tuple[int, int] | None = None
        self._published_version: tuple[int, int] | None = None

        self.pub_map = self.create_publisher(PointCloud2, "memgs/map/gaussians", qos.latched())
        self.pub_color = self.create_publisher(Image, "memgs/merger/render/color", qos.reliable(2))
        self.pub_depth = self.create_publisher(Image, "memgs/merger/render/depth", qos.reliable(2))
        self.create_subscription(PointCloud2, "memgs/map/delta", self.on_delta, qos.reliable(50))
        self.create_subscription(PointCloud2, "memgs/mapper/snapshot", self.on_snapshot, qos.latched())
        self.create_subscription(PoseStamped, "memgs/merger/view_pose", self.on_view_request, qos.reliable(5))
        self.snapshot_client = self.create_client(Trigger, "memgs/mapper/publish_snapshot")
        self.create_service(Trigger, "memgs/save_map", self.on_save)
        self.create_service(Trigger, "memgs/merger/publish_map", self.on_publish_map)
        if self.save_period > 0:
            self.create_timer(self.save_period, self._save_periodic)
        if self.publish_period > 0:
            self.create_timer(self.publish_period, lambda: self.publish_map(force=False))
        self.create_timer(0.5, self._retry_resync)

    # ------------------------------------------------------------------ sync
    def _decode(self, msg: PointCloud2) -> MapMessage | None:
        try:
            return decode(pointcloud2_to_structured(msg))
        except MessageError as err:
            self.stats.problem("bad_map_message", f"map message refused: {err}")
            return None

    def on_delta(self, msg: PointCloud2) -> None:
        m = self._decode(msg)
        if m is None:
            return
        self.stats.counters["deltas"] += 1
        self._heard_delta = True
        self.stats.counters["delta_bytes"] += len(msg.data)
        if self.drop_every and self.stats.counters["deltas"] % self.drop_every == 0:
            self.stats.counters["fault_dropped_deltas"] += 1
            return
        if self.resyncing:
            self.buffer.append(m)
            return
        self._apply(m)

    def on_snapshot(self, msg: PointCloud2) -> None:
        m = self._decode(msg)
        if m is None or m.kind is not MessageKind.SNAPSHOT:
            return
        status = self.replica.apply(m)
        self.stats.counters["snapshots"] += 1
        if status is not ApplyStatus.APPLIED:
            return
        self.resyncing = False
        self._requests_unanswered = 0
        pending = sorted((d for d in self.buffer if d.epoch == self.replica.epoch and d.seq > self.replica.seq),
                         key=lambda d: d.seq)
        self.buffer.clear()
        for d in pending:
            if not self._apply(d):
                break
        self._gauges()

    def _apply(self, m: MapMessage) -> bool:
        """Apply one delta; on a gap, late start or mismatch start a resync. True while in step."""
        unknown = self.replica.unknown_removals
        status = self.replica.apply(m)
        self._gauges()
        if self.replica.unknown_removals > unknown:
            # The sender removed Gaussians this replica never had: harmless if the counts still
            # agree (a mismatch resyncs below), but it means the two maps drifted apart once.
            self.stats.problem("unknown_removal", f"delta {m.seq} removes {self.replica.unknown_removals - unknown} "
                                                  "id(s) the replica does not hold; ignored")
        if status in (ApplyStatus.APPLIED, ApplyStatus.STALE):
            return True
        self.stats.counters[f"resync.{status.value}"] += 1
        self.get_logger().warning(f"delta {m.seq}: {status.value} at replica seq {self.replica.seq}; resynchronising")
        self.resyncing = True
        self.buffer.append(m)
        self._request_snapshot()
        return False

    def _request_snapshot(self) -> None:
        now = time.monotonic()
        # Backoff: a snapshot is megabytes, and each request makes the mapper publish a new one into
        # its one-deep latched history, replacing one still on its way; asking every second while
        # a busy mapper answers late could keep replacing it before it ever arrives whole.
        wait = self.resync_interval * min(2 ** self._requests_unanswered, 8)
        if now - self._last_request < wait or not self.snapshot_client.service_is_ready():
            return
        self._last_request = now
        self._requests_unanswered += 1
        self._ask_snapshot()

    def _retry_resync(self) -> None:
        if self.resyncing:
            self._request_snapshot()
        # A merger (re)started after the mapper went quiet (finished, or idle) would wait for a
        # delta that never comes: ask once for the current map.
        elif (not self._heard_delta and not self._asked_at_start and time.monotonic() - self._started > 2.0
              and self.snapshot_client.service_is_ready()):
            self._asked_at_start = True
            self._last_request = time.monotonic()
            self._ask_snapshot()

    def _ask_snapshot(self) -> None:
        """Ask the mapper for a snapshot (it arrives on the snapshot topic); a refusal or a failed
        call is counted and logged (``problem.snapshot_request``), not dropped with its future."""
        def answered(future: Future) -> None:
            try:  # rclpy's result() never waits: it returns what was set (None when cancelled) or raises
                res = future.result()
            except Exception as err:  # noqa: BLE001 - counted and logged below
                why = f"{type(err).__name__}: {err}"
            else:
                if res is None or res.success:
                    return
                why = res.message
            self.stats.problem("snapshot_request", f"the mapper did not take a snapshot request: {why}")

        self.snapshot_client.call_async(Trigger.Request()).add_done_callback(answered)
        self.stats.counters["snapshot_requests"] += 1

    def _gauges(self) -> None:
        self.stats.gauges["seq"] = self.replica.seq
        self.stats.gauges["epoch"] = self.replica.epoch
        self.stats.gauges["gaussians"] = len(self.replica)
        self.stats.gauges["resyncing"] = int(self.resyncing)
        self.stats.gauges["unknown_removals"] = self.replica.unknown_removals
        # What the merger holds: the replica's rows, deltas buffered during a resync, and the
        # render inputs of the last view request (no training state: no gradients, no Adam).
        self.stats.gauges["map_bytes"] = self.replica.records.nbytes if len(self.replica) else 0
        self.stats.gauges["buffered_deltas"] = len(self.buffer)
        cache = self._render_cache
        self.stats.gauges["render_cache_bytes"] = 0 if cache is None else sum(
            t.numel() * t.element_size() for t in cache[2])

    # ------------------------------------------------------------------ outputs
    def save(self) -> Path | None:
        """Write the PLY atomically if the map changed since the last save."""
        if not self.replica.synced:
            return None
        version = (self.replica.seq, len(self.replica))
        if version != self._saved_version or not self.map_path.exists():
            save_ply(self.replica.records, self.map_path)
            self._saved_version = version
            self.stats.counters["saves"] += 1
        return self.map_path

    def _save_periodic(self) -> None:
        """The timer's save. A full or read-only disk must not end the node (the timer's exception
        would, losing the map it holds): counted, logged once, retried next period; the last
        complete PLY stays (atomic write)."""
        try:
            self.save()
        except (MemgsError, OSError) as err:
            self.stats.problem("save_failed", f"could not save {self.map_path}: {err}; the previous file stays")

    def on_save(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        try:
            path = self.save()
        except (MemgsError, OSError) as err:
            res.success, res.message = False, f"could not save {self.map_path}: {err}"
            return res
        res.success = path is not None
        res.message = (f"{path.resolve()} gaussians={len(self.replica)} seq={self.replica.seq}" if path
                       else "no map received yet")
        return res

    def publish_map(self, force: bool = True) -> None:
        """Publish the whole map (latched); the periodic call skips an unchanged map."""
        version = (self.replica.seq, len(self.replica))
        if not self.replica.synced or (not force and version == self._published_version):
            return
        self._published_version = version
        rows = encode(MessageKind.SNAPSHOT, self.replica.seq, len(self.replica), self.replica.records,
                      np.zeros(0, np.int64), sh_degree=3, epoch=self.replica.epoch, rgb=True)
        self.pub_map.publish(structured_to_pointcloud2(rows, self.get_clock().now().nanoseconds, self.world_frame))

    def on_publish_map(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        self.publish_map()
        res.success, res.message = True, f"gaussians={len(self.replica)} seq={self.replica.seq}"
        return res

    def on_view_request(self, msg: PoseStamped) -> None:
        if len(self.replica) == 0:
            return
        # torch and the rasterizer load on the first view request: a merger that only holds,
        # publishes and saves the map stays without them (~200 MB less resident memory).
        import torch

        from memgs_ros.core.mapping.gaussians import render_tensors
        from memgs_ros.core.raster import rasterize

        key = (self.replica.seq, len(self.replica))
        if self._render_cache is None or self._render_cache[:2] != key:
            self._render_cache = (*key, render_tensors(self.replica.records))
        T_cw = torch.from_numpy(np.linalg.inv(pose_to_matrix(msg.pose))).float()
        with torch.no_grad():
            out = rasterize(self._render_cache[2], T_cw, self.render_camera, sh_degree=3)
        stamp = stamp_to_ns(msg.header.stamp)
        rgb = (out.color.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        self.pub_color.publish(numpy_to_image(np.ascontiguousarray(rgb), "rgb8", stamp, "render_camera"))
        self.pub_depth.publish(depth_to_image(out.depth.numpy().astype(np.float32), "32FC1", stamp, "render_camera"))
        self.stats.counters["renders"] += 1

    def on_shutdown(self) -> None:
        path = self.save()
        if path is not None:
            self.get_logger().info(f"map saved to {path} ({len(self.replica)} Gaussians)")


def main(args: list[str] | None = None) -> int:
    return run_node(MergerNode, "merger", args)


if __name__ == "__main__":
    sys.exit(main())
