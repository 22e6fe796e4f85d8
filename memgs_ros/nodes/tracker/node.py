"""tracker node: colour (+ depth) + camera_info in (sensor-data QoS; raw Images, or image_transport's
compressed topics); the camera's pose, odometry, TF, path and tracking state, each keyframe's images,
pose and keypoints, earlier keyframes' refined, loop-corrected and culled poses, and every frame's
answer (``memgs/tracker/processed``) out: each topic's type, content and QoS in docs/design.md's topic
table; the messages are made in ``outputs.py``, TF in ``tf.py``.

Frames are gated by ``core/tracking/frame_gate.py`` (its docstring has the stamp rules); a frame
dropped is still answered on ``memgs/tracker/processed``, so a player awaiting acknowledgements goes
on. Problems are counted as ``problem.<kind>`` in the stats and logged once per kind. The camera is
the first valid camera_info's, or the ``camera.*`` parameters' with ``camera_info_override``
(docs/usage.md, "Calibration from the config": the tracker is the camera's one way into the graph).
"""
from __future__ import annotations

import functools
import sys
import time
from typing import Any

from sensor_msgs.msg import CameraInfo, Image
from std_srvs.srv import Trigger

from memgs_ros.core.geometry.camera import describe_camera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.runtime.warm import WarmUpThread
from memgs_ros.core.tracking import Tracker, TrackerConfig, TrackResult, make_tracker, warm_up
from memgs_ros.core.tracking.frame_gate import CameraSource, LiveGate, StampRules
from memgs_ros.core.tracking.telemetry import timed_track
from memgs_ros.errors import ConfigError, DataError, MessageError
from memgs_ros.io.image_decoding import decode_camera_info
from memgs_ros.nodes.params import NODE_CONFIGS, TrackerParams
from memgs_ros.nodes.tracker.inputs import decompressed, to_frame
from memgs_ros.nodes.tracker.map_part import TrackerMapPart, map_check
from memgs_ros.nodes.tracker.outputs import TrackerOutbox
from memgs_ros.nodes.tracker.stats import TrackerStats
from memgs_ros.ros import qos
from memgs_ros.ros.camera_params import declare_calibration
from memgs_ros.ros.codecs import stamp_to_ns
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.images import subscribe_camera
from memgs_ros.ros.lifecycle import ManagedNode
from memgs_ros.ros.map_loading import NodeMapLoader
from memgs_ros.ros.node_main import run_node
from memgs_ros.ros.stamp_sync import RgbdPairing

__all__ = ["TrackerNode", "main"]

# What rclpy hands a subscription callback that takes two arguments (rmw's message info):
# source_timestamp (ns, the publisher's clock), received_timestamp, publication_sequence_number, ...
MessageInfo = dict[str, Any]

CONFIGS = NODE_CONFIGS["tracker"]
_WARM_UP_JOIN_S = 10.0  # how long a node being destroyed waits for its warm-up thread


class TrackerNode(ManagedNode):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("tracker", **node_kwargs)
        self.params = v = declare_config(self, TrackerParams, "")
        self.cfg: TrackerConfig = declare_config(self, TrackerConfig, "tracker")
        self.calibration = declare_calibration(self)
        if v.camera_info_override and self.calibration is None:
            raise ConfigError("camera_info_override is true but no calibration is set: give camera.width, "
                              "camera.height, camera.fx, camera.fy, camera.cx, camera.cy (and distortion)")
        NodeMapLoader(self, "memgs/tracker/load_map", lambda: map_check(self))  # a map at run time
        self._last_images: tuple[Image, Image | None] | None = None  # the last tracked frame's (end_flight)
        self.create_service(Trigger, "memgs/tracker/end_flight", self.on_end_flight)
        self.start_lifecycle(v.autostart)

    def configure_node(self) -> None:
        v, calibration = self.params, self.calibration
        # The configured camera replaces camera_info (override), else the first camera_info's.
        self.cams: CameraSource[tuple[Image, Image | None]] = CameraSource(
            calibration if v.camera_info_override else None)
        self.rgbd = self.cfg.mode == "rgbd"
        self.stamps = StampRules(int(1e9 * v.time_jump_back_s), int(1e9 * v.max_stamp_ahead_s))
        self.gate = LiveGate(int(1e9 * v.max_frame_age_s))  # 0: never stale (the runner's acknowledged replays)
        self.pairing = RgbdPairing(
            0 if v.sync == "exact" else int(v.max_sync_dt_s * 1e9), v.unpaired_warn_s,
            (self.resolve_topic_name(v.color_topic), self.resolve_topic_name(v.depth_topic), v.max_sync_dt_s),
            lambda pair: self._handle(pair[1], pair[2]), self._unpaired,
            lambda why: self.stats.problem("unpaired_color", why))
        self.tracker: Tracker | None = None
        self.stats = TrackerStats(self)
        self.out = TrackerOutbox(self, v, self.stats)
        self.bundle = TrackerMapPart(self, v, self.stats, lambda: self.tracker, lambda: {
            "frames": self.stats.frames_in, "depth_scale": v.depth_scale, "map_frame": v.map_frame})
        sensor = qos.sensor() if v.input_reliability == "best_effort" else qos.reliable(5)
        self.create_subscription(CameraInfo, v.camera_info_topic, self.on_camera_info, sensor)
        self.compressed = v.image_transport == "compressed"  # decoded once a frame is taken
        self.get_logger().info(f"tracking {self.cfg.mode} from " + subscribe_camera(
            self, v.color_topic, v.depth_topic if self.rgbd else None, self.compressed, self.on_color,
            lambda msg: self.pairing.depth(stamp_to_ns(msg.header.stamp), msg), sensor))
        # The kernels load (on a fresh install: compile, ~10 s) beside the executor, neither on the
        # first frame (a live camera does not wait) nor in __init__ (a compiling node missed its stop
        # deadline). The runner starts a replay once ``kernels_warm`` is 1; a live frame before
        # that is counted (skipped.warming); an acknowledged frame waits (inside make_tracker).
        self.stats.kernels_warm = 0
        self._warm = WarmUpThread(warm_up, self._warmed, name="tracker-warm-up")
        # It starts by reading ORB's tests off OpenCV (~0.5 s, in native code): a process that exits
        # under it aborts. Bounded: a first compile after that can take ~10 s.
        self.end_with_node("warm-up", functools.partial(self._warm.join, _WARM_UP_JOIN_S))

    def _warmed(self, seconds: float, error: Exception | None) -> None:
        if error is not None:
            self.stats.post_problem("warm_up", f"could not load the tracking kernels ahead of time: {error}")
        self.stats.post_set(TrackerStats.warm_up_s, round(seconds, 2))
        self.stats.post_set(TrackerStats.kernels_warm, 1)

    def wait_until_warm(self, timeout_s: float) -> bool:
        """Whether the kernels are in within ``timeout_s`` (a live frame before that is "warming")."""
        return self._warm.wait(timeout_s)

    # ------------------------------------------------------------------ inputs
    def on_camera_info(self, msg: CameraInfo) -> None:
        try:
            cam = decode_camera_info(msg)
        except MessageError as err:
            self.stats.problem("camera_info", f"camera_info refused: {err}")
            return
        verdict = self.cams.info(cam)
        if verdict.kind == "set":
            self._camera_set("camera_info")
            for color, depth in verdict.released:
                self._handle(color, depth)
        elif verdict.kind == "changed":
            self.stats.problem("camera_changed", "camera_info changed after tracking started; keeping the first")
        elif verdict.kind == "differs":
            self.stats.camera_info_differs += 1
            self.get_logger().warning(
                f"camera_info on {self.resolve_topic_name(self.params.camera_info_topic)} ({describe_camera(cam)}) "
                f"differs from the configured calibration by more than 1 % ({'; '.join(verdict.differences)}): "
                "using the configured one (camera_info_override)")

    def _camera_set(self, origin: str) -> None:
        assert self.cams.camera is not None
        self.tracker = make_tracker(self.cfg, self.cams.camera)
        self.bundle.load_into(self.tracker)  # map_bundle: no pose until relocalised in it
        self.get_logger().info(f"camera from {origin}: {describe_camera(self.cams.camera)}")

    def on_color(self, msg: Image, info: MessageInfo) -> None:
        if not self.active:  # paused (lifecycle inactive): counted, answered, not tracked
            self.stats.skipped["inactive"] += 1
            self.out.processed(stamp_to_ns(msg.header.stamp))
            return
        seq, sent = int(info.get("publication_sequence_number") or 0), int(info.get("source_timestamp") or 0)
        refused, lost = self.gate.admit(seq, sent, time.time_ns(), self._warm.ready.is_set())
        self.stats.skipped["busy"] += lost
        if refused is not None:
            self.stats.skipped[refused] += 1
            self.out.processed(stamp_to_ns(msg.header.stamp))
        elif not self.rgbd:
            self._handle(msg, None)
        else:
            self.pairing.color(stamp_to_ns(msg.header.stamp), msg, time.monotonic())

    def _unpaired(self, n: int) -> None:
        self.stats.skipped["unpaired"] += n

    def _ready_camera(self, color: Image, depth: Image | None) -> bool:
        """Whether the camera is known; else the frame waits for camera_info (the one it pushes out
        is answered), or the configured calibration does not fit it (answered, counted)."""
        had = self.cams.camera is not None
        try:
            known, dropped = self.cams.for_frame((color, depth), color.width, color.height)
        except DataError as err:
            self.stats.problem("camera_info", f"the configured calibration does not fit the images: {err}")
            self.stats.frames_in += 1
            self.out.processed(stamp_to_ns(color.header.stamp))
            return False
        if dropped is not None:
            self.stats.problem("no_camera_info", f"no valid camera_info on {self.params.camera_info_topic} yet: "
                                                 "dropping the oldest waiting frame")
            self.out.processed(stamp_to_ns(dropped[0].header.stamp))
        if known and not had:
            self._camera_set("the configured calibration (camera_info_override)")
        return known

    def _handle(self, color: Image, depth: Image | None) -> None:
        cpu0, wall0 = time.thread_time(), time.perf_counter()  # this thread's CPU: the frame path alone
        images = decompressed(color, depth, self.params.depth_scale, self.stats) if self.compressed else (color, depth)
        if images is None:
            self.out.processed(stamp_to_ns(color.header.stamp))  # refused, counted
            return
        color, depth = images
        if not self._ready_camera(color, depth):
            return
        self.stats.frames_in += 1
        t, cam = self.tracker, self.cams.camera
        assert t is not None and cam is not None  # made together with the camera (_camera_set)
        frame = to_frame(color, depth, cam, self.stamps, self.get_clock().now().nanoseconds, self.params.depth_scale,
                         self.stats)
        if frame is None:
            self.out.processed(stamp_to_ns(color.header.stamp))
            return
        result = self._track(t, frame)
        self._last_images = (color, depth)
        self.out.frame(result, cam, color, depth, t.poll_refined_keyframes(),
                       t.poll_loop_corrected_keyframes(), t.poll_loop_corrections(), t.poll_culled_keyframes())
        self.out.frame_cost(cpu0, wall0)

    def _track(self, tracker: Tracker, frame: Frame) -> TrackResult:
        """``tracker.track(frame)``, its cost and the sparse map's size in the stats (``timed_track``)."""
        tracker.covariance_wanted = self.out.odometry_wanted()
        result, smap = timed_track(self.stats, tracker, frame, not self.cfg.ba_threaded, self.stats.problem)
        if smap is not None:
            self.out.keyframes.forget(smap.keyframe_ids, smap.keyframes)
        return result

    def on_end_flight(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        """``memgs/tracker/end_flight`` (the runner calls it at the source's end): the last tracked
        frame becomes a keyframe unless one sees its view (``Tracker.end_flight``). Answers
        "keyframe <stamp ns>" or "none"."""
        t, images, self._last_images = getattr(self, "tracker", None), self._last_images, None
        result = t.end_flight() if t is not None and images is not None else None  # a tracker: a camera
        res.success, res.message = True, "none"
        if result is None or t is None or images is None or self.cams.camera is None:
            return res
        self.out.end_flight(result, self.cams.camera, *images, t.poll_refined_keyframes(), t.poll_culled_keyframes())
        self.get_logger().info(f"the flight's last view ({result.stamp_ns}) made a keyframe")
        res.success, res.message = True, f"keyframe {result.stamp_ns}"
        return res

    def close_node(self) -> None:
        if self.tracker is not None:
            self.tracker.close()
            self.tracker = None


def main(args: list[str] | None = None) -> int:
    return run_node(TrackerNode, "tracker", args)


if __name__ == "__main__":
    sys.exit(main())
