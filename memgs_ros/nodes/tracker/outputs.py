"""Everything the tracker node publishes, made from its results (each topic: docs/design.md's table):
``TrackerOutbox``, and ``CorrectedPath`` for ``memgs/path``."""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header, String

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frames import FrameConvention
from memgs_ros.core.tracking import TrackResult
from memgs_ros.core.tracking.anchored_path import AnchoredPath, PathChanges
from memgs_ros.core.tracking.telemetry import state_stats
from memgs_ros.nodes.tracker.stats import TrackerStats
from memgs_ros.nodes.tracker.tf import TfOutbox
from memgs_ros.ros import qos
from memgs_ros.ros.codecs import (
    append_to_path,
    matrix_to_pose_stamped,
    pose_to_odometry,
    set_header,
    set_tracked_odometry,
    stamp_to_ns,
)
from memgs_ros.ros.diagnostics import RollingMedian
from memgs_ros.ros.keyframe_bundle import KeyframeOutbox

__all__ = ["CorrectedPath", "TrackerOutbox"]

class CorrectedPath:
    """``memgs/path``: every published pose, moved with the keyframe it was tracked against when a
    loop closure corrects that keyframe (:class:`AnchoredPath`, its changes :class:`PathChanges`).
    The message and the anchored poses hold the same frames, index for index; ``max_len`` 0 keeps all."""

    def __init__(self, world_frame: str, max_len: int) -> None:
        self.world_frame, self.max_len = world_frame, max_len
        self.msg = Path()
        self.msg.header.frame_id = world_frame
        self.changes = PathChanges(AnchoredPath(max_len))

    def add(self, result: TrackResult, pose: PoseStamped | None, loops: Sequence[Mapping[int, np.ndarray]],
            heirs: Mapping[int, int] | None = None) -> None:
        """A tracked frame (``pose``: its published pose, None when lost) after the loop
        corrections committed while it was tracked; ``heirs``: {culled keyframe: heir} since the last."""
        if pose is not None:
            append_to_path(self.msg, pose, self.max_len)
        self.changes.update(result, loops, heirs)

    def take_message(self) -> Path | None:
        """The path to publish, corrections applied, or None when nothing changed since."""
        moved = self.changes.take()
        if moved is None:
            return None
        for i, T in zip(moved[0].tolist(), moved[1]):
            old = self.msg.poses[i]
            self.msg.poses[i] = matrix_to_pose_stamped(T, stamp_to_ns(old.header.stamp), self.world_frame)
        return self.msg


class TrackerOutbox:
    """The tracker node's publishers, fed one frame's result at a time; what it published is
    counted in ``stats`` (``state.<STATE>``, ``poses_out``, ``keyframes``, the refined and
    loop-corrected keyframe poses)."""

    def __init__(self, node: Node, params: Any, stats: TrackerStats) -> None:
        """``params``: the node's TrackerParams (frames, mount, path length and rate)."""
        world_frame, path_max_len = params.world_frame, params.path_max_len
        self.world_frame, self.camera_frame, self.stats = world_frame, params.camera_frame, stats
        self.map_frame, self.base_frame = params.map_frame, params.base_frame
        self.tf = TfOutbox(node, params) if params.publish_tf else None  # it settles the camera's mount
        self._frames: FrameConvention = params.frame_convention()  # without TF: the parameters' mount
        self._frame_cpu_ms, self._frame_ms = RollingMedian(), RollingMedian()
        stats.compute(TrackerStats.frame_cpu_ms_median, self._frame_cpu_ms)  # message in to pose out
        stats.compute(TrackerStats.frame_ms_median, self._frame_ms)  # wall: an acknowledged frame's share
        rel = qos.reliable(10)
        # The camera in world_frame. Keep last 100: a reliable writer drops what its history no longer holds, and
        # a replay tracks ~100 frames a second; at 10 a runner stalled for 0.1 s lost a pose of its trajectory
        self.pose = node.create_publisher(PoseStamped, "memgs/pose", qos.reliable(100))
        # Tracked poses only (state OK), with the covariance: what a flight controller fuses. The body
        # (base_frame) in map_frame, z up (REP-103/105)
        self.odom = node.create_publisher(Odometry, "memgs/odom", rel)
        self.pose_cov = node.create_publisher(PoseWithCovarianceStamped, "memgs/pose_with_covariance", rel)
        self._last_tracked: tuple[int, np.ndarray] | None = None  # (stamp, body in map) of the last OK pose
        self.path_pub = node.create_publisher(Path, "memgs/path", rel)
        self.state = node.create_publisher(String, "memgs/tracking_state", rel)
        self.processed_pub = node.create_publisher(Header, "memgs/tracker/processed", qos.reliable(100))
        self.keyframes = KeyframeOutbox(node, world_frame, params.depth_scale)
        self.path = CorrectedPath(world_frame, path_max_len)
        node.create_timer(1.0 / params.path_rate_hz, self.publish_path)
        # Filled in place and published at once (publish serializes before it returns): the
        # per-frame messages nothing keeps. The poses are new each frame: the path keeps them.
        self._state, self._odom, self._processed = String(), Odometry(), Header()

    def processed(self, stamp_ns: int, keyframe: bool = False, parts: tuple[str, ...] = ()) -> None:
        """The answer for every frame handled, tracked or refused (a player awaiting acknowledgements
        waits on it): "keyframe" or "frame", then "+<part>" for each pose message sent with it."""
        self.processed_pub.publish(set_header(self._processed, stamp_ns,
                                              "+".join(("keyframe" if keyframe else "frame", *parts))))

    def frame(self, result: TrackResult, camera: PinholeCamera, color: Image, depth: Image | None,
              refined: list[tuple[int, np.ndarray]], corrected: list[tuple[int, np.ndarray]],
              loops: Sequence[Mapping[int, np.ndarray]], culled: Sequence[tuple[int, int, np.ndarray]] = ()) -> None:
        """A tracked frame: its state, pose and odometry (when not lost), its keyframe messages,
        the keyframe poses that moved meanwhile (``refined`` by local BA, ``corrected`` by a loop
        closure; ``loops``: the closures' world-frame corrections), the keyframes culling removed
        (``culled``: (id, heir id, T_wc)), then its answer."""
        stats, stamp = self.stats, result.stamp_ns
        camera_frame = color.header.frame_id or self.camera_frame
        self._state.data = name = result.state.name
        self.state.publish(self._state)
        if state_stats(stats, name, result.segment_id):
            stats.publish()  # lost, or back: /diagnostics hears it now, not at the next second
        pose = None
        if self.tf is not None and self.tf.settle_mount(camera_frame):
            self.tf.set_camera_frame(camera_frame)
        if result.T_wc is not None:
            pose = matrix_to_pose_stamped(result.T_wc, stamp, self.world_frame)
            self.pose.publish(pose)
            stats.poses_out += 1
            if not self.mount_settled:
                stats.odometry_withheld += 1  # the body's pose waits for the camera's mount
            elif result.pose_cov is not None:  # tracked (not coasted, not a start without a pose fit), and read
                self._tracked_odometry(result.T_wc, result.pose_cov, stamp)
            else:
                self._last_tracked = None
            if self.mount_settled and self.tf is not None and self.tf.available and name == "OK":
                # False only with an odom_frame and no odom -> base_link near the frame's stamp
                if self.tf.tracked(result.T_wc, stamp):
                    stats.tf_out += 1
                else:
                    stats.tf_no_odom += 1
            if result.keyframe is not None:
                self.keyframes.publish(result, camera, camera_frame, color, depth)
                stats.keyframes += 1
        parts = self._moved_keyframes(stamp, refined, corrected, culled)
        self.path.add(result, pose, loops, {k: heir for k, heir, _ in culled})
        self.processed(stamp, keyframe=result.keyframe is not None, parts=tuple(parts))

    def _moved_keyframes(self, stamp: int, refined: list[tuple[int, np.ndarray]],
                         corrected: list[tuple[int, np.ndarray]],
                         culled: Sequence[tuple[int, int, np.ndarray]]) -> list[str]:
        """The keyframe poses that moved (``refined``, ``corrected``) or went (``culled``), sent with
        the frame stamped ``stamp`` and counted; returns the parts its answer names."""
        kf, stats, parts = self.keyframes, self.stats, []
        if refined and (n := kf.publish_poses(refined, kf.refined, stamp)):
            stats.refined_keyframe_poses += n
            parts.append("refined")
        if corrected and (n := kf.publish_poses(corrected, kf.loop, stamp)):
            stats.loop_corrected_keyframe_poses += n
            parts.append("loop")
        if culled and (n := kf.publish_culled(list(culled), stamp)):
            stats.culled_keyframes += n
            parts.append("culled")
        return parts

    def end_flight(self, result: TrackResult, camera: PinholeCamera, color: Image, depth: Image | None,
                   refined: list[tuple[int, np.ndarray]], culled: Sequence[tuple[int, int, np.ndarray]]) -> None:
        """The flight's last view made a keyframe after its frame went out (``Tracker.end_flight``):
        its keyframe messages, and the keyframe poses its insertion moved or culled."""
        self.keyframes.publish(result, camera, color.header.frame_id or self.camera_frame, color, depth)
        self.stats.keyframes += 1
        self._moved_keyframes(result.stamp_ns, refined, [], culled)

    @property
    def frames(self) -> FrameConvention:
        return self._frames if self.tf is None else self.tf.frames

    @property
    def mount_settled(self) -> bool:
        return self.tf is None or self.tf.mount_wait.settled

    def frame_cost(self, cpu0: float, wall0: float) -> None:
        """The frame path's cost since ``cpu0`` (this thread's CPU: the frame path alone) and ``wall0``
        (perf_counter), into the stats."""
        cost_ms = (time.thread_time() - cpu0) * 1e3
        self._frame_cpu_ms.add(cost_ms)
        self._frame_ms.add((time.perf_counter() - wall0) * 1e3)
        self.stats.frame_cpu_us_total += int(cost_ms * 1e3)
        self.stats.frame_cpu_ms = round(cost_ms, 2)

    def odometry_wanted(self) -> bool:
        """Whether anything subscribes to ``memgs/odom`` or ``memgs/pose_with_covariance``: without a
        reader the tracker skips the covariance and no odometry is built (a live subscriber, a
        recorder, a flight controller's bridge each count)."""
        return self.odom.get_subscription_count() > 0 or self.pose_cov.get_subscription_count() > 0

    def _tracked_odometry(self, T_wc: np.ndarray, pose_cov: np.ndarray, stamp: int) -> None:
        """``memgs/odom`` and ``memgs/pose_with_covariance``: the body in map_frame, the covariance
        carried over from the camera's, the twist from the last tracked pose (within 0.5 s)."""
        T_mb = self.frames.base_in_map(T_wc)
        prev = self._last_tracked
        dt_s = (stamp - prev[0]) * 1e-9 if prev is not None else 0.0
        body = matrix_to_pose_stamped(T_mb, stamp, self.map_frame)
        odom = pose_to_odometry(body, self.base_frame, self._odom)
        set_tracked_odometry(odom, self.frames.covariance_in_map(pose_cov, T_wc), T_mb,
                             prev[1] if prev is not None and 0 < dt_s <= 0.5 else None, dt_s)
        self.odom.publish(odom)
        cov = PoseWithCovarianceStamped(header=body.header)
        cov.pose.pose, cov.pose.covariance = body.pose, odom.pose.covariance
        self.pose_cov.publish(cov)
        self._last_tracked = (stamp, T_mb)
        self.stats.odometry_out += 1

    def publish_path(self) -> None:
        msg = self.path.take_message()
        if msg is not None:
            self.path_pub.publish(msg)
