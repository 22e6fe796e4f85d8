"""mapper node: owns the Gaussian map; trains it on keyframes, merges, publishes deltas and views.

Subscribes (reliable): ``memgs/keyframe/{color,depth,camera_info,pose}`` from the tracker and
``memgs/keyframe/seeds`` from the sampler (one stamp per keyframe), ``memgs/keyframe/refined_poses``
(Path), ``memgs/pose`` (latest tracked pose, for the live view), ``memgs/render/view_pose``
(render requests), ``memgs/tracker/processed`` (lockstep handshake).
Publishes: ``memgs/map/delta`` (PointCloud2, see core/map_delta.py), ``memgs/mapper/snapshot``
(latched full map), ``memgs/render/{color,depth,camera_info}``, ``memgs/frame_ack`` (lockstep),
``memgs/mapper/stats``. Services: ``memgs/mapper/publish_snapshot`` and ``memgs/mapper/finish``
(std_srvs/Trigger; finish stops training, flushes every change and answers ``seq=<n> gaussians=<n>``).

With ``checkpoint_path`` set the mapper writes its map and keyframes there (core/checkpoint.py,
atomic) every ``checkpoint_period_s``, when finished and at shutdown; a mapper started with an
existing checkpoint resumes from it, announces a new delta epoch and publishes a snapshot, so
the merger replaces its copy with the resumed map.

Training runs in its own thread while messages arrive; in ``lockstep`` mode it instead runs a
fixed number of iterations per frame before acknowledging it, so a lockstep replay is
deterministic run to run.
"""
from __future__ import annotations

import pathlib
import secrets
import sys
import threading
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
from memgs_ros.core.camera import PinholeCamera
from memgs_ros.core.map_delta import DeltaOutbox, message_dtype
from memgs_ros.core.mapping import GaussianMapper, MappingConfig
from memgs_ros.core.merge import MergeConfig
from memgs_ros.core.runtime import configure_cpu_runtime
from memgs_ros.core.view import view_preparation
from memgs_ros.errors import DataError, MessageError
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import (
    camera_to_camera_info,
    depth_to_image,
    make_header,
    numpy_to_image,
    pointcloud2_to_structured,
    pose_to_matrix,
    stamp_to_ns,
    structured_to_pointcloud2,
)
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
        self.depth_scale = declare(self, "depth_scale", 1000.0,
                                   "16UC1 keyframe depth units per metre (the tracker publishes 32FC1 metres)",
                                   range=(1e-3, 1e6))
        self.cfg: MappingConfig = declare_config(self, MappingConfig, "mapping")
        self.merge_cfg: MergeConfig = declare_config(self, MergeConfig, "merge")
        device = declare(self, "device", "auto", "torch device for the map: auto (CUDA when present), cpu, cuda, cuda:N")
        self.lockstep = declare(self, "lockstep", False,
                                "train a fixed number of iterations per frame and acknowledge each (deterministic replay)")
        self.lockstep_iters = declare(self, "lockstep_iterations", 10,
                                      "training iterations per frame in lockstep mode", range=(0, 10000))
        self.final_iters = declare(self, "final_iterations", 0,
                                   "extra training iterations run by the finish service before the final flush",
                                   range=(0, 10**7))
        self.delta_rate = declare(self, "delta_rate_hz", 1.0, "map deltas per second", range=(0.01, 100.0))
        self.delta_budget = declare(self, "delta_budget_kbytes_per_s", 500.0,
                                    "link budget for map deltas; the largest changes go first, the rest wait "
                                    "(the final flush ignores it)", range=(1.0, 1e7))
        delta_tol = declare(self, "delta_tolerance", 1e-3,
                            "send a Gaussian again only when a parameter moved more than this (m, or "
                            "pre-activation units); the final flush is exact", range=(0.0, 10.0))
        self.snapshot_period = declare(self, "snapshot_period_s", 0.0,
                                       "publish a full snapshot this often (0 = only on request)", range=(0.0, 1e6))
        self.render_rate = declare(self, "render_rate_hz", 1.0, "live view renders per second (0 = off)",
                                   range=(0.0, 60.0))
        self.world_frame = declare(self, "world_frame", "map", "frame id of published maps and poses")
        self.ack_topic = declare(self, "ack_topic", "memgs/frame_ack", "lockstep acknowledgement topic (to the player)")
        ckpt_path = declare(self, "checkpoint_path", "",
                            "file for map + keyframe checkpoints (.npz); empty = no checkpoints")
        self.ckpt_period = declare(self, "checkpoint_period_s", 30.0,
                                   "write a checkpoint this often while the map changes (0 = only at finish/shutdown)",
                                   range=(0.0, 1e6))
        resume = declare(self, "resume", True, "start from the checkpoint at checkpoint_path when one exists")
        self.insert_queue = declare(self, "insert_queue", 4,
                                    "free-running: complete keyframes waiting for insertion; when full the oldest "
                                    "is dropped and counted (problem.keyframe_overload)", range=(1, 1000))

        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device == "cpu":
            configure_cpu_runtime()
        self.mapper = GaussianMapper(self.cfg, device=device, merge_cfg=self.merge_cfg)
        # A new epoch every start: a merger that held the map of an earlier life resynchronises.
        self.outbox = DeltaOutbox(self.cfg.max_sh_degree, delta_tol, epoch=secrets.randbits(32))
        self.stats = NodeStats(self, "mapper")
        self.kf_ids: dict[int, int] = {}  # keyframe stamp -> mapper keyframe id
        self.ckpt_path = pathlib.Path(ckpt_path).expanduser() if ckpt_path else None
        self._ckpt_lock = threading.Lock()
        self._ckpt_version: tuple[int, int] | None = None  # (iteration, keyframes) last written
        resumed = resume and self.ckpt_path is not None and self.ckpt_path.exists() and self._resume()
        self.render_camera: PinholeCamera | None = None
        self.latest_pose: PoseStamped | None = None
        self.awaiting_keyframes: set[int] = set()
        # (arrival time, stamp) of keyframes the tracker announced: a keyframe whose parts have not
        # all arrived 60 s later was lost on the way (a reader too slow for the transient-local
        # history of 10). Under CPU overload parts can arrive more than 10 s after the announcement.
        self._announced: deque[tuple[float, int]] = deque(maxlen=10_000)
        # Free-running, keyframes are inserted on their own thread from a bounded queue: the
        # executor only decodes parts, so it drains the keyframe topics' 10-deep history in
        # time, and overload drops (and counts) whole queued keyframes instead of DDS losing parts.
        self._inserts: deque[tuple[int, dict]] = deque()
        self._insert_cv = threading.Condition()
        self._inserting = False
        self._insert_stop = threading.Event()
        self._complete: deque[int] = deque(maxlen=4096)  # stamps of recent complete bundles ...
        self._complete_set: set[int] = set()  # ... and the same as a set (duplicate replays)
        self._pending_poses: dict[int, np.ndarray] = {}  # refined poses for the next training step
        self._pose_lock = threading.Lock()
        self._send_lock = threading.Lock()  # one delta/snapshot cut at a time, in seq order
        self._stop = threading.Event()
        self._finished = False

        parts = {"color", "camera_info", "pose", "seeds"} | ({"depth"} if self.mode == "rgbd" else set())
        self.bundler = StampBundler(parts, max_pending=16)
        rel = qos.reliable(20)
        self.pub_delta = self.create_publisher(PointCloud2, "memgs/map/delta", qos.reliable(50))
        self.pub_snapshot = self.create_publisher(PointCloud2, "memgs/mapper/snapshot", qos.latched())
        self.pub_color = self.create_publisher(Image, "memgs/render/color", qos.reliable(2))
        self.pub_depth = self.create_publisher(Image, "memgs/render/depth", qos.reliable(2))
        self.pub_info = self.create_publisher(CameraInfo, "memgs/render/camera_info", qos.reliable(2))
        self.pub_ack = self.create_publisher(Header, self.ack_topic, qos.reliable(100))

        io_group = MutuallyExclusiveCallbackGroup()  # keyframe insertion and lockstep stay ordered
        kfq = qos.keyframes()  # a resumed mapper gets the keyframes sent while it was down
        self.create_subscription(Image, "memgs/keyframe/color", lambda m: self._part("color", m), kfq,
                                 callback_group=io_group)
        self.create_subscription(CameraInfo, "memgs/keyframe/camera_info", lambda m: self._part("camera_info", m),
                                 kfq, callback_group=io_group)
        self.create_subscription(PoseStamped, "memgs/keyframe/pose", lambda m: self._part("pose", m), kfq,
                                 callback_group=io_group)
        self.create_subscription(PointCloud2, "memgs/keyframe/seeds", lambda m: self._part("seeds", m), kfq,
                                 callback_group=io_group)
        if self.mode == "rgbd":
            self.create_subscription(Image, "memgs/keyframe/depth", lambda m: self._part("depth", m), kfq,
                                     callback_group=io_group)
        self.create_subscription(Path, "memgs/keyframe/refined_poses", self.on_refined, rel, callback_group=io_group)
        self.create_subscription(Header, "memgs/tracker/processed", self.on_processed, qos.reliable(100),
                                 callback_group=io_group)
        self.create_subscription(PoseStamped, "memgs/pose", self.on_pose, qos.reliable(5))
        self.create_subscription(PoseStamped, "memgs/render/view_pose", self.on_view_request, qos.reliable(5))
        self.create_service(Trigger, "memgs/mapper/publish_snapshot", self.on_snapshot_request)
        self.create_service(Trigger, "memgs/mapper/finish", self.on_finish, callback_group=MutuallyExclusiveCallbackGroup())
        self.create_timer(1.0 / self.delta_rate, self.send_delta)
        if self.snapshot_period > 0:
            self.create_timer(self.snapshot_period, self.publish_snapshot)
        if self.ckpt_path is not None and self.ckpt_period > 0:
            self.create_timer(self.ckpt_period, self.save_checkpoint, callback_group=MutuallyExclusiveCallbackGroup())
        if resumed:
            self.publish_snapshot()  # latched: the merger takes the resumed map and its epoch
        if self.render_rate > 0:
            self.create_timer(1.0 / self.render_rate, self.render_live)
        self.create_timer(1.0, self._count_missed_keyframes)
        self.trainer: threading.Thread | None = None
        self.inserter: threading.Thread | None = None
        if not self.lockstep:
            self.trainer = threading.Thread(target=self._train_loop, name="mapper-training", daemon=True)
            self.trainer.start()
            self.inserter = threading.Thread(target=self._insert_loop, name="mapper-insert", daemon=True)
            self.inserter.start()
        self.get_logger().info(f"mapper on {device}, {'lockstep' if self.lockstep else 'free-running'} training")

    # ------------------------------------------------------------------ checkpoints
    def _resume(self) -> bool:
        """Load the checkpoint; a file that cannot be read is moved aside, never overwritten."""
        assert self.ckpt_path is not None
        try:
            ck = checkpoint.load(self.ckpt_path)
            checkpoint.restore(self.mapper, ck)
        except DataError as err:
            aside = self.ckpt_path.with_name(f"{self.ckpt_path.name}.unreadable-{int(time.time())}")
            self.ckpt_path.replace(aside)
            self.get_logger().error(f"cannot resume: {err}; moved it to {aside} and starting an empty map")
            return False
        self.kf_ids = {int(stamp): int(kf) for stamp, kf in ck.extra.get("keyframe_stamps", {}).items()}
        cam = ck.keyframes[-1].camera if ck.keyframes else None
        if cam is not None:
            self.render_camera = cam  # prepared keyframes carry the undistorted, scaled camera
        self._ckpt_version = (self.mapper.iteration, len(self.kf_ids))
        self.stats.counters["resumed"] += 1
        self.get_logger().info(
            f"resumed from {self.ckpt_path}: {len(self.mapper.gmap)} Gaussians, {len(ck.keyframes)} keyframes, "
            f"iteration {ck.iteration} (written {time.time() - ck.saved_at_s:.0f} s ago)")
        return True

    def save_checkpoint(self, force: bool = False) -> pathlib.Path | None:
        """Write the map and keyframes atomically when they changed since the last write."""
        if self.ckpt_path is None:
            return None
        with self._ckpt_lock:
            version = (self.mapper.iteration, len(self.kf_ids))
            if not force and version == self._ckpt_version:
                return None
            t0 = time.perf_counter()
            try:
                ck = checkpoint.capture(self.mapper, {"keyframe_stamps": {str(k): v for k, v in self.kf_ids.items()}})
                checkpoint.save(ck, self.ckpt_path)
            except (OSError, DataError) as err:
                self.stats.problem("checkpoint_failed", f"could not write checkpoint {self.ckpt_path}: {err}")
                return None
            self._ckpt_version = version
            self.stats.counters["checkpoints"] += 1
            self.stats.gauges["checkpoint_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
            return self.ckpt_path

    # ------------------------------------------------------------------ keyframes
    def _part(self, part: str, msg) -> None:  # noqa: ANN001 - any bundle message type
        stamp = stamp_to_ns(msg.header.stamp)
        if stamp in self.kf_ids or stamp in self._complete_set:
            # Keyframe topics replay recent samples to a (re)started mapper: keep the first copy.
            self.stats.counters["duplicate_keyframe_parts"] += 1
            return
        bundle = self.bundler.add(part, stamp, msg)
        self.stats.gauges["dropped_keyframe_bundles"] = self.bundler.dropped
        if bundle is None:
            return
        if len(self._complete) == self._complete.maxlen:
            self._complete_set.discard(self._complete[0])
        self._complete.append(stamp)
        self._complete_set.add(stamp)
        if self.inserter is None:
            self._insert(stamp, bundle)  # lockstep: in order, before the frame is acknowledged
            return
        with self._insert_cv:
            if len(self._inserts) >= self.insert_queue:
                old, _ = self._inserts.popleft()
                self.stats.problem("keyframe_overload", f"mapper cannot keep up: keyframe {old} dropped from "
                                                        "its full insert queue")
            self._inserts.append((stamp, bundle))
            self.stats.gauges["insert_queue"] = len(self._inserts)
            self._insert_cv.notify()

    def _insert_loop(self) -> None:
        while not self._insert_stop.is_set():
            with self._insert_cv:
                if not self._inserts:
                    self._insert_cv.wait(0.1)
                    continue
                batch = list(self._inserts)
                self._inserts.clear()
                self._inserting = True
            try:
                # Everything queued goes in under one hold of the map: one wait for the running
                # training step per batch instead of one per keyframe.
                t0 = time.perf_counter()
                with self.mapper.exclusive():
                    for stamp, bundle in batch:
                        try:
                            self._insert(stamp, bundle)
                        except Exception as err:  # noqa: BLE001 - one keyframe must not end insertion
                            self.stats.problem("bad_keyframe", f"keyframe {stamp} insertion failed: {err}")
                self.stats.gauges["insert_ms"] = round(1e3 * (time.perf_counter() - t0) / len(batch), 1)
                self.stats.gauges["insert_batch"] = len(batch)
            finally:
                with self._insert_cv:
                    self._inserting = False
                    self.stats.gauges["insert_queue"] = len(self._inserts)
                    self._insert_cv.notify_all()

    def _drain_inserts(self, timeout_s: float = 120.0) -> None:
        """Wait until every queued keyframe is inserted, then stop the insert thread."""
        if self.inserter is None:
            return
        with self._insert_cv:
            self._insert_cv.wait_for(lambda: not self._inserts and not self._inserting, timeout_s)
        self._insert_stop.set()
        self.inserter.join(timeout=10.0)

    def _insert(self, stamp_ns: int, b: dict) -> None:
        """Add a keyframe bundle to the map, or refuse it whole (the map unchanged) and count the
        problem by kind, as the keyframe_sampler does: camera_info, bad_image, size_mismatch,
        empty_depth, bad_pose, bad_seeds, bad_keyframe."""
        if self._finished:
            return
        stage = "bad_seeds"  # the problem kind a failure from here on is counted under
        try:
            kf = decode_keyframe_images(b, self.depth_scale)
            cam, rgb, depth, T_wc = kf.camera, kf.rgb, kf.depth_m, kf.T_wc
            points, colors = decode_seeds(pointcloud2_to_structured(b["seeds"]))
            stage = "bad_keyframe"
            kf_id = len(self.kf_ids)
            # With a training thread the budget is enforced on its next step, off this callback
            # thread, which must keep up with the keyframe topics' 10-deep history.
            added = self.mapper.add_keyframe(kf_id, stamp_ns, T_wc, rgb, depth, cam, points, colors,
                                             enforce_budget=self.trainer is None)
        except KeyframeBundleError as err:
            self.stats.problem(err.kind, f"keyframe {stamp_ns} refused: {err}")
            return
        except (MessageError, DataError) as err:
            self.stats.problem(stage, f"keyframe {stamp_ns} refused: {err}")
            return
        self.kf_ids[stamp_ns] = kf_id
        self.render_camera = self.render_camera or view_preparation(cam, self.cfg.resolution_scale).camera
        self.stats.counters["keyframes"] += 1
        self.stats.counters["seeded_gaussians"] += added
        if stamp_ns in self.awaiting_keyframes:
            self.awaiting_keyframes.discard(stamp_ns)
            self._lockstep_ack(stamp_ns)

    def on_refined(self, msg: Path) -> None:
        """Refined keyframe poses from the tracker's bundle adjustment. Free-running, they wait
        for the training thread's next step (which holds the map lock anyway): applying each
        here waited for a running step, and that stalled every keyframe topic behind it."""
        poses: dict[int, np.ndarray] = {}
        for p in msg.poses:
            kf_id = self.kf_ids.get(stamp_to_ns(p.header.stamp))
            if kf_id is None:
                continue
            try:
                poses[kf_id] = pose_to_matrix(p.pose)
            except (MessageError, DataError) as err:
                self.stats.problem("bad_pose", f"refined pose of keyframe {kf_id} ignored: {err}")
        if not poses:
            return
        if self.trainer is None:
            self._apply_refined(poses)
            return
        with self._pose_lock:
            self._pending_poses.update(poses)  # the newest refinement of a keyframe wins

    def _apply_refined(self, poses: dict[int, np.ndarray]) -> None:
        updated = self.mapper.update_keyframe_poses(poses)
        self.stats.counters["keyframe_pose_updates"] += updated
        self.stats.counters["refined_poses_of_dropped_keyframes"] += len(poses) - updated

    # ------------------------------------------------------------------ training
    def _train_loop(self) -> None:
        while not self._stop.is_set():
            if not self.mapper.ready:
                self._stop.wait(0.05)
                continue
            try:
                self._step()
            except (DataError, RuntimeError) as err:
                # One bad step (a keyframe gone mid-step, a CUDA hiccup) must not end training.
                self.stats.problem("training_step", f"training step failed: {err}")
                self._stop.wait(0.1)

    def _apply_pending_poses(self) -> None:
        with self._pose_lock:
            poses, self._pending_poses = self._pending_poses, {}
        if poses:
            self._apply_refined(poses)

    def _step(self) -> None:
        self._apply_pending_poses()
        st = self.mapper.step()
        if st is None:
            return
        g = self.stats.gauges
        g["iteration"] = st.iteration
        g["gaussians"] = st.num_gaussians
        g["loss"] = round(sum(st.terms.values()), 5)
        mem = self.mapper.gmap.memory_bytes()
        g["model_bytes"] = mem.total
        g["model_bytes_peak"] = max(int(g.get("model_bytes_peak", 0)), mem.total)
        g["gaussians_peak"] = max(int(g.get("gaussians_peak", 0)), st.num_gaussians)
        if self.mapper.device.type == "cuda":
            g["cuda_max_allocated"] = torch.cuda.max_memory_allocated(self.mapper.device)
        self.stats.counters["merged_removed"] += st.merged_removed
        self.stats.counters["merged_added"] += st.merged_added
        self.stats.counters["budget_merged"] += st.budget_merged
        self.stats.counters["budget_pruned"] += st.budget_pruned
        g["keyframes_trained"] = len(self.mapper.keyframes)
        g["keyframes_dropped"] = self.mapper.keyframes_dropped
        g["budget_gaussians"] = self.mapper.budget_gaussians

    def on_processed(self, msg: Header) -> None:
        """Lockstep: acknowledge a frame once its keyframe (if any) is in and training ran.
        Always: remember announced keyframes, so ones that never arrive are counted."""
        stamp = stamp_to_ns(msg.stamp)
        if msg.frame_id == "keyframe":
            self._announced.append((time.monotonic(), stamp))
            self.stats.counters["keyframes_announced"] += 1
        if not self.lockstep:
            return
        if msg.frame_id == "keyframe" and stamp not in self.kf_ids:
            self.awaiting_keyframes.add(stamp)
            return
        self._lockstep_ack(stamp)

    def _count_missed_keyframes(self) -> None:
        now = time.monotonic()
        while self._announced and now - self._announced[0][0] > MISSED_AFTER_S:
            _, stamp = self._announced.popleft()
            if stamp not in self.kf_ids and stamp not in self._complete_set:  # queued ones are counted there
                self.stats.counters["keyframes_missed"] += 1

    def _lockstep_ack(self, stamp_ns: int) -> None:
        if self.mapper.ready:
            for _ in range(self.lockstep_iters):
                self._step()
        self.pub_ack.publish(make_header(stamp_ns, "mapper"))

    # ------------------------------------------------------------------ deltas
    def send_delta(self, exact: bool = False) -> None:
        """Diff the map against what the merger holds and publish the difference.

        exact: tolerance 0 and no row limit, repeated until nothing differs (final flush).
        """
        with self._send_lock:
            self.mapper.discard_changes()  # the outbox diffs snapshots: the change log only grows
            while True:
                rows = self.outbox.next_delta(self.mapper.snapshot(), None if exact else self._rows_per_delta(),
                                              0.0 if exact else None)
                if rows is None:
                    break
                msg = structured_to_pointcloud2(rows, self.get_clock().now().nanoseconds, self.world_frame)
                self.pub_delta.publish(msg)
                self.stats.counters["delta_messages"] += 1
                self.stats.counters["delta_bytes"] += len(msg.data)
                self.stats.gauges["seq"] = self.outbox.seq
                if not exact:
                    break
            self.stats.gauges["delta_pending_rows"] = self.outbox.pending_rows

    def _rows_per_delta(self) -> int:
        row_bytes = message_dtype(self.cfg.max_sh_degree).itemsize
        return max(1, int(self.delta_budget * 1000.0 / self.delta_rate / row_bytes))

    def publish_snapshot(self) -> int:
        """Publish the whole map (latched) at the current seq; returns its size."""
        with self._send_lock:
            records = self.mapper.snapshot()
            rows = self.outbox.snapshot(records)
        self.pub_snapshot.publish(structured_to_pointcloud2(rows, self.get_clock().now().nanoseconds,
                                                            self.world_frame))
        self.stats.counters["snapshots"] += 1
        return len(records)

    def on_snapshot_request(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        n = self.publish_snapshot()
        res.success, res.message = True, f"seq={self.outbox.seq} gaussians={n}"
        return res

    def on_finish(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        """Insert what is queued, stop training, run the final iterations, flush every change;
        answer the final seq."""
        self._drain_inserts()
        self._stop.set()
        if self.trainer is not None:
            self.trainer.join()
        self._apply_pending_poses()
        if not self._finished and self.mapper.ready:
            t0 = time.perf_counter()
            for _ in range(self.final_iters):
                self._step()
            self.get_logger().info(f"final {self.final_iters} iterations in {time.perf_counter() - t0:.1f} s")
        self._finished = True
        self.send_delta(exact=True)
        self.save_checkpoint()
        res.success = True
        res.message = f"seq={self.outbox.seq} gaussians={len(self.mapper.gmap)} epoch={self.outbox.epoch}"
        return res

    # ------------------------------------------------------------------ views
    def on_pose(self, msg: PoseStamped) -> None:
        self.latest_pose = msg

    def render_live(self) -> None:
        if self.latest_pose is not None:
            self._render(self.latest_pose)

    def on_view_request(self, msg: PoseStamped) -> None:
        self._render(msg)

    def _render(self, pose: PoseStamped) -> None:
        cam = self.render_camera
        if cam is None or len(self.mapper.gmap) == 0:
            return
        out = self.mapper.render(pose_to_matrix(pose.pose), cam)
        stamp = stamp_to_ns(pose.header.stamp)
        rgb = (out.color.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
        depth = out.depth.cpu().numpy().astype(np.float32)
        self.pub_color.publish(numpy_to_image(np.ascontiguousarray(rgb), "rgb8", stamp, "render_camera"))
        self.pub_depth.publish(depth_to_image(depth, "32FC1", stamp, "render_camera"))
        self.pub_info.publish(camera_to_camera_info(cam, stamp, "render_camera"))
        self.stats.counters["renders"] += 1

    def on_shutdown(self) -> None:
        self._insert_stop.set()
        self._stop.set()
        if self.trainer is not None:
            self.trainer.join(timeout=10.0)
        if self.save_checkpoint() is not None:
            self.get_logger().info(f"checkpoint written to {self.ckpt_path} ({len(self.mapper.gmap)} Gaussians)")


def main(args: list[str] | None = None) -> int:
    return run_node(MapperNode, "mapper", args, threads=4)


if __name__ == "__main__":
    sys.exit(main())
