"""mapper node: turns keyframes, poses and requests into commands of a ``MappingSession``
(core/mapper_service/session.py, the one owner of the Gaussian map) and publishes what it returns.

In: ``memgs/keyframe/{color,depth,camera_info,pose,seeds}`` (one stamp per keyframe),
``memgs/keyframe/refined_poses`` (bundle adjustment), ``memgs/keyframe/loop_corrected_poses``,
``memgs/keyframe/culled`` (keyframes the tracker culled: out of training),
``memgs/pose`` (live view), ``memgs/render/view_pose``, ``memgs/tracker/processed`` (an acknowledged replay).
Out: ``memgs/map/delta`` (core/map_io/map_delta.py), ``memgs/mapper/snapshot`` (latched, with a packed ``rgb`` colour),
``memgs/render/{color,depth,camera_info}``, ``memgs/frame_ack``, ``memgs/mapper/stats``; services
``memgs/mapper/publish_snapshot`` and ``memgs/mapper/finish``
(answers a ``MapAnswer``: seq, gaussians, epoch). With ``checkpoint_path`` the session's state is
written there atomically (periodically, at finish and shutdown) and a restarted mapper resumes
from it under a new delta epoch, publishing a snapshot so the merger replaces its copy.

The node translates messages and parameters; the rules are ROS-free services in core/mapping/:
``mapper_start`` (device, resume), ``output_pacing`` (periodic deltas, live view), ``finish`` and
``checkpoint_saver``; a replay's acknowledgements are the replay service's (core/runtime/replay.py).
Messages are read in nodes/mapper/inputs.py and sent from nodes/mapper/outputs.py; the stats are
nodes/mapper/stats.py's.
"""
from __future__ import annotations

import functools
import pathlib
import sys
import time
from concurrent.futures import Future
from typing import Any

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.callback_groups import ReentrantCallbackGroup
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from memgs_ros.core.map_io.answers import MapAnswer
from memgs_ros.core.map_io.map_delta import message_dtype
from memgs_ros.core.mapper_service.checkpoint_saver import CheckpointSaver
from memgs_ros.core.mapper_service.finish import FinalPlan, FinishSteps, finish_map
from memgs_ros.core.mapper_service.mapper_start import MapperStart, SessionOptions, start_mapper
from memgs_ros.core.mapper_service.output_pacing import DeltaPacer, LiveView, delta_rows
from memgs_ros.core.mapping import checkpoint
from memgs_ros.core.mapping.mapper import MappingConfig
from memgs_ros.core.merge.config import MergeConfig
from memgs_ros.core.raster.backend_choice import device_label
from memgs_ros.core.runtime.replay import FrameAcknowledger
from memgs_ros.nodes.mapper.inputs import KeyframeReceiver, keyframe_poses
from memgs_ros.nodes.mapper.outputs import MapperOutbox
from memgs_ros.nodes.mapper.stats import MapperStats
from memgs_ros.nodes.params import NODE_CONFIGS, MapperParams
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import pose_to_matrix, stamp_to_ns
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.lifecycle import ManagedNode
from memgs_ros.ros.map_bundles import PartService
from memgs_ros.ros.map_loading import NodeMapLoader, set_aside_checkpoint
from memgs_ros.ros.node_main import run_node

CONFIGS = NODE_CONFIGS["mapper"]
SHUTDOWN_SAVE_TIMEOUT_S = 15.0  # within the runner's stop deadline (20 s)
SESSION_CLOSE_TIMEOUT_S = 30.0  # the step or command in progress ends first (a cold warm-up: ~20 s)


class MapperNode(ManagedNode):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("mapper", **node_kwargs)
        self.params = p = declare_config(self, MapperParams, "")
        self.niceness = p.niceness  # applied by run_node to this node's process
        self.cfg: MappingConfig = declare_config(self, MappingConfig, "mapping")
        self.merge_cfg: MergeConfig = declare_config(self, MergeConfig, "merge")
        NodeMapLoader(self, "memgs/mapper/load_map", dict,  # its state is in metres: any depth unit will do
                      set_aside_checkpoint(p.checkpoint_path))  # a map at run time: its checkpoint won't win
        self.start_lifecycle(p.autostart)

    def configure_node(self) -> None:
        """torch and the device, the session (resumed from the checkpoint), the topics and timers."""
        p = self.params
        self.frozen = p.map_mode == "localize"  # a loaded map rendered, never trained
        opts = SessionOptions(pacing=p.replay, insert_queue=p.insert_queue, delta_tolerance=p.delta_tolerance,
                              niceness=p.niceness, checkpoint_path=p.checkpoint_path, resume=p.resume,
                              map_bundle=p.map_bundle, frozen=self.frozen)
        start = start_mapper(self.cfg, self.merge_cfg, p.device, opts)
        self.session = start.session
        # its threads end with the node (close is idempotent): a worker still compiling aborts an exiting process
        self.end_with_node("session", functools.partial(self.session.close, SESSION_CLOSE_TIMEOUT_S))
        before = start.resumed.iteration if start.from_bundle is not None and start.resumed else 0  # a bundle's
        self.final_total = p.final_total_iterations and p.final_total_iterations + before  # ... are not this flight's
        self.stats = MapperStats(self, start.raster.backend, p.checkpoint_period_s if p.checkpoint_path else 0.0)
        self.checkpoints = CheckpointSaver(self.session, start.checkpoint, self.stats)
        self.out = MapperOutbox(self, p.world_frame, p.ack_topic)
        # These three: the executor's thread only.
        self.deltas = DeltaPacer(
            delta_rows(p.delta_budget_kbytes_per_s, p.delta_rate_hz, message_dtype(self.cfg.max_sh_degree).itemsize),
            lambda rows: self.stats.watch(self.session.delta(rows, False, self.out.delta_rows), "delta"),
            self.out.receivers_acked,
            lambda: self.stats.post_add(MapperStats.delta_waits))
        self.live_view = LiveView()
        self.acks = FrameAcknowledger(
            p.ack_window, lambda: self.stats.watch(self.session.train(0 if self.frozen else p.iterations_per_frame),
                                                   "train"),
            self.out.hand_over, self.out.ack, self.stats.ack_ms.add)
        self.latest_pose: PoseStamped | None = None
        topics = {"color": Image, "camera_info": CameraInfo, "pose": PoseStamped, "seeds": PointCloud2,
                  **({"depth": Image} if p.mode == "rgbd" else {})}
        self.keyframes = KeyframeReceiver(set(topics), self.session.resumed_stamps)
        self._subscribe(topics)
        self._serve(checkpoints=start.checkpoint is not None)
        # The bundle's mapper part: the session's state as a checkpoint file, captured and written on its worker.
        PartService(self, "mapper", p.bundle_dir, self.out.hand_over,
                    lambda path: self.session.save_state(lambda st: checkpoint.save(st, path)),
                    lambda: self.stats.post_add(MapperStats.map_parts), "the mapper state",
                    f" sh_degree={self.cfg.max_sh_degree}")
        if start.resumed is not None:
            self._periodic_snapshot()  # latched: the merger takes the resumed map and its epoch
        # The rasterizer's and SSIM's compiled kernels load (on a fresh install: compile) as the
        # session's first command, on its worker, while the node already spins (a stop is answered
        # meanwhile) and keyframes queue behind it; kernels_warm says when they are in.
        self.stats.warm_up(self.session, start.device, self.cfg)
        self.create_timer(0.1, lambda: self.stats.sync(self.session, self.keyframes.intake))
        self._log_start(start)

    def _subscribe(self, topics: dict[str, type]) -> None:
        # One thread runs every callback (run_node's single-threaded executor) and none of them waits:
        # training, deltas and renders run on the session's threads, whose results are handed back
        # through one queue (MapperOutbox.hand_over); the services that must wait for them are
        # coroutines, each in a group of its own, so everything else goes on meanwhile. (A
        # multi-threaded executor took ~30 ms, at times seconds, to pick up a message here: every
        # acknowledged frame waited on it.)
        kfq = qos.keyframes()  # a resumed mapper gets the keyframes sent while it was down
        for part, msg_type in topics.items():
            self.create_subscription(msg_type, f"memgs/keyframe/{part}", lambda m, info, p=part: self._part(p, m, info),
                                     kfq)
        self.create_subscription(Path, "memgs/keyframe/refined_poses", self.on_refined, qos.reliable(20))
        self.create_subscription(Path, "memgs/keyframe/culled", self.on_culled, qos.reliable(20))
        self.create_subscription(Path, "memgs/keyframe/loop_corrected_poses", self.on_loop_corrected,
                                 qos.reliable(20))
        self.create_subscription(Header, "memgs/tracker/processed", self.on_processed, qos.reliable(100))
        self.create_subscription(PoseStamped, "memgs/pose", lambda m: setattr(self, "latest_pose", m), qos.reliable(5))
        self.create_subscription(PoseStamped, "memgs/render/view_pose", lambda m: self._render(m, True),
                                 qos.reliable(5))

    def _serve(self, checkpoints: bool) -> None:
        """The services and the periodic deltas, snapshots, checkpoints and live views."""
        p = self.params
        self.create_service(Trigger, "memgs/mapper/publish_snapshot", self.on_snapshot_request,
                            callback_group=ReentrantCallbackGroup())
        self.create_service(Trigger, "memgs/mapper/finish", self.on_finish, callback_group=ReentrantCallbackGroup())
        self.create_timer(1.0 / p.delta_rate_hz, self.deltas.tick)
        if p.replay.acknowledged:
            self.create_timer(1.0, self.acks.expire_parts)  # the last frame's pose messages, at most PART_WAIT_S
        if p.snapshot_period_s > 0:
            self.create_timer(p.snapshot_period_s, self._periodic_snapshot)
        if checkpoints and p.checkpoint_period_s > 0:
            self.create_timer(p.checkpoint_period_s, self.save_checkpoint)
        if p.render_rate_hz > 0:
            self.create_timer(1.0 / p.render_rate_hz, lambda: self._render(self.latest_pose))

    def _log_start(self, start: MapperStart) -> None:
        log = self.get_logger()
        if start.set_aside:
            log.error(start.set_aside)
        elif start.resumed is not None and (where := start.from_bundle or start.checkpoint) is not None:
            self.stats.resumed += 1
            r = start.resumed
            log.info(f"resumed from {getattr(where, 'path', where)}: {len(r.gaussians)} Gaussians, {len(r.keyframes)} "
                     f"keyframes, iteration {r.iteration}{' (localize: not trained)' if self.frozen else ''}")
        log.info(f"mapper on {device_label(start.device)}, rasterizer {start.raster.backend}, "
                 f"{'per-frame' if self.params.replay.acknowledged else 'free-running'} training "
                 f"({self.params.pacing})")
        if start.raster.fallback_warning:
            log.warning("CUDA without gsplat: the torch fallback rasterizer is several times slower; "
                        "install gsplat (README 'On a Jetson')")

    def save_checkpoint(self, force: bool = False) -> Future[pathlib.Path | None]:
        """The session's state written if changed (``CheckpointSaver``): its path, or None (counted)."""
        return self.checkpoints.save(force)

    def _part(self, part: str, msg: Any, info: dict[str, Any]) -> None:
        """A complete bundle is decoded and queued, or refused whole and counted by kind (bad_seeds...)."""
        cpu0 = time.thread_time()
        got = self.keyframes.add(part, msg, info)
        self.stats.post_set(MapperStats.duplicate_keyframe_parts, self.keyframes.intake.duplicate_parts)
        self.stats.post_set(MapperStats.dropped_keyframe_bundles, self.keyframes.intake.dropped)
        if got is None:
            return
        if got.keyframe is None:
            self.stats.post_problem(got.problem, got.message)
        else:
            self.stats.watch(self.session.insert_keyframe(got.keyframe, time.thread_time() - cpu0), "insert_keyframe")
        self.acks.bundle_complete(got.stamp_ns)

    def _keyframe_poses(self, msg: Path) -> dict[int, Any]:
        poses, refused = keyframe_poses(msg)
        for line in refused:
            self.stats.post_problem("bad_pose", line)
        return poses

    def on_refined(self, msg: Path) -> None:
        """Keyframe poses refined by bundle adjustment: new training poses, the Gaussians stay
        (the session ignores unknown stamps)."""
        poses = self._keyframe_poses(msg)
        if poses:
            self.stats.watch(self.session.update_poses(poses), "update_poses")
        self._part_arrived(msg, "refined")

    def on_culled(self, msg: Path) -> None:
        """Keyframes the tracker culled as redundant: their views leave training and their Gaussians
        follow the nearest kept keyframe (``MappingSession.retire_keyframes``)."""
        poses = self._keyframe_poses(msg)
        if poses:
            self.stats.watch(self.session.retire_keyframes(list(poses)), "retire_keyframes")
        self._part_arrived(msg, "culled")

    def on_loop_corrected(self, msg: Path) -> None:
        """Keyframe poses a loop closure corrected: each keyframe's Gaussians move with it and
        it is retrained first (``MappingSession.correct_keyframes``)."""
        poses = self._keyframe_poses(msg)
        if poses:
            self.stats.watch(self.session.correct_keyframes(poses), "correct_keyframes")
        self._part_arrived(msg, "loop")

    def _part_arrived(self, msg: Path, part: str) -> None:
        """Acknowledged pacing: a pose message the tracker sent with the frame it is stamped with,
        its command queued; that frame's training may follow (``FrameAcknowledger``)."""
        if self.params.replay.acknowledged:
            self.acks.part_arrived(stamp_to_ns(msg.header.stamp), part)

    def on_processed(self, msg: Header) -> None:
        """Acknowledged pacing: acknowledge a frame once its keyframe (if any) and the pose messages
        sent with it are queued and training ran (``FrameAcknowledger``). Always: remember announced
        keyframes, so ones that never arrive are counted."""
        kind, *parts = msg.frame_id.split("+")  # "keyframe" or "frame", then the pose messages sent with it
        stamp, keyframe = stamp_to_ns(msg.stamp), kind == "keyframe"
        if keyframe:
            self.keyframes.intake.announce(stamp, time.monotonic())
            self.stats.post_add(MapperStats.keyframes_announced)
        if self.params.replay.acknowledged:
            self.acks.processed(stamp, keyframe, self.keyframes.intake.seen(stamp), frozenset(parts))

    def publish_snapshot(self) -> Future:
        """Queue the whole map as a (latched) snapshot at the next seq: (rows, size, seq)."""
        return self.session.snapshot_message(self.out.snapshot_rows)

    def _periodic_snapshot(self) -> None:
        """A snapshot nobody waits for (timer, resume): its error is counted."""
        self.stats.watch(self.publish_snapshot(), "snapshot")

    async def on_snapshot_request(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        _, n, seq = await self.out.hand_over.result(self.publish_snapshot())
        res.success, res.message = True, MapAnswer(seq, n).message()
        return res

    async def on_finish(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        """Insert what is queued, stop training, run the final iterations, flush every change
        (core/mapper_service/finish.py)."""
        p, hand_over = self.params, self.out.hand_over
        self.deltas.finishing = True  # a latch, read by the periodic delta timer
        steps = FinishSteps(
            flush=lambda: self.session.delta(None, True, self.out.delta_rows), snapshot=self.publish_snapshot,
            save=self.save_checkpoint, receivers_acked=self.out.receivers_acked, wait=hand_over.result,
            sleep=hand_over.sleep, log=self.get_logger().info)
        plan = FinalPlan() if self.frozen else FinalPlan(p.final_iterations, p.final_densify, p.final_budget_s,
                                                         self.final_total)
        res.success, res.message = True, await finish_map(self.session, plan, steps)
        return res

    def _render(self, pose: PoseStamped | None, requested: bool = False) -> None:
        """Queue a render at ``pose``: the live view's as ``LiveView`` allows, a requested one always."""
        if pose is None:
            return
        stamp = stamp_to_ns(pose.header.stamp)
        if not requested and not self.live_view.due(stamp, self.session.status):
            return
        rendered = self.session.render(pose_to_matrix(pose.pose), publish=self.out.view_at(stamp))
        self.stats.watch(rendered, "render")
        if not requested:
            self.live_view.started(rendered)

    def set_active(self, active: bool) -> None:
        """Inactive: training pauses (keyframes are still taken in, the map is served and saved)."""
        super().set_active(active)
        if self.configured:
            self.stats.watch(self.session.set_training(active), "set_training")

    def close_node(self) -> None:
        self.session.interrupt()  # a finish in progress ends after its step: the save comes next
        try:  # bounded: the runner kills a node that takes longer than its stop deadline
            saved = self.checkpoints.save_within(SHUTDOWN_SAVE_TIMEOUT_S)
        except TimeoutError:
            self.get_logger().error(f"the checkpoint was not written within {SHUTDOWN_SAVE_TIMEOUT_S:.0f} s")
        else:
            if saved is not None:
                self.get_logger().info(f"checkpoint written to {saved} ({self.session.status.gaussians} Gaussians)")
        self.session.close(SESSION_CLOSE_TIMEOUT_S)
        self.out.hand_over.close()  # a cleanup destroys the publishers: what the session sent late is dropped


def main(args: list[str] | None = None) -> int:
    return run_node(MapperNode, "mapper", args)


if __name__ == "__main__":
    sys.exit(main())
