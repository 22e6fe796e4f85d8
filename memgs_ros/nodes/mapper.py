"""mapper node: turns keyframes, poses and requests into commands of a ``MappingSession``
(core/mapping/session.py, the one owner of the Gaussian map) and publishes what it returns.

In: ``memgs/keyframe/{color,depth,camera_info,pose,seeds}`` (one stamp per keyframe),
``memgs/keyframe/refined_poses`` (bundle adjustment), ``memgs/keyframe/loop_corrected_poses``,
``memgs/pose`` (live view), ``memgs/render/view_pose``, ``memgs/tracker/processed`` (lockstep).
Out: ``memgs/map/delta`` (core/maps/map_delta.py), ``memgs/mapper/snapshot`` (latched, with a packed ``rgb`` colour),
``memgs/render/{color,depth,camera_info}``, ``memgs/frame_ack``, ``memgs/mapper/stats``; services
``memgs/mapper/publish_snapshot`` and ``memgs/mapper/finish``
(answers ``seq=<n> gaussians=<n> epoch=<n>``). With ``checkpoint_path`` the session's state is
written there atomically (periodically, at finish and shutdown) and a restarted mapper resumes
from it under a new delta epoch, publishing a snapshot so the merger replaces its copy.
"""
from __future__ import annotations

import functools
import pathlib
import queue
import secrets
import sys
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import replace
from typing import TypeVar

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.task import Future as RclpyFuture
from rclpy.timer import Timer
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from memgs_ros.core.mapping import checkpoint, losses
from memgs_ros.core.mapping.finish import FinalPlan, FinishSteps, finish_map
from memgs_ros.core.mapping.frame_acks import LockstepAcknowledger
from memgs_ros.core.mapping.keyframe_input import check_seed_depths
from memgs_ros.core.mapping.mapper import MappingConfig
from memgs_ros.core.mapping.output_pacing import DeltaPacer, LiveView, delta_rows
from memgs_ros.core.mapping.session import MappingSession
from memgs_ros.core.maps.map_delta import message_dtype
from memgs_ros.core.merge.config import MergeConfig
from memgs_ros.core.raster import warm_up
from memgs_ros.core.raster.backend_choice import choose_backend, device_label, device_problem, resolve_device
from memgs_ros.core.runtime.cpu import configure_cpu_runtime
from memgs_ros.core.runtime.worker import WorkerStopped
from memgs_ros.errors import ConfigError, DataError, MessageError
from memgs_ros.nodes.params import NODE_CONFIGS, MapperParams
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
from memgs_ros.ros.diagnostics import NodeStats, RollingMedian, peak_rss_mb, rss_mb
from memgs_ros.ros.keyframe_bundle import KeyframeBundleError, decode_keyframe_images
from memgs_ros.ros.node_main import run_node
from memgs_ros.ros.seed_cloud import decode_seeds
from memgs_ros.ros.stamp_sync import KeyframeIntake

CONFIGS = NODE_CONFIGS["mapper"]
SHUTDOWN_SAVE_TIMEOUT_S = 15.0  # within the runner's stop deadline (20 s)
SESSION_CLOSE_TIMEOUT_S = 30.0  # the step or command in progress ends first (a cold warm-up: ~20 s)
T = TypeVar("T")


def _resolved(value: T) -> Future[T]:
    f: Future[T] = Future()
    f.set_result(value)
    return f


class MapperNode(Node):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("mapper", **node_kwargs)
        self.params = p = declare_config(self, MapperParams, "")
        self.niceness = p.niceness  # applied by run_node to this node's process
        self._rate_mark = (time.monotonic(), -1)  # (time, iteration) at the last stats sync; -1: none yet
        self.cfg: MappingConfig = declare_config(self, MappingConfig, "mapping")
        merge_cfg: MergeConfig = declare_config(self, MergeConfig, "merge")
        problem = device_problem(p.device, self.cfg.raster_backend)
        if problem:
            raise ConfigError(problem)
        device = resolve_device(p.device)
        raster = choose_backend(device, self.cfg.raster_backend)  # what warm_up and training will run
        if device == "cpu":
            configure_cpu_runtime()
        # Free heap pages go back every 2 s (each trim ~5 ms): training leaves ~30-50 MB of
        # freed step buffers a step, and at the default 30 s they piled up into the peak RSS.
        self.stats = NodeStats(self, "mapper", trim_period_s=2.0)
        self.stats.gauges["raster_backend"] = raster.backend
        # Whether this mapper checkpoints (0: never): fault injection waits for a checkpoint to resume from.
        self.stats.gauges["checkpoint_period_s"] = p.checkpoint_period_s if p.checkpoint_path else 0.0
        self.ckpt = (checkpoint.CheckpointFile(pathlib.Path(p.checkpoint_path).expanduser())
                     if p.checkpoint_path else None)
        resumed, why = self.ckpt.read_or_set_aside() if p.resume and self.ckpt else (None, None)
        # A new delta epoch every start: a merger that held the map of an earlier life resynchronises.
        start = functools.partial(MappingSession, self.cfg, device, merge_cfg=merge_cfg, free_running=not p.lockstep,
                                  insert_queue=p.insert_queue, delta_tolerance=p.delta_tolerance,
                                  delta_epoch=secrets.randbits(32), niceness=p.niceness)
        try:
            self.session = start(checkpoint=resumed)
        except DataError as err:  # read, but not a state this mapper can take: set it aside
            resumed, why = None, self.ckpt.set_aside(err)
            self.session = start()
        if why:
            self.get_logger().error(why)
        elif resumed is not None:
            self.stats.counters["resumed"] += 1
            self.get_logger().info(f"resumed from {self.ckpt.path}: {len(resumed.gaussians)} Gaussians, "
                                   f"{len(resumed.keyframes)} keyframes, iteration {resumed.iteration}")
        self.latest_pose: PoseStamped | None = None
        # These two: the executor's thread only.
        self.deltas = DeltaPacer(
            delta_rows(p.delta_budget_kbytes_per_s, p.delta_rate_hz, message_dtype(self.cfg.max_sh_degree).itemsize),
            lambda rows: self.session.delta(rows, False, self._publish_delta),
            self._receivers_acked,
            lambda: self.stats.post_count("delta_waits"))
        self.live_view = LiveView()
        ack_ms = self.stats.computed["lockstep_ack_ms_median"] = RollingMedian()  # a lockstep frame's time here
        self.lockstep = LockstepAcknowledger(
            p.lockstep_window, self._train_frame, self._hand_over,
            lambda stamp: self.pub_ack.publish(make_header(stamp, "mapper")), ack_ms.add)
        self._decided: dict[int, int] = {}  # keyframe stamp -> its pose's publication time (ns), until complete
        topics = {"color": Image, "camera_info": CameraInfo, "pose": PoseStamped, "seeds": PointCloud2,
                  **({"depth": Image} if p.mode == "rgbd" else {})}
        self.intake = KeyframeIntake(set(topics), known=self.session.resumed_stamps)
        self.pub_delta = self.create_publisher(PointCloud2, "memgs/map/delta", qos.reliable(50))
        self.pub_snapshot = self.create_publisher(PointCloud2, "memgs/mapper/snapshot", qos.latched())
        self.pub_color = self.create_publisher(Image, "memgs/render/color", qos.reliable(2))
        self.pub_depth = self.create_publisher(Image, "memgs/render/depth", qos.reliable(2))
        self.pub_info = self.create_publisher(CameraInfo, "memgs/render/camera_info", qos.reliable(2))
        self.pub_ack = self.create_publisher(Header, p.ack_topic, qos.reliable(100))
        # One thread runs every callback (run_node's single-threaded executor) and none of them waits:
        # training, deltas and renders run on the session's threads, whose results are handed back
        # through one queue; the services that must wait for them are coroutines, each in a group of
        # its own, so everything else goes on meanwhile. (A multi-threaded executor took ~30 ms, at
        # times seconds, to pick up a message here: every lockstep frame waited on it.)
        kfq = qos.keyframes()  # a resumed mapper gets the keyframes sent while it was down
        for part, msg_type in topics.items():
            # The pose's publication time is the tracker's decision: the keyframe's latency counts from it.
            self.create_subscription(msg_type, f"memgs/keyframe/{part}", lambda m, info, p=part: self._part(p, m, info),
                                     kfq)
        self.create_subscription(Path, "memgs/keyframe/refined_poses", self.on_refined, qos.reliable(20))
        self.create_subscription(Path, "memgs/keyframe/loop_corrected_poses", self.on_loop_corrected,
                                 qos.reliable(20))
        self.create_subscription(Header, "memgs/tracker/processed", self.on_processed, qos.reliable(100))
        self.create_subscription(PoseStamped, "memgs/pose", lambda m: setattr(self, "latest_pose", m), qos.reliable(5))
        self.create_subscription(PoseStamped, "memgs/render/view_pose", lambda m: self._render(m, True),
                                 qos.reliable(5))
        # The session's threads hand finished messages over here and never call ROS themselves;
        # they are published in the order they were handed over (deltas, snapshots and the final
        # flush leave in seq order).
        self._outgoing: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        self._outgoing_ready = self.create_guard_condition(self._publish_outgoing)
        self.create_service(Trigger, "memgs/mapper/publish_snapshot", self.on_snapshot_request,
                            callback_group=ReentrantCallbackGroup())
        self.create_service(Trigger, "memgs/mapper/finish", self.on_finish, callback_group=ReentrantCallbackGroup())
        self.create_timer(1.0 / p.delta_rate_hz, self.send_delta)
        if p.snapshot_period_s > 0:
            self.create_timer(p.snapshot_period_s, self.publish_snapshot)
        if self.ckpt is not None and p.checkpoint_period_s > 0:
            self.create_timer(p.checkpoint_period_s, self.save_checkpoint)
        if resumed is not None:
            self.publish_snapshot()  # latched: the merger takes the resumed map and its epoch
        if p.render_rate_hz > 0:
            self.create_timer(1.0 / p.render_rate_hz, lambda: self._render(self.latest_pose))
        # The rasterizer's and SSIM's compiled kernels load (on a fresh install: compile) as the
        # session's first command, on its worker, while the node already spins (a stop is answered
        # meanwhile) and keyframes queue behind it; kernels_warm says when they are in.
        self._rss_baseline_mb: float | None = None
        self.stats.gauges["kernels_warm"] = 0
        warmed = self.session.call(functools.partial(self._warm_up, device, time.perf_counter()))
        warmed.add_done_callback(self._warm_up_failed)
        self.create_timer(0.1, self._sync_stats)
        self.get_logger().info(f"mapper on {device_label(device)}, rasterizer {raster.backend}, "
                               f"{'lockstep' if p.lockstep else 'free-running'} training")
        if raster.fallback_warning:
            self.get_logger().warning("CUDA without gsplat: the torch fallback rasterizer is several times slower; "
                                      "install gsplat (README 'On a Jetson')")

    def save_checkpoint(self, force: bool = False) -> Future[pathlib.Path | None]:
        """Write the session's state atomically when it changed since the last write, on the
        session's worker (a timer's save never overwrites the final one). The future gives the
        path, or None (unchanged, no checkpoint file, or failed: counted as checkpoint_failed)."""
        if self.ckpt is None:
            return _resolved(None)
        ckpt, t0 = self.ckpt, time.perf_counter()

        def write(state: checkpoint.MapperCheckpoint) -> pathlib.Path:
            ckpt.write(state)
            self.stats.post_count("checkpoints")
            self.stats.post_gauge("checkpoint_gaussians", len(state.gaussians))
            self.stats.post_gauge("checkpoint_ms", round((time.perf_counter() - t0) * 1e3, 1))
            return ckpt.path

        def failed(f: Future) -> None:
            err = None if f.cancelled() else f.exception()
            if err is not None:
                self.stats.post_problem("checkpoint_failed", f"could not write checkpoint {ckpt.path}: {err}")

        try:
            saved = self.session.save_state(write, only_if_changed=not force)
        except WorkerStopped as err:
            self.stats.post_problem("checkpoint_failed", f"could not write checkpoint {ckpt.path}: {err}")
            return _resolved(None)
        saved.add_done_callback(failed)
        return saved

    def _warm_up(self, device: str, t0: float, _mapper: object) -> None:
        """On the session's worker: load the kernels, then take the memory baseline (imports, node,
        session and kernels; the working memory is above it)."""
        warm_up(device, self.cfg.raster_backend, self.cfg.max_sh_degree)
        losses.warm_up(device)
        self._rss_baseline_mb = rss_mb()
        self.stats.post_gauge("rss_baseline_mb", round(self._rss_baseline_mb, 1))
        self.stats.post_gauge("warm_up_s", round(time.perf_counter() - t0, 2))
        self.stats.post_gauge("kernels_warm", 1)

    def _warm_up_failed(self, future: Future) -> None:
        err = None if future.cancelled() else future.exception()
        if err is not None and not isinstance(err, WorkerStopped):
            # The run goes on (a training step will meet the same error and report it) rather than wait.
            self.stats.post_problem("warm_up", f"could not load the mapping kernels: {type(err).__name__}: {err}")
            self.stats.post_gauge("kernels_warm", 1)

    def _part(self, part: str, msg, info: dict) -> None:  # noqa: ANN001 - any bundle message type
        """A complete bundle is decoded and queued, or refused whole and counted by kind (bad_seeds...)."""
        cpu0 = time.thread_time()
        stamp = stamp_to_ns(msg.header.stamp)
        if part == "pose":
            self._decided[stamp] = int(info.get("source_timestamp") or 0)
        b = self.intake.add(part, stamp, msg)
        self.stats.post_counter("duplicate_keyframe_parts", self.intake.duplicate_parts)
        self.stats.post_gauge("dropped_keyframe_bundles", self.intake.dropped)
        if b is None:
            return
        stage = "bad_seeds"
        try:
            kf = decode_keyframe_images(b, stamp, self.params.depth_scale, self._decided.pop(stamp, 0))
            points, colors = decode_seeds(pointcloud2_to_structured(b["seeds"]))
            kf = replace(kf, points_w=points, colors=colors)
            stage = "depth_scale"
            check_seed_depths(kf, self.params.depth_scale)
        except KeyframeBundleError as err:
            self.stats.post_problem(err.kind, f"keyframe {stamp} refused: {err}")
        except (MessageError, DataError) as err:
            self.stats.post_problem(stage, f"keyframe {stamp} refused: {err}")
        else:
            inserted = self.session.insert_keyframe(kf, time.thread_time() - cpu0)
            inserted.add_done_callback(self._report_failure("insert_keyframe"))
        self.lockstep.bundle_complete(stamp)
        if len(self._decided) > 64:  # poses whose bundle never completed
            self._decided = dict(list(self._decided.items())[-32:])

    def _report_failure(self, command: str) -> Callable[[Future], None]:
        """A done-callback for a session command nobody waits on: its error reaches the stats
        (``problem.command_failed``) instead of vanishing with the future."""
        def done(future: Future) -> None:
            err = None if future.cancelled() else future.exception()
            if err is not None and not isinstance(err, WorkerStopped):  # stopped: the node is shutting down
                self.stats.post_problem("command_failed", f"{command} failed: {type(err).__name__}: {err}")
        return done

    def _keyframe_poses(self, msg: Path) -> dict[int, np.ndarray]:
        poses: dict[int, np.ndarray] = {}
        for p in msg.poses:
            try:
                poses[stamp_to_ns(p.header.stamp)] = pose_to_matrix(p.pose)
            except (MessageError, DataError) as err:
                self.stats.post_problem("bad_pose",
                                        f"refined pose of keyframe {stamp_to_ns(p.header.stamp)} ignored: {err}")
        return poses

    def on_refined(self, msg: Path) -> None:
        """Keyframe poses refined by bundle adjustment: new training poses, the Gaussians stay
        (the session ignores unknown stamps)."""
        poses = self._keyframe_poses(msg)
        if poses:
            self.session.update_poses(poses).add_done_callback(self._report_failure("update_poses"))

    def on_loop_corrected(self, msg: Path) -> None:
        """Keyframe poses a loop closure corrected: each keyframe's Gaussians move with it and
        it is retrained first (``MappingSession.correct_keyframes``)."""
        poses = self._keyframe_poses(msg)
        if poses:
            self.session.correct_keyframes(poses).add_done_callback(self._report_failure("correct_keyframes"))

    def on_processed(self, msg: Header) -> None:
        """Lockstep: acknowledge a frame once its keyframe (if any) is queued and training ran.
        Always: remember announced keyframes, so ones that never arrive are counted."""
        stamp = stamp_to_ns(msg.stamp)
        if msg.frame_id == "keyframe":
            self.intake.announce(stamp, time.monotonic())
            self.stats.post_count("keyframes_announced")
        if self.params.lockstep:
            self.lockstep.processed(stamp, msg.frame_id == "keyframe", self.intake.seen(stamp))

    def _train_frame(self) -> Future:
        """A lockstep frame's training: queued on the session (after its keyframe's insertion)."""
        trained = self.session.train(self.params.lockstep_iterations)
        trained.add_done_callback(self._report_failure("train"))
        return trained

    def _sync_stats(self) -> None:
        """Session problems and status, and lost keyframes, into the stats; also applies what the
        session's threads posted."""
        self.stats.apply_posted()
        self.stats.counters["keyframes_missed"] += self.intake.missed(time.monotonic())
        for ev in self.session.poll_events():
            self.stats.problem(ev.kind, ev.message)
        st = self.session.status
        dict.update(self.stats.counters, st.counters)  # assigned, not added (Counter.update): totals
        self.stats.gauges.update(st.gauges())
        # Training speed over the last stats period: what the cores left the mapper (it runs niced
        # below the tracker, so this falls while tracking needs the CPU and rises when it idles).
        now = time.monotonic()
        last_t, last_it = self._rate_mark
        if now > last_t and last_it >= 0:
            self.stats.gauges["iterations_per_s"] = round((st.iteration - last_it) / (now - last_t), 1)
        self._rate_mark = (now, st.iteration)
        # Peak resident memory above the start-up baseline (VmHWM, read 10 times a second).
        if self._rss_baseline_mb is not None:
            self.stats.gauges["working_peak_mb"] = round(max(peak_rss_mb() - self._rss_baseline_mb, 0.0), 1)

    def send_delta(self, exact: bool = False) -> Future | None:
        """Queue a delta (exact: all, tolerance 0), published by the session in seq order; the
        periodic ones as ``DeltaPacer`` allows (``delta_waits`` counts a receiver lagging)."""
        return self.session.delta(None, True, self._publish_delta) if exact else self.deltas.tick()

    def _receivers_acked(self) -> bool:
        """Whether every delta receiver acknowledged every delta sent (never waits)."""
        return self.pub_delta.wait_for_all_acked(Duration(nanoseconds=0))

    def _publish_delta(self, rows: np.ndarray) -> None:  # on the session's outbox thread
        self._hand_over(lambda: self.pub_delta.publish(self._cloud(rows)))

    def _hand_over(self, publish: Callable[[], None]) -> None:
        """From the session's threads: queue a publication (or any ROS call) for the executor's thread."""
        self._outgoing.put(publish)
        self._outgoing_ready.trigger()

    def _publish_outgoing(self) -> None:
        while True:
            try:
                publish = self._outgoing.get_nowait()
            except queue.Empty:
                return
            publish()

    def _cloud(self, rows: np.ndarray) -> PointCloud2:
        return structured_to_pointcloud2(rows, self.get_clock().now().nanoseconds, self.params.world_frame)

    def publish_snapshot(self) -> Future:
        """Queue the whole map as a (latched) snapshot at the next seq: (size, seq)."""
        def publish(rows: np.ndarray) -> None:  # on the session's outbox thread
            self._hand_over(lambda: self.pub_snapshot.publish(self._cloud(rows)))

        return self.session.snapshot_message(publish)

    async def _done(self, future: Future[T]) -> T:
        """Await a session future in a coroutine callback without holding the executor: the
        future's completion is handed over, whose guard condition wakes the executor."""
        woken = RclpyFuture()
        future.add_done_callback(lambda _f: self._hand_over(lambda: woken.set_result(None)))
        await woken
        return future.result(timeout=0)

    async def _sleep(self, seconds: float) -> None:
        woken = RclpyFuture()
        timer: Timer | None = None

        def fire() -> None:
            assert timer is not None
            timer.cancel()
            self.destroy_timer(timer)
            woken.set_result(None)

        timer = self.create_timer(seconds, fire)
        await woken

    async def on_snapshot_request(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        _, n, seq = await self._done(self.publish_snapshot())
        res.success, res.message = True, f"seq={seq} gaussians={n}"
        return res

    async def on_finish(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        """Insert what is queued, stop training, run the final iterations, flush every change
        (core/mapping/finish.py)."""
        p = self.params
        self.deltas.finishing = True  # a latch, read by the periodic delta timer
        steps = FinishSteps(
            flush=lambda: self.session.delta(None, True, self._publish_delta), snapshot=self.publish_snapshot,
            save=self.save_checkpoint, receivers_acked=self._receivers_acked,
            wait=self._done, sleep=self._sleep, log=self.get_logger().info)
        plan = FinalPlan(p.final_iterations, p.final_densify, p.final_budget_s, p.final_total_iterations)
        res.success, res.message = True, await finish_map(self.session, plan, steps)
        return res

    def _render(self, pose: PoseStamped | None, requested: bool = False) -> None:
        """Queue a render at ``pose`` (the live view as ``LiveView`` allows; a requested one always)."""
        if pose is None:
            return
        stamp = stamp_to_ns(pose.header.stamp)
        if not requested and not self.live_view.due(stamp, self.session.status):
            return

        def send(view) -> None:  # noqa: ANN001 - RenderedView
            self.pub_color.publish(numpy_to_image(view.rgb, "rgb8", stamp, "render_camera"))
            self.pub_depth.publish(depth_to_image(view.depth, "32FC1", stamp, "render_camera"))
            self.pub_info.publish(camera_to_camera_info(view.camera, stamp, "render_camera"))

        def publish(view) -> None:  # noqa: ANN001 - on the session's worker
            self._hand_over(lambda: send(view))
        future = self.session.render(pose_to_matrix(pose.pose), publish=publish)
        future.add_done_callback(self._report_failure("render"))
        if not requested:
            self.live_view.started(future)

    def on_shutdown(self) -> None:
        try:  # bounded: the runner kills a node that takes longer than its stop deadline
            saved = self.save_checkpoint().result(timeout=SHUTDOWN_SAVE_TIMEOUT_S)
        except TimeoutError:
            self.get_logger().error(f"the checkpoint was not written within {SHUTDOWN_SAVE_TIMEOUT_S:.0f} s")
            saved = None
        except (OSError, DataError, WorkerStopped):  # counted by save_checkpoint
            saved = None
        if saved is not None:
            self.get_logger().info(f"checkpoint written to {self.ckpt.path} "
                                   f"({self.session.status.gaussians} Gaussians)")
        self.session.close(SESSION_CLOSE_TIMEOUT_S)

    def destroy_node(self) -> None:
        # The session's threads end with the node (idempotent after on_shutdown): a worker still in
        # native code (a warm-up's compile) when the process exits aborts it.
        self.session.close(SESSION_CLOSE_TIMEOUT_S)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(MapperNode, "mapper", args)


if __name__ == "__main__":
    sys.exit(main())
