"""mapper node: translates keyframes, poses and requests into commands of a ``MappingSession``
(memgs_ros/core/session.py, the one owner of the Gaussian map) and publishes what it returns.

Subscribes (reliable): ``memgs/keyframe/{color,depth,camera_info,pose}`` from the tracker and
``memgs/keyframe/seeds`` from the sampler (one stamp per keyframe), ``memgs/keyframe/refined_poses``
(Path), ``memgs/pose`` (latest tracked pose, for the live view), ``memgs/render/view_pose``
(render requests), ``memgs/tracker/processed`` (lockstep handshake).
Publishes: ``memgs/map/delta`` (PointCloud2, see core/map_delta.py), ``memgs/mapper/snapshot``
(latched full map), ``memgs/render/{color,depth,camera_info}``, ``memgs/frame_ack`` (lockstep),
``memgs/mapper/stats``. Services: ``memgs/mapper/publish_snapshot`` and ``memgs/mapper/finish``
(std_srvs/Trigger; finish stops training, flushes every change and answers ``seq=<n> gaussians=<n>``).

With ``checkpoint_path`` set the session's state is written there (core/checkpoint.py, atomic)
every ``checkpoint_period_s``, when finished and at shutdown; a mapper started with an existing
checkpoint resumes from it, announces a new delta epoch and publishes a snapshot, so the merger
replaces its copy with the resumed map. Lockstep: each frame's acknowledgement waits for the
session to train ``lockstep_iterations`` steps, so a lockstep replay is deterministic.
"""
from __future__ import annotations

import pathlib
import secrets
import sys
import time
from collections import deque

import numpy as np
import torch
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from memgs_ros.core import checkpoint
from memgs_ros.core.map_delta import message_dtype
from memgs_ros.core.mapping import MappingConfig
from memgs_ros.core.merge import MergeConfig
from memgs_ros.core.runtime import configure_cpu_runtime
from memgs_ros.core.session import KeyframeInput, MappingSession
from memgs_ros.errors import DataError, MessageError
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import (camera_to_camera_info, depth_to_image, make_header, numpy_to_image,
                                  pointcloud2_to_structured, pose_to_matrix, stamp_to_ns, structured_to_pointcloud2)
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats
from memgs_ros.ros.keyframe_bundle import KeyframeBundleError, decode_keyframe_images
from memgs_ros.ros.node_main import run_node
from memgs_ros.ros.params import declare
from memgs_ros.ros.seed_cloud import decode_seeds
from memgs_ros.ros.stamp_sync import StampBundler

MISSED_AFTER_S = 60.0  # an announced keyframe still incomplete this long after is counted missed


class MapperNode(Node):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("mapper", **node_kwargs)
        self.mode = declare(self, "mode", "rgbd", "camera mode (mono: keyframes carry no depth)",
                            choices=("rgbd", "mono"))
        self.depth_scale = declare(self, "depth_scale", 1000.0, "16UC1 keyframe depth units per metre (the "
                                   "tracker publishes 32FC1 metres)", range=(1e-3, 1e6))
        self.cfg: MappingConfig = declare_config(self, MappingConfig, "mapping")
        merge_cfg: MergeConfig = declare_config(self, MergeConfig, "merge")
        device = declare(self, "device", "auto", "torch device for the map: auto (CUDA when present), cpu, cuda, cuda:N")
        self.lockstep = declare(self, "lockstep", False,
                                "train a fixed number of iterations per frame and acknowledge each (deterministic replay)")
        self.lockstep_iters = declare(self, "lockstep_iterations", 10, "training iterations per frame in lockstep mode",
                                      range=(0, 10000))
        self.final_iters = declare(self, "final_iterations", 0, "extra training iterations run by the finish service "
                                   "before the final flush", range=(0, 10**7))
        self.delta_rate = declare(self, "delta_rate_hz", 1.0, "map deltas per second", range=(0.01, 100.0))
        self.delta_budget = declare(self, "delta_budget_kbytes_per_s", 500.0, "link budget for map deltas; the largest "
                                    "changes go first, the rest wait (the final flush ignores it)", range=(1.0, 1e7))
        delta_tol = declare(self, "delta_tolerance", 1e-3, "send a Gaussian again only when a parameter moved more "
                            "than this (m, or pre-activation units); the final flush is exact", range=(0.0, 10.0))
        snapshot_period = declare(self, "snapshot_period_s", 0.0, "publish a full snapshot this often (0 = only on "
                                  "request)", range=(0.0, 1e6))
        render_rate = declare(self, "render_rate_hz", 1.0, "live view renders per second (0 = off)", range=(0.0, 60.0))
        self.world_frame = declare(self, "world_frame", "map", "frame id of published maps and poses")
        ack_topic = declare(self, "ack_topic", "memgs/frame_ack", "lockstep acknowledgement topic (to the player)")
        ckpt_path = declare(self, "checkpoint_path", "", "file for map + keyframe checkpoints (.npz); empty = none")
        ckpt_period = declare(self, "checkpoint_period_s", 30.0, "write a checkpoint this often while the map "
                              "changes (0 = only at finish/shutdown)", range=(0.0, 1e6))
        resume = declare(self, "resume", True, "start from the checkpoint at checkpoint_path when one exists")
        insert_queue = declare(self, "insert_queue", 4, "free-running: complete keyframes waiting for insertion; when "
                               "full the oldest is dropped and counted (problem.keyframe_overload)", range=(1, 1000))

        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device == "cpu":
            configure_cpu_runtime()
        self.stats = NodeStats(self, "mapper")
        self.ckpt_path = pathlib.Path(ckpt_path).expanduser() if ckpt_path else None
        resumed = self._read_checkpoint() if resume and self.ckpt_path is not None and self.ckpt_path.exists() else None
        # A new delta epoch every start: a merger that held the map of an earlier life resynchronises.
        self.session = MappingSession(self.cfg, device, merge_cfg=merge_cfg, free_running=not self.lockstep,
                                      insert_queue=insert_queue, delta_tolerance=delta_tol,
                                      delta_epoch=secrets.randbits(32), checkpoint=resumed)
        self.latest_pose: PoseStamped | None = None
        self.awaiting_keyframes: set[int] = set()  # lockstep: announced, not yet complete
        # (arrival time, stamp) of announced keyframes: one whose parts have not all arrived 60 s
        # later was lost on the way (under CPU overload parts can arrive > 10 s late).
        self._announced: deque[tuple[float, int]] = deque(maxlen=10_000)
        self._complete: deque[int] = deque(maxlen=4096)  # stamps of recent complete bundles ...
        self._complete_set: set[int] = set()  # ... as a set (replays of the keyframe topics)
        for stamp in sorted(self.session.resumed_stamps)[-4096:]:
            self._remember(stamp)

        parts = {"color", "camera_info", "pose", "seeds"} | ({"depth"} if self.mode == "rgbd" else set())
        self.bundler = StampBundler(parts, max_pending=16)
        self.pub_delta = self.create_publisher(PointCloud2, "memgs/map/delta", qos.reliable(50))
        self.pub_snapshot = self.create_publisher(PointCloud2, "memgs/mapper/snapshot", qos.latched())
        self.pub_color = self.create_publisher(Image, "memgs/render/color", qos.reliable(2))
        self.pub_depth = self.create_publisher(Image, "memgs/render/depth", qos.reliable(2))
        self.pub_info = self.create_publisher(CameraInfo, "memgs/render/camera_info", qos.reliable(2))
        self.pub_ack = self.create_publisher(Header, ack_topic, qos.reliable(100))
        io = MutuallyExclusiveCallbackGroup()  # keyframe parts, poses and lockstep stay ordered
        kfq = qos.keyframes()  # a resumed mapper gets the keyframes sent while it was down
        topics = {"color": Image, "camera_info": CameraInfo, "pose": PoseStamped, "seeds": PointCloud2,
                  **({"depth": Image} if self.mode == "rgbd" else {})}
        for part, msg_type in topics.items():
            self.create_subscription(msg_type, f"memgs/keyframe/{part}", lambda m, p=part: self._part(p, m), kfq,
                                     callback_group=io)
        self.create_subscription(Path, "memgs/keyframe/refined_poses", self.on_refined, qos.reliable(20),
                                 callback_group=io)
        self.create_subscription(Header, "memgs/tracker/processed", self.on_processed, qos.reliable(100),
                                 callback_group=io)
        self.create_subscription(PoseStamped, "memgs/pose", self.on_pose, qos.reliable(5))
        self.create_subscription(PoseStamped, "memgs/render/view_pose", self._render, qos.reliable(5))
        self.create_service(Trigger, "memgs/mapper/publish_snapshot", self.on_snapshot_request)
        self.create_service(Trigger, "memgs/mapper/finish", self.on_finish, callback_group=MutuallyExclusiveCallbackGroup())
        out = MutuallyExclusiveCallbackGroup()  # deltas and snapshots leave in seq order
        self.create_timer(1.0 / self.delta_rate, self.send_delta, callback_group=out)
        if snapshot_period > 0:
            self.create_timer(snapshot_period, self.publish_snapshot, callback_group=out)
        if self.ckpt_path is not None and ckpt_period > 0:
            self.create_timer(ckpt_period, self.save_checkpoint, callback_group=MutuallyExclusiveCallbackGroup())
        if resumed is not None:
            self.publish_snapshot()  # latched: the merger takes the resumed map and its epoch
        if render_rate > 0:
            self.create_timer(1.0 / render_rate, lambda: self.latest_pose and self._render(self.latest_pose))
        self.create_timer(0.1, self._sync_stats)
        self.create_timer(1.0, self._count_missed_keyframes)
        self.get_logger().info(f"mapper on {device}, {'lockstep' if self.lockstep else 'free-running'} training")

    # ------------------------------------------------------------------ checkpoints
    def _read_checkpoint(self) -> checkpoint.MapperCheckpoint | None:
        """The checkpoint to resume from; a file that cannot be read is moved aside, never overwritten."""
        assert self.ckpt_path is not None
        try:
            ck = checkpoint.load(self.ckpt_path)
        except DataError as err:
            aside = self.ckpt_path.with_name(f"{self.ckpt_path.name}.unreadable-{int(time.time())}")
            self.ckpt_path.replace(aside)
            self.get_logger().error(f"cannot resume: {err}; moved it to {aside} and starting an empty map")
            return None
        self.stats.counters["resumed"] += 1
        self.get_logger().info(f"resuming from {self.ckpt_path}: {len(ck.gaussians)} Gaussians, {len(ck.keyframes)} "
                               f"keyframes, iteration {ck.iteration} (written {time.time() - ck.saved_at_s:.0f} s ago)")
        return ck

    def save_checkpoint(self, force: bool = False) -> pathlib.Path | None:
        """Write the session's state atomically when it changed since the last write."""
        if self.ckpt_path is None:
            return None
        t0 = time.perf_counter()
        try:
            ck = self.session.state_dict(only_if_changed=not force).result()
            if ck is None:
                return None
            checkpoint.save(ck, self.ckpt_path)
        except (OSError, DataError) as err:
            self.stats.problem("checkpoint_failed", f"could not write checkpoint {self.ckpt_path}: {err}")
            return None
        self.stats.counters["checkpoints"] += 1
        self.stats.gauges["checkpoint_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
        return self.ckpt_path

    # ------------------------------------------------------------------ keyframes
    def _remember(self, stamp: int) -> None:
        if len(self._complete) == self._complete.maxlen:
            self._complete_set.discard(self._complete[0])
        self._complete.append(stamp)
        self._complete_set.add(stamp)

    def _part(self, part: str, msg) -> None:  # noqa: ANN001 - any bundle message type
        """Collect a keyframe's parts; a complete bundle is decoded and queued for insertion, or
        refused whole and counted by kind (camera_info, bad_image, size_mismatch, empty_depth,
        bad_pose, bad_seeds) as the keyframe_sampler does."""
        stamp = stamp_to_ns(msg.header.stamp)
        if stamp in self._complete_set:  # the keyframe topics replay recent samples: keep the first
            self.stats.counters["duplicate_keyframe_parts"] += 1
            return
        b = self.bundler.add(part, stamp, msg)
        self.stats.gauges["dropped_keyframe_bundles"] = self.bundler.dropped
        if b is None:
            return
        self._remember(stamp)
        try:
            kf = decode_keyframe_images(b, self.depth_scale)
            points, colors = decode_seeds(pointcloud2_to_structured(b["seeds"]))
        except KeyframeBundleError as err:
            self.stats.problem(err.kind, f"keyframe {stamp} refused: {err}")
        except (MessageError, DataError) as err:
            self.stats.problem("bad_seeds", f"keyframe {stamp} refused: {err}")
        else:
            self.session.insert_keyframe(KeyframeInput(stamp, kf.T_wc, kf.rgb, kf.depth_m, kf.camera, points, colors))
        if stamp in self.awaiting_keyframes:
            self.awaiting_keyframes.discard(stamp)
            self._lockstep_ack(stamp)

    def on_refined(self, msg: Path) -> None:
        """Refined keyframe poses from the tracker's bundle adjustment (the session ignores stamps
        it never inserted)."""
        poses: dict[int, np.ndarray] = {}
        for p in msg.poses:
            try:
                poses[stamp_to_ns(p.header.stamp)] = pose_to_matrix(p.pose)
            except (MessageError, DataError) as err:
                self.stats.problem("bad_pose", f"refined pose of keyframe {stamp_to_ns(p.header.stamp)} ignored: {err}")
        if poses:
            self.session.update_poses(poses)

    def on_processed(self, msg: Header) -> None:
        """Lockstep: acknowledge a frame once its keyframe (if any) is queued and training ran.
        Always: remember announced keyframes, so ones that never arrive are counted."""
        stamp = stamp_to_ns(msg.stamp)
        if msg.frame_id == "keyframe":
            self._announced.append((time.monotonic(), stamp))
            self.stats.counters["keyframes_announced"] += 1
        if not self.lockstep:
            return
        if msg.frame_id == "keyframe" and stamp not in self._complete_set:
            self.awaiting_keyframes.add(stamp)
            return
        self._lockstep_ack(stamp)

    def _lockstep_ack(self, stamp_ns: int) -> None:
        self.session.train(self.lockstep_iters).result()  # after the keyframe's insertion: one queue
        self.pub_ack.publish(make_header(stamp_ns, "mapper"))

    def _count_missed_keyframes(self) -> None:
        now = time.monotonic()
        while self._announced and now - self._announced[0][0] > MISSED_AFTER_S:
            if self._announced.popleft()[1] not in self._complete_set:
                self.stats.counters["keyframes_missed"] += 1

    def _sync_stats(self) -> None:
        """The session's problems and status into this node's stats (on the executor: NodeStats
        has one writer)."""
        for ev in self.session.poll_events():
            self.stats.problem(ev.kind, ev.message)
        st = self.session.status
        self.stats.counters.update({k: v for k, v in st.counters.items() if k != "keyframes_overload"})
        g = self.stats.gauges
        g.update(iteration=st.iteration, gaussians=st.gaussians, model_bytes=st.model_bytes,
                 model_bytes_peak=st.model_bytes_peak, gaussians_peak=st.gaussians_peak, insert_queue=st.insert_queue,
                 keyframes_trained=st.keyframes_trained, keyframes_dropped=st.keyframes_dropped,
                 budget_gaussians=st.budget_gaussians)
        if st.loss is not None:
            g["loss"] = st.loss
        if self.session.device.type == "cuda":
            g["cuda_max_allocated"] = torch.cuda.max_memory_allocated(self.session.device)

    # ------------------------------------------------------------------ outputs
    def send_delta(self, exact: bool = False) -> None:
        """Publish the next map delta (exact: every difference, tolerance 0, no row limit)."""
        rows_per_delta = max(1, int(self.delta_budget * 1000.0 / self.delta_rate
                                    / message_dtype(self.cfg.max_sh_degree).itemsize))
        batch = self.session.delta(rows_per_delta, exact).result()
        for rows in batch.messages:
            self.pub_delta.publish(structured_to_pointcloud2(rows, self.get_clock().now().nanoseconds,
                                                             self.world_frame))
        self.stats.gauges["seq"] = batch.seq
        self.stats.gauges["delta_pending_rows"] = batch.pending_rows

    def publish_snapshot(self) -> tuple[int, int]:
        """Publish the whole map (latched) at the next seq; returns (its size, its seq)."""
        rows, n, seq = self.session.snapshot_message().result()
        self.pub_snapshot.publish(structured_to_pointcloud2(rows, self.get_clock().now().nanoseconds, self.world_frame))
        self.stats.counters["snapshots"] += 1
        self.stats.gauges["seq"] = seq
        return n, seq

    def on_snapshot_request(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        n, seq = self.publish_snapshot()
        res.success, res.message = True, f"seq={seq} gaussians={n}"
        return res

    def on_finish(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        """Insert what is queued, stop training, run the final iterations, flush every change."""
        done = self.session.finish(self.final_iters).result()
        if done.final_iterations:
            self.get_logger().info(f"final {done.final_iterations} iterations in {done.seconds:.1f} s")
        self.send_delta(exact=True)
        self.save_checkpoint()
        st = self.session.status
        res.success = True
        res.message = f"seq={self.stats.gauges['seq']} gaussians={st.gaussians} epoch={done.epoch}"
        return res

    def on_pose(self, msg: PoseStamped) -> None:
        self.latest_pose = msg

    def _render(self, pose: PoseStamped) -> None:
        view = self.session.render(pose_to_matrix(pose.pose)).result()
        if view is None:
            return
        stamp = stamp_to_ns(pose.header.stamp)
        self.pub_color.publish(numpy_to_image(view.rgb, "rgb8", stamp, "render_camera"))
        self.pub_depth.publish(depth_to_image(view.depth, "32FC1", stamp, "render_camera"))
        self.pub_info.publish(camera_to_camera_info(view.camera, stamp, "render_camera"))
        self.stats.counters["renders"] += 1

    def on_shutdown(self) -> None:
        if self.save_checkpoint() is not None:
            self.get_logger().info(f"checkpoint written to {self.ckpt_path} ({self.session.status.gaussians} Gaussians)")
        self.session.close()


def main(args: list[str] | None = None) -> int:
    return run_node(MapperNode, "mapper", args, threads=4)


if __name__ == "__main__":
    sys.exit(main())
