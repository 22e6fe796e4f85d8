"""bag_player: replay a frame source (TUM folder, ROS 1/2 bag, synthetic spec) as camera topics.

Publishes, per frame and with one shared header stamp:
``color/image_raw`` (rgb8), ``depth/image_raw`` (32FC1 metres or 16UC1 scaled units),
``color/camera_info``, and ``groundtruth/pose`` (PoseStamped, camera in world) when the
source has ground truth. At the end it latches ``memgs/player/done`` (std_msgs/Bool:
True when every frame was played, False when the source failed) and exits, unless
``loop`` is set.

Two pacings:
- real time: frame i goes out at start + (stamp_i - stamp_0) / rate (never skipping
  frames; a slow machine just plays late);
- lockstep: frame i+1 goes out when a std_msgs/Header with frame i's stamp arrives on
  ``ack_topic`` (or after ``ack_timeout_s``, with a warning), so the pipeline sees every
  frame however slow it is. ``rate`` is ignored.

When looping, each pass is shifted by the length of the sequence plus one frame period,
so stamps downstream never go backwards.

camera_info is the source's own (a bag's CameraInfo, a TUM folder's camera.json or
freiburg1/2/3 name); the ``camera.*`` calibration parameters give the camera of a TUM folder
that names none. Replacing a source's camera_info is the tracker's job (``camera_info_override``),
so it happens once for every source, live cameras included.

    python -m memgs_ros.nodes.bag_player --ros-args -p source:=synthetic:w=64,h=48,n=20 -p lockstep:=true
"""
from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Bool, Header

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.errors import ConfigError, MemgsError
from memgs_ros.io.skips import SkipLog
from memgs_ros.nodes.params import NODE_CONFIGS, BagPlayerParams
from memgs_ros.ros import codecs, qos
from memgs_ros.ros.camera_params import declare_calibration
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats, RollingMedian
from memgs_ros.ros.node_main import started_by_runner

# The tick sleeps until the next frame is due (real time; at least MIN_TICK_S) or, in lockstep,
# where frames go out from the ack callback, only watches for timeouts. A fixed 5 ms tick cost an
# idle player 11 % of a core, 14 s of CPU over a 156 s replay on 2 cores.
MIN_TICK_S = 0.001
MAX_TICK_S = 0.05
SETTLE_S = 0.5  # subscriber counts must be steady this long before the first frame goes out
LINGER_S = 0.5  # keep the latched "done" publisher alive so matched readers receive it
PROGRESS_EVERY_S = 5.0
DEFAULT_PERIOD_NS = 33_333_333  # loop gap for a one-frame source (30 Hz)


CONFIGS = NODE_CONFIGS["bag_player"]


class BagPlayer(Node):
    """Replays ``frames`` (or ``open_source(source)`` when None); ``finished`` completes at the end."""

    def __init__(self, frames: Iterable[Frame] | None = None, **node_kwargs: object) -> None:
        super().__init__("bag_player", **node_kwargs)
        self.cfg = declare_config(self, BagPlayerParams, "")
        folder_camera = declare_calibration(self)  # for a TUM folder that names no camera
        if frames is None:
            if not self.cfg.source:
                raise ConfigError("parameter 'source' is empty: give a TUM folder, bag or 'synthetic:...' spec")
            from memgs_ros.io.sources import open_source  # heavy readers only when replaying files

            source = open_source(self.cfg.source, default_camera=folder_camera, strict=self.cfg.strict)
            _ = source.camera  # a TUM folder with no camera fails here, before the first frame
            frames = source
        if self.cfg.preload_mb > 0:
            t0 = time.monotonic()
            frames = Preloaded(frames, self.cfg.preload_mb, 0 if self.cfg.loop else self.cfg.max_frames)
            self.get_logger().info(f"preloaded {len(frames)} frames ({frames.nbytes / 1e6:.0f} MB) "
                                   f"in {time.monotonic() - t0:.1f} s")
        self._source = frames
        # Frames skipped here (stamp going backwards, camera changed); the source counts its own.
        self._skips = SkipLog("bag_player", self.cfg.strict)
        self._first_camera: PinholeCamera | None = None
        self.finished: Future = Future()
        self.ok = True

        self._pub_color = self.create_publisher(Image, "color/image_raw", qos.reliable(5))
        self._pub_depth = self.create_publisher(Image, "depth/image_raw", qos.reliable(5))
        self._pub_info = self.create_publisher(CameraInfo, "color/camera_info", qos.reliable(5))
        self._pub_gt = self.create_publisher(PoseStamped, "groundtruth/pose", qos.reliable(10))
        self._pub_done = self.create_publisher(Bool, "memgs/player/done", qos.latched())
        self.stats = NodeStats(self, "player")
        # Frames this replay will publish (0 = unknown: a looping replay or a source of unknown length),
        # so a watcher can show a total and an ETA.
        self.stats.gauges["frames_total"] = 0 if self.cfg.loop else _frames_total(frames, self.cfg.max_frames)
        self._ack_sub = (
            self.create_subscription(Header, self.cfg.ack_topic, self._on_ack, qos.reliable(10))
            if self.cfg.lockstep
            else None
        )

        self._it: Iterator[Frame] = iter(self._source)
        self._loop_offset_ns = 0
        self._first_src_ns: int | None = None  # first / last source stamp of the current pass
        self._last_src_ns: int | None = None
        self._period_ns = DEFAULT_PERIOD_NS
        self._next: Frame | None = None
        self._next_stamp_ns = 0
        self._published = 0
        self._last_sent_ns = 0
        self._awaiting_ns: int | None = None  # lockstep: stamp of the frame we wait an ack for
        self._sent_at = 0.0
        self._ack_wait_ms = RollingMedian()  # lockstep: publication to acknowledgement, per frame
        self.stats.computed["ack_wait_ms_median"] = self._ack_wait_ms
        self._ack_timeouts = 0
        self._created_at = time.monotonic()
        self._frame_pubs = (self._pub_color, self._pub_depth, self._pub_info, self._pub_gt)
        self._wait_for = tuple(n.strip() for n in self.cfg.wait_for_readers.split(",") if n.strip())
        self._match_counts: tuple[int, ...] = ()
        self._steady_since = self._created_at
        self._t0: float | None = None  # wall time and stamp of the first frame (real-time pacing)
        self._stamp0_ns = 0
        self._last_progress = 0.0
        self._finish_at: float | None = None
        self._timer = self.create_timer(MAX_TICK_S, self._tick)
        try:
            count = f"{len(frames)} frames, "  # type: ignore[arg-type]
        except TypeError:  # a plain iterable has no length
            count = ""
        self.get_logger().info(
            f"replaying '{self.cfg.source or type(frames).__name__}' ({count}"
            f"{'lockstep' if self.cfg.lockstep else f'real time x{self.cfg.rate:g}'}"
            f"{', looping' if self.cfg.loop else ''})"
        )

    @property
    def frames_published(self) -> int:
        return self._published

    @property
    def ack_timeouts(self) -> int:
        """Lockstep frames after which the player went on without an ack."""
        return self._ack_timeouts

    # ------------------------------------------------------------------ pacing

    def _tick(self) -> None:
        now = time.monotonic()
        if self._finish_at is not None:
            if now >= self._finish_at and not self.finished.done():
                self.finished.set_result(self.ok)
            return
        if self._t0 is None:
            if not self._ready_to_start(now):
                return
            self._t0 = now
            self._last_progress = now
            self._prefetch()
            if self._next is None:
                self.get_logger().warning("the source has no frames")
                self._finish(ok=self.ok)
                return
            self._stamp0_ns = self._next_stamp_ns
        if self.cfg.lockstep:
            if self._awaiting_ns is None:
                self._publish_next()
            elif now - self._sent_at > self.cfg.ack_timeout_s:
                self._ack_timeouts += 1
                self.get_logger().warning(
                    f"no ack for stamp {self._awaiting_ns} within {self.cfg.ack_timeout_s:g} s "
                    f"on '{self.cfg.ack_topic}' ({self._ack_timeouts} timeouts so far); going on"
                )
                self._awaiting_ns = None
                self._publish_next()
        else:
            due = self._due()
            if now >= due:
                # How late the frame goes out: a reader too slow for the source shows up here.
                self.stats.gauges["late_ms"] = round((now - due) * 1e3, 1)
                self._publish_next()
            if self._next is not None and self._finish_at is None:
                self._sleep_until(self._due())
        if now - self._last_progress >= PROGRESS_EVERY_S:
            self._last_progress = now
            self._log_progress(now)

    def _due(self) -> float:
        """Monotonic time the next frame goes out in real-time replay."""
        assert self._t0 is not None
        return self._t0 + (self._next_stamp_ns - self._stamp0_ns) * 1e-9 / self.cfg.rate

    def _sleep_until(self, t: float) -> None:
        """Make the next tick come at ``t`` (within [MIN_TICK_S, MAX_TICK_S] from now)."""
        period_ns = int(min(max(t - time.monotonic(), MIN_TICK_S), MAX_TICK_S) * 1e9)
        self._timer.timer_period_ns = period_ns
        self._timer.reset()  # count the new period from now, not from the last call

    def _ready_to_start(self, now: float) -> bool:
        """Start once a color subscriber (and, in lockstep, an ack publisher) has matched, every
        node named in wait_for_readers has its readers matched, and the match counts of all topics
        have been steady for SETTLE_S (so a subscriber's depth and info readers, discovered a moment
        after its color reader, get the first frame too), or when start_delay_s runs out.

        Naming the tracker matters when other nodes read the frames too (a Rerun bridge): their
        readers can match first, and a lockstep frame the tracker never got waits out the ack
        timeout and is lost."""
        counts = tuple(p.get_subscription_count() for p in self._frame_pubs)
        has_reader = counts[0] > 0
        has_acker = self._ack_sub is None or self._ack_sub.get_publisher_count() > 0
        unmatched = self._unmatched_readers()
        if counts != self._match_counts:
            self._match_counts, self._steady_since = counts, now
        if (has_reader and has_acker and not unmatched
                and now - self._steady_since >= min(SETTLE_S, self.cfg.start_delay_s)):
            return True
        if now - self._created_at >= self.cfg.start_delay_s:
            missing = [] if has_reader else ["a color subscriber"]
            missing += [] if has_acker else [f"a publisher on '{self.cfg.ack_topic}'"]
            missing += unmatched
            if missing:
                self.get_logger().warning(f"starting without {'; '.join(missing)} after {self.cfg.start_delay_s:g} s")
            return True
        return False

    def _unmatched_readers(self) -> list[str]:
        """What still keeps the first frame from the nodes in wait_for_readers: a node whose color
        or camera_info reader the graph does not show yet, or a reader the graph shows that this
        publisher has not matched yet."""
        if not self._wait_for:
            return []
        missing = []
        for pub in (self._pub_color, self._pub_info):
            readers = self.get_subscriptions_info_by_topic(pub.topic_name)
            names = {r.node_name for r in readers}
            missing += [f"{n}'s reader on '{pub.topic_name}'" for n in self._wait_for if n not in names]
            if pub.get_subscription_count() < len(readers):
                missing.append(f"a match for all {len(readers)} readers on '{pub.topic_name}'")
        return missing

    def _on_ack(self, msg: Header) -> None:
        stamp_ns = codecs.stamp_to_ns(msg.stamp)
        if self._awaiting_ns is None or stamp_ns != self._awaiting_ns:
            self.get_logger().debug(f"ignoring ack for stamp {stamp_ns} (waiting for {self._awaiting_ns})")
            return
        self._awaiting_ns = None
        self._ack_wait_ms.add((time.monotonic() - self._sent_at) * 1e3)
        if self._finish_at is None:
            self._publish_next()

    # ------------------------------------------------------------------ frames

    def _prefetch(self) -> None:
        """Load the next good frame into self._next (None at the end), handling loops and
        max_frames; bad frames are skipped and counted (``strict``: the replay fails instead)."""
        self._next = None
        if self.cfg.max_frames and self._published >= self.cfg.max_frames:
            return
        while True:
            try:
                frame = next(self._it, None)
                if frame is None and self.cfg.loop and self._first_src_ns is not None:
                    span = (self._last_src_ns or self._first_src_ns) - self._first_src_ns
                    self._loop_offset_ns += span + self._period_ns
                    self._first_src_ns = self._last_src_ns = None
                    self._it = iter(self._source)
                    frame = next(self._it, None)
                problem = None if frame is None else self._bad_frame(frame)
                if problem is not None:
                    self._skips.skip(*problem)
            except MemgsError as err:
                self.get_logger().error(f"cannot read the next frame: {err}")
                self.ok = False
                return
            finally:
                self._count_skips()
            if frame is None:
                return
            if problem is None:
                break
        if self._first_src_ns is None:
            self._first_src_ns = frame.stamp_ns
        elif self._last_src_ns is not None and frame.stamp_ns > self._last_src_ns and self._published < 2:
            self._period_ns = frame.stamp_ns - self._last_src_ns
        self._last_src_ns = frame.stamp_ns
        self._next = frame
        self._next_stamp_ns = frame.stamp_ns + self._loop_offset_ns

    def _bad_frame(self, frame: Frame) -> tuple[str, str] | None:
        """(kind, detail) when ``frame`` must be skipped: its stamp does not follow the last one of
        this pass, or its camera is not the first frame's (the nodes keep one calibration)."""
        if self._last_src_ns is not None and frame.stamp_ns <= self._last_src_ns:
            return "stamp_backwards", f"{frame.stamp_ns} after {self._last_src_ns}"
        if self._first_camera is None:
            self._first_camera = frame.camera
        elif frame.camera != self._first_camera:
            return "camera_changed", f"{frame.camera} (first frame: {self._first_camera})"
        return None

    def _count_skips(self) -> None:
        """Frames skipped so far (by the source and here) into the stats, by kind."""
        for log in (getattr(self._source, "skipped", {}), self._skips.counts):
            for kind, n in log.items():
                self.stats.counters[f"skipped.{kind}"] = n

    def _publish_next(self) -> None:
        frame, stamp_ns = self._next, self._next_stamp_ns
        if frame is None:
            self._finish(ok=self.ok)
            return
        fid = self.cfg.frame_id
        self._pub_color.publish(codecs.numpy_to_image(frame.rgb, "rgb8", stamp_ns, fid))
        if frame.depth_m is not None:
            self._pub_depth.publish(
                codecs.depth_to_image(frame.depth_m, self.cfg.depth_encoding, stamp_ns, fid, self.cfg.depth_scale)
            )
        self._pub_info.publish(codecs.camera_to_camera_info(frame.camera, stamp_ns, fid))
        if frame.T_wc_gt is not None:
            self._pub_gt.publish(codecs.matrix_to_pose_stamped(frame.T_wc_gt, stamp_ns, self.cfg.world_frame_id))
        self._published += 1
        self.stats.counters["frames_published"] += 1
        self.stats.gauges["ack_timeouts"] = self._ack_timeouts
        self._last_sent_ns = stamp_ns
        self._sent_at = time.monotonic()
        if self.cfg.lockstep:
            self._awaiting_ns = stamp_ns
        self._prefetch()
        if self._next is None and not self.cfg.lockstep:
            self._finish(ok=self.ok)

    def _finish(self, ok: bool) -> None:
        if self._finish_at is not None:
            return
        now = time.monotonic()
        self.ok = ok
        self._count_skips()
        self.stats.publish()  # the final counts before "done": the runner's summary reads them
        self._pub_done.publish(Bool(data=ok))
        self._log_progress(now, final=True)
        self._finish_at = now + LINGER_S

    def _log_progress(self, now: float, final: bool = False) -> None:
        elapsed = max(now - (self._t0 or now), 1e-9)
        self.get_logger().info(
            f"{'done: ' if final else ''}{self._published} frames in {elapsed:.1f} s "
            f"({self._published / elapsed:.1f} frames/s), last stamp {self._last_sent_ns * 1e-9:.3f} s, "
            f"ack timeouts {self._ack_timeouts}"
        )


class Preloaded:
    """The frames of ``source`` decoded into memory up front, so that a replay only publishes (a
    camera's cost, not a file decoder's). Iterates like the source: a read error met while
    preloading is raised where it happened, after the frames read before it.

    Raises ConfigError when the frames need more than ``budget_mb``; ``max_frames`` > 0 stops
    reading there.
    """

    def __init__(self, source: Iterable[Frame], budget_mb: int, max_frames: int = 0) -> None:
        self._source = source
        self.frames: list[Frame] = []
        self.nbytes = 0
        self.error: MemgsError | None = None
        try:
            for frame in source:
                self.nbytes += frame.rgb.nbytes + (0 if frame.depth_m is None else frame.depth_m.nbytes)
                if self.nbytes > budget_mb * 1e6:
                    raise ConfigError(f"the source does not fit preload_mb={budget_mb} MB ({len(self.frames)} "
                                      "frames did): raise preload_mb, or set it to 0 to decode frames as they go out")
                self.frames.append(frame)
                if max_frames and len(self.frames) >= max_frames:
                    break
        except ConfigError:
            raise
        except MemgsError as err:  # a strict source's bad frame: the replay fails there, as without preloading
            self.error = err

    @property
    def skipped(self) -> dict[str, int]:
        """The source's own count of skipped bad frames, by kind."""
        return dict(getattr(self._source, "skipped", {}))

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        yield from self.frames
        if self.error is not None:
            raise self.error


def _frames_total(frames: Iterable[Frame], max_frames: int) -> int:
    """len(frames) capped at ``max_frames`` (0 = no cap); 0 when the source has no length."""
    try:
        n = len(frames)  # type: ignore[arg-type]
    except TypeError:
        return max_frames
    return min(n, max_frames) if max_frames else n


def main(args: list[str] | None = None) -> int:
    if not started_by_runner():
        return 0
    rclpy.init(args=args)
    node: BagPlayer | None = None
    code = 0
    try:
        node = BagPlayer()
        rclpy.spin_until_future_complete(node, node.finished)
        code = 0 if node.finished.done() and node.finished.result() else 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C / SIGTERM: a clean stop (exit 0); the runner tells a whole source by "done"
    except MemgsError as err:
        rclpy.logging.get_logger("bag_player").fatal(str(err))
        code = 2
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
