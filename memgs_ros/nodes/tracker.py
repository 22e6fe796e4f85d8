"""tracker node: colour (+ depth) + camera_info in; pose, path, tracking state and keyframes out.

Subscribes (sensor-data QoS): ``color_topic``, ``depth_topic`` (RGB-D only), ``camera_info_topic``.
Publishes: ``memgs/pose`` (PoseStamped), ``memgs/odom`` (Odometry), ``memgs/path`` (Path),
``memgs/tracking_state`` (String), per keyframe ``memgs/keyframe/{color,depth,camera_info,pose,
keypoints}`` sharing the frame's stamp (images as recorded with the camera's distortion in
camera_info; keypoint u, v are undistorted pixel positions), refined keyframe poses after local
BA on ``memgs/keyframe/refined_poses`` and the keyframes a loop closure corrected on
``memgs/keyframe/loop_corrected_poses`` (Path each, one PoseStamped per keyframe stamp: the mapper
takes the first as new training poses and moves each keyframe's Gaussians with the second), and
``memgs/tracker/processed`` (Header; frame_id "keyframe" or "frame") for every frame handled, which
the lockstep player or the mapper waits on.

``memgs/pose`` and ``memgs/odom`` are per-frame odometry, published once and never revised.
``memgs/path`` is the corrected trajectory: each pose moves with the keyframe it was tracked
against when a loop closure corrects that keyframe (``AnchoredPath``; local BA refinements go
only to the mapper).

Frame stamps (a frame is the colour image and its paired depth, stamped by the colour header):
- a stamp equal to the previous frame's is a duplicate delivery: dropped (``stamp_duplicate``);
- a stamp up to ``time_jump_back_s`` before the previous one is a late, out-of-order frame: dropped
  (``stamp_order``), since tracking cannot go back in time;
- a stamp more than ``time_jump_back_s`` before the previous one is a time reset (a bag replayed in
  a loop, a restarted sensor or sim clock): the frame is accepted, counted (``time_jump_back``),
  and the stamp order starts again from it. The map is kept: the tracker relocalises in it, or
  starts a new segment if it cannot;
- a stamp more than ``max_stamp_ahead_s`` ahead of the node's clock (when that clock runs) is a
  broken sensor clock: dropped (``stamp_future``), so one bad stamp cannot block the frames after it.
Every dropped frame is still answered on ``memgs/tracker/processed`` so a lockstep player goes on.
Problems are counted on ``memgs/tracker/stats`` as ``problem.<kind>`` and logged once per kind.

Calibration: the camera comes from the first valid camera_info, or, with ``camera_info_override``,
from the ``camera.*`` parameters (fitted to the image size; camera_info is then only compared
with it, one warning when they differ by more than 1 %). The tracker is the one entry point of
the camera into the graph: sampler and mapper take the keyframe camera_info it republishes, so
the override applies once, to every source.
"""
from __future__ import annotations

import sys
import threading
import time
from collections import deque
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rclpy.node import Node
from rclpy.publisher import Publisher
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header, String

from memgs_ros.core.geometry.camera import PinholeCamera, calibration_differences, describe_camera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.tracking import Tracker, TrackerConfig, TrackResult, make_tracker, warm_up
from memgs_ros.core.tracking.anchored_path import AnchoredPath
from memgs_ros.errors import ConfigError, DataError, MessageError
from memgs_ros.io.image_decoding import decode_camera_info, decode_depth, decode_rgb
from memgs_ros.nodes.params import NODE_CONFIGS, TrackerParams
from memgs_ros.ros import qos
from memgs_ros.ros.camera_params import declare_calibration
from memgs_ros.ros.codecs import (
    append_to_path,
    camera_to_camera_info,
    make_header,
    matrix_to_odometry,
    matrix_to_pose_stamped,
    stamp_to_ns,
    structured_to_pointcloud2,
)
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats, RollingMedian
from memgs_ros.ros.node_main import run_node
from memgs_ros.ros.stamp_sync import NearestPairer

# What rclpy hands a subscription callback that takes two arguments (rmw's message info):
# source_timestamp (ns, the publisher's clock), received_timestamp, publication_sequence_number, ...
MessageInfo = dict[str, Any]

KEYPOINT_DTYPE = np.dtype([("u", np.float32), ("v", np.float32), ("depth", np.float32), ("active", np.uint8)])


CONFIGS = NODE_CONFIGS["tracker"]
_WARM_UP_JOIN_S = 10.0  # how long a node being destroyed waits for its warm-up thread


class TrackerNode(Node):
    def __init__(self, **node_kwargs: object) -> None:
        super().__init__("tracker", **node_kwargs)
        v = declare_config(self, TrackerParams, "")
        self.color_topic, self.depth_topic, self.info_topic = v.color_topic, v.depth_topic, v.camera_info_topic
        self.depth_scale, self.sync, max_dt = v.depth_scale, v.sync, v.max_sync_dt_s
        self.world_frame, self.camera_frame = v.world_frame, v.camera_frame
        self.input_reliability, self.path_max_len = v.input_reliability, v.path_max_len
        path_rate = v.path_rate_hz
        self.jump_back_ns = int(1e9 * v.time_jump_back_s)
        self.max_ahead_ns = int(1e9 * v.max_stamp_ahead_s)
        self.max_age_ns = int(1e9 * v.max_frame_age_s)  # 0: never (the runner's lockstep replays)
        self._least_wait_ns: int | None = None  # least publish-to-callback wait seen (transport + clock offset)
        self._last_color_seq = 0  # the colour publisher's sequence number last seen (0 = none yet)
        self._frame_cpu_ms = RollingMedian()  # node CPU per tracked frame, message in to pose out
        self._frame_ms = RollingMedian()  # its wall time (a lockstep frame's share of the cycle)
        self.cfg: TrackerConfig = declare_config(self, TrackerConfig, "tracker")
        override = v.camera_info_override
        calibration = declare_calibration(self)
        if override and calibration is None:
            raise ConfigError("camera_info_override is true but no calibration is set: give camera.width, "
                              "camera.height, camera.fx, camera.fy, camera.cx, camera.cy (and distortion)")
        # The configured camera when it replaces camera_info, else None.
        self.calibration: PinholeCamera | None = calibration if override else None
        self._info_compared = False
        self.rgbd = self.cfg.mode == "rgbd"

        self.stats = NodeStats(self, "tracker")
        self.stats.computed["frame_cpu_ms_median"] = self._frame_cpu_ms  # a median per frame cost 0.4 ms
        self.stats.computed["frame_ms_median"] = self._frame_ms
        self.camera: PinholeCamera | None = None
        self.tracker: Tracker | None = None
        self.last_stamp_ns = -1
        self.kf_stamps: dict[int, int] = {}
        self.path = Path()
        self.path.header.frame_id = self.world_frame
        # Every published pose anchored to its reference keyframe: memgs/path shows them loop-corrected.
        self.anchored = AnchoredPath(self.path_max_len)
        self._path_stale: set[int] = set()  # keyframes moved since the last path publication
        self.kf_path = Path()
        self.kf_path.header.frame_id = self.world_frame
        # Frames that arrive before the first camera_info wait here (camera topics race at start).
        self.waiting: deque[tuple[Image, Image | None]] = deque(maxlen=5)
        self.pairer: NearestPairer[Image] = NearestPairer(
            max_dt_ns=0 if self.sync == "exact" else int(max_dt * 1e9), queue_size=5)

        rel = qos.reliable(10)
        self.pub_pose = self.create_publisher(PoseStamped, "memgs/pose", rel)
        self.pub_odom = self.create_publisher(Odometry, "memgs/odom", rel)
        self.pub_path = self.create_publisher(Path, "memgs/path", rel)
        self._path_changed = False
        self.create_timer(1.0 / path_rate, self._publish_path)
        self.pub_state = self.create_publisher(String, "memgs/tracking_state", rel)
        self.pub_processed = self.create_publisher(Header, "memgs/tracker/processed", qos.reliable(100))
        kf = qos.keyframes()  # replayed to a restarted sampler/mapper
        self.pub_kf_color = self.create_publisher(Image, "memgs/keyframe/color", kf)
        self.pub_kf_depth = self.create_publisher(Image, "memgs/keyframe/depth", kf)
        self.pub_kf_info = self.create_publisher(CameraInfo, "memgs/keyframe/camera_info", kf)
        self.pub_kf_pose = self.create_publisher(PoseStamped, "memgs/keyframe/pose", kf)
        from sensor_msgs.msg import PointCloud2  # local: only the keypoint cloud needs it
        self.pub_kf_kps = self.create_publisher(PointCloud2, "memgs/keyframe/keypoints", kf)
        self.pub_refined = self.create_publisher(Path, "memgs/keyframe/refined_poses", qos.reliable(20))
        self.pub_loop = self.create_publisher(Path, "memgs/keyframe/loop_corrected_poses", qos.reliable(20))

        sensor = qos.sensor() if self.input_reliability == "best_effort" else qos.reliable(5)
        self.create_subscription(CameraInfo, self.info_topic, self.on_camera_info, sensor)
        self.create_subscription(Image, self.color_topic, self.on_color, sensor)
        if self.rgbd:
            self.create_subscription(Image, self.depth_topic, self.on_depth, sensor)
        self.get_logger().info(
            f"tracking {self.cfg.mode} from {self.resolve_topic_name(self.color_topic)}"
            + (f" + {self.resolve_topic_name(self.depth_topic)}" if self.rgbd else ""))
        # Load (on a fresh install: compile, ~10 s) the tracking kernels beside the executor, not on
        # the first frame: a live camera does not wait, and 0.4 s of loading on frame 1 cost the next
        # dozen frames and the track. Not in __init__ either: a node still compiling missed its stop
        # deadline. The runner starts a replay once ``kernels_warm`` is 1. A live camera's frame that
        # comes first is counted (skipped.warming) and dropped: waiting for the kernels would make it
        # and the frames queued behind it stale anyway. A lockstep frame waits (inside make_tracker).
        self.stats.gauges["kernels_warm"] = 0
        self._kernels_ready = threading.Event()
        self._warm_thread = threading.Thread(target=self._warm_up, name="tracker-warm-up", daemon=True)
        self._warm_thread.start()

    def _warm_up(self) -> None:
        t0 = time.perf_counter()
        try:
            warm_up()
        except Exception as err:  # noqa: BLE001 - a failed warm-up only costs the first frame the time
            self.stats.post_problem("warm_up", f"could not load the tracking kernels ahead of time: {err}")
        self.stats.post_gauge("warm_up_s", round(time.perf_counter() - t0, 2))
        self.stats.post_gauge("kernels_warm", 1)
        self._kernels_ready.set()

    def wait_until_warm(self, timeout_s: float) -> bool:
        """Whether the kernels are in within ``timeout_s`` (a live frame before that is "warming")."""
        return self._kernels_ready.wait(timeout_s)

    # ------------------------------------------------------------------ inputs
    def on_camera_info(self, msg: CameraInfo) -> None:
        try:
            cam = decode_camera_info(msg)
        except MessageError as err:
            self.stats.problem("camera_info", f"camera_info refused: {err}")
            return
        if self.calibration is not None:
            self._compare_camera_info(cam)
        elif self.camera is None:
            self._set_camera(cam, "camera_info")
            while self.waiting:
                self._handle(*self.waiting.popleft())
        elif cam != self.camera:
            self.stats.problem("camera_changed", "camera_info changed after tracking started; keeping the first")

    def _set_camera(self, cam: PinholeCamera, origin: str) -> None:
        self.camera = cam
        self.tracker = make_tracker(self.cfg, cam)
        self.get_logger().info(f"camera from {origin}: {describe_camera(cam)}")

    def _compare_camera_info(self, cam: PinholeCamera) -> None:
        """Override mode: say once when camera_info disagrees with the configured calibration."""
        if self._info_compared:
            return
        self._info_compared = True
        assert self.calibration is not None
        diffs = calibration_differences(cam, self.calibration)
        if diffs:
            self.stats.counters["camera_info_differs"] += 1
            self.get_logger().warning(
                f"camera_info on {self.resolve_topic_name(self.info_topic)} ({describe_camera(cam)}) differs "
                f"from the configured calibration by more than 1 % ({'; '.join(diffs)}): using the "
                "configured one (camera_info_override)")

    def _calibrated_camera(self, color: Image) -> bool:
        """Override mode, first frame: fit the configured camera to the image size. False (counted,
        logged once) when the images have another aspect ratio than the calibration."""
        assert self.calibration is not None
        try:
            cam = self.calibration.fitted(int(color.width), int(color.height))
        except DataError as err:
            self.stats.problem("camera_info", f"the configured calibration does not fit the images: {err}")
            return False
        self._set_camera(cam, "the configured calibration (camera_info_override)")
        return True

    def on_color(self, msg: Image, info: MessageInfo) -> None:
        if not self._take(msg, info):
            return
        if not self.rgbd:
            self._handle(msg, None)
            return
        pair = self.pairer.add_a(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self._handle(pair[1], pair[2])

    def _take(self, msg: Image, info: MessageInfo) -> bool:
        """Count the colour frames the camera published that never reached this callback (the
        reader's queue overflowed while the tracker was busy, or best-effort transport lost them:
        skipped.busy), and drop a live frame that came before the kernels (skipped.warming) or
        stale (skipped.stale). False: dropped."""
        seq = int(info.get("publication_sequence_number") or 0)
        if seq and self._last_color_seq and seq > self._last_color_seq + 1:
            self.stats.counters["skipped.busy"] += seq - self._last_color_seq - 1
        if seq:
            self._last_color_seq = seq  # a smaller one: the publisher restarted; count from it
        if self.max_age_ns and not self._kernels_ready.is_set():
            self.stats.counters["skipped.warming"] += 1
            self._processed(stamp_to_ns(msg.header.stamp), keyframe=False)
            return False
        sent = int(info.get("source_timestamp") or 0)
        if not self.max_age_ns or not sent:
            return True
        # The wait beyond the least wait seen: immune to a clock offset between camera and robot.
        wait = time.time_ns() - sent
        self._least_wait_ns = wait if self._least_wait_ns is None else min(self._least_wait_ns, wait)
        if wait - self._least_wait_ns <= self.max_age_ns:
            return True
        self.stats.counters["skipped.stale"] += 1
        self._processed(stamp_to_ns(msg.header.stamp), keyframe=False)
        return False

    def on_depth(self, msg: Image) -> None:
        pair = self.pairer.add_b(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self._handle(pair[1], pair[2])

    def _frame(self, color: Image, depth: Image | None) -> Frame | None:
        """Messages to a Frame, or None (counted, logged once) when they cannot be used."""
        assert self.camera is not None
        try:
            rgb = decode_rgb(color)
            depth_m = decode_depth(depth, self.depth_scale) if depth is not None else None
            return Frame(stamp_to_ns(color.header.stamp), rgb, depth_m, self.camera)
        except (MessageError, DataError) as err:
            self.stats.problem("bad_image", f"frame {stamp_to_ns(color.header.stamp)} refused: {err}")
            return None

    def _handle(self, color: Image, depth: Image | None) -> None:
        cpu0 = time.thread_time()  # this thread's CPU: the frame path alone, not the back-end's threads
        wall0 = time.perf_counter()
        if self.camera is None and self.calibration is not None and not self._calibrated_camera(color):
            self.stats.counters["frames_in"] += 1
            self._processed(stamp_to_ns(color.header.stamp), keyframe=False)
            return
        if self.camera is None:
            if len(self.waiting) == self.waiting.maxlen:
                self.stats.problem("no_camera_info", f"no valid camera_info on {self.info_topic} yet: "
                                                    "dropping the oldest waiting frame")
                self._processed(stamp_to_ns(self.waiting[0][0].header.stamp), keyframe=False)
            self.waiting.append((color, depth))
            return
        self.stats.counters["frames_in"] += 1
        stamp = stamp_to_ns(color.header.stamp)
        if not self._stamp_ok(stamp):
            self._processed(stamp, keyframe=False)
            return
        frame = self._frame(color, depth)
        if frame is None:
            self._processed(stamp, keyframe=False)
            return
        if depth is not None and not frame.valid_depth_mask().any():
            self.stats.problem("empty_depth", f"frame {stamp} has no valid depth")
        self.last_stamp_ns = stamp
        t0 = time.perf_counter()
        assert self.tracker is not None
        ba_before = self.tracker.ba_time_s
        result = self.tracker.track(frame)
        dt = time.perf_counter() - t0
        if not self.cfg.ba_threaded:
            # Inline local BA (lockstep replays) is back-end work: report the front end alone,
            # as a threaded BA would leave it, and the BA time beside it.
            ba_dt = self.tracker.ba_time_s - ba_before
            dt -= ba_dt
            self.stats.counters["ba_us_total"] += int(ba_dt * 1e6)
        self.stats.gauges["track_ms"] = round(dt * 1e3, 2)
        self.stats.gauges["keyframes_deferred"] = int(getattr(self.tracker, "keyframes_deferred", 0))
        self.stats.gauges["ba_waits"] = int(getattr(self.tracker, "ba_waits", 0))
        self.stats.counters["track_us_total"] += int(dt * 1e6)
        smap = self.tracker.map_stats() if result.keyframe is not None else None  # None: ORB-SLAM3 has no map
        if smap is not None:
            self.stats.gauges["map_keyframes"] = smap.keyframes
            self.stats.gauges["map_points"] = smap.points
            self.stats.gauges["map_keyframes_removed"] = smap.keyframes_removed
            if len(self.kf_stamps) > 2 * smap.keyframes + 64:  # BA refines only kept keyframes
                self.kf_stamps = {i: s for i, s in self.kf_stamps.items() if i in smap.keyframe_ids}
        refined = self.tracker.poll_refined_keyframes()
        corrected = self.tracker.poll_loop_corrected_keyframes()
        self._publish(frame, result, color, depth)
        self._publish_refined(refined, self.pub_refined, "refined_keyframe_poses")
        self._publish_refined(corrected, self.pub_loop, "loop_corrected_keyframe_poses")
        loops = self.tracker.poll_loop_corrections()
        moved = self.anchored.update(result, loops)
        if moved:
            self._path_stale |= moved  # re-expressed at the next path publication
            self._path_changed = True
        self._processed(stamp, keyframe=result.keyframe is not None)
        cost_ms = (time.thread_time() - cpu0) * 1e3
        self._frame_cpu_ms.add(cost_ms)
        self._frame_ms.add((time.perf_counter() - wall0) * 1e3)
        self.stats.counters["frame_cpu_us_total"] += int(cost_ms * 1e3)
        self.stats.gauges["frame_cpu_ms"] = round(cost_ms, 2)

    def _stamp_ok(self, stamp: int) -> bool:
        """Apply the stamp rules of the module docstring; False = drop the frame (counted)."""
        now = self.get_clock().now().nanoseconds
        if self.max_ahead_ns and now > 0 and stamp - now > self.max_ahead_ns:
            self.stats.problem("stamp_future", f"frame stamp {stamp} is {(stamp - now) * 1e-9:.0f} s ahead of the "
                                               "clock: dropped (sensor clock wrong?)")
            return False
        last = self.last_stamp_ns
        if last < 0 or stamp > last:
            return True
        if stamp == last:
            self.stats.problem("stamp_duplicate", f"frame stamp {stamp} came twice: the copy is dropped")
            return False
        if last - stamp <= self.jump_back_ns:
            self.stats.problem("stamp_order", f"frame stamp {stamp} is {(last - stamp) * 1e-6:.1f} ms before the "
                                              "previous frame: dropped (late, out of order)")
            return False
        self.stats.problem("time_jump_back", f"time jumped back {(last - stamp) * 1e-9:.1f} s (bag loop or clock "
                                             f"reset): tracking goes on from stamp {stamp}, relocalising in the map")
        return True

    # ------------------------------------------------------------------ outputs
    def _processed(self, stamp_ns: int, keyframe: bool) -> None:
        self.pub_processed.publish(make_header(stamp_ns, "keyframe" if keyframe else "frame"))

    def _publish(self, frame: Frame, result: TrackResult, color: Image, depth: Image | None) -> None:
        camera_frame = color.header.frame_id or self.camera_frame
        self.pub_state.publish(String(data=result.state.name))
        self.stats.counters[f"state.{result.state.name}"] += 1
        self.stats.gauges["segment"] = result.segment_id
        if result.T_wc is None:
            return
        pose = matrix_to_pose_stamped(result.T_wc, frame.stamp_ns, self.world_frame)
        self.pub_pose.publish(pose)
        self.pub_odom.publish(matrix_to_odometry(result.T_wc, frame.stamp_ns, self.world_frame, camera_frame))
        append_to_path(self.path, pose, self.path_max_len)
        self._path_changed = True
        self.stats.counters["poses_out"] += 1
        if result.keyframe is not None:
            self._publish_keyframe(frame, result, camera_frame, color, depth)

    def _publish_path(self) -> None:
        if self._path_changed:
            self._path_changed = False
            if self._path_stale:
                idx, T_wc = self.anchored.poses_following(self._path_stale)
                self._path_stale = set()
                for i, T in zip(idx.tolist(), T_wc):  # anchored path and memgs/path hold the same frames
                    old = self.path.poses[i]
                    self.path.poses[i] = matrix_to_pose_stamped(T, stamp_to_ns(old.header.stamp), self.world_frame)
            self.pub_path.publish(self.path)

    def _publish_keyframe(self, frame: Frame, result: TrackResult, camera_frame: str, color: Image,
                          depth: Image | None) -> None:
        kf = result.keyframe
        assert kf is not None and self.camera is not None
        stamp = frame.stamp_ns
        kps = np.zeros(len(kf.keypoints_uv), dtype=KEYPOINT_DTYPE)
        kps["u"], kps["v"] = kf.keypoints_uv[:, 0], kf.keypoints_uv[:, 1]
        kps["depth"], kps["active"] = kf.keypoint_depth, kf.keypoint_active
        # The image messages go out as they came in (each consumer decodes and undistorts them once
        # and knows which pixels of the undistorted image hold real content); a depth message paired
        # from another stamp takes the colour's, which names the keyframe's bundle.
        self.pub_kf_info.publish(camera_to_camera_info(self.camera, stamp, camera_frame))
        self.pub_kf_color.publish(color)
        if depth is not None:
            depth.header.stamp = color.header.stamp
            self.pub_kf_depth.publish(depth)
        self.pub_kf_kps.publish(structured_to_pointcloud2(kps, stamp, camera_frame))
        self.pub_kf_pose.publish(matrix_to_pose_stamped(kf.T_wc, stamp, self.world_frame))
        self.kf_stamps[kf.keyframe_id] = stamp
        self.stats.counters["keyframes"] += 1

    def _publish_refined(self, refined: list[tuple[int, np.ndarray]], pub: Publisher, counter: str) -> None:
        poses = [matrix_to_pose_stamped(T, self.kf_stamps[i], self.world_frame)
                 for i, T in refined if i in self.kf_stamps]
        if poses:
            self.kf_path.poses = poses
            pub.publish(self.kf_path)
            self.stats.counters[counter] += len(poses)

    def on_shutdown(self) -> None:
        if self.tracker is not None:
            self.tracker.close()

    def destroy_node(self) -> None:
        # The warm-up starts by reading ORB's tests off OpenCV (~0.5 s, in OpenCV's native code): a
        # process that exits under it aborts ("terminate called without an active exception").
        # Bounded: a first compile of the kernels after that can take ~10 s.
        self._warm_thread.join(timeout=_WARM_UP_JOIN_S)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(TrackerNode, "tracker", args)


if __name__ == "__main__":
    sys.exit(main())
