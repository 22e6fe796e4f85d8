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

The frame order, loops and skips are :class:`memgs_ros.io.replay.ReplayFeed`'s; the start rule
and the acknowledgement awaited are the replay service's (:mod:`memgs_ros.core.runtime.replay`); the messages
:class:`memgs_ros.nodes.bag_player.outputs.FrameOutbox`'s.

    python -m memgs_ros.nodes.bag_player.node --ros-args -p source:=synthetic:w=64,h=48,n=20 -p pacing:=lockstep
"""
from __future__ import annotations

import sys
import time
from collections.abc import Iterable
from typing import Any

from rclpy.node import Node
from rclpy.task import Future
from std_msgs.msg import Bool, Header

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.runtime.replay import AckWait, RealTimeClock, StartGate
from memgs_ros.core.runtime.telemetry_fields import PlayerFields
from memgs_ros.errors import MemgsError
from memgs_ros.io.replay import ReplayFeed, frames_total, open_frames, replay_frames
from memgs_ros.nodes.bag_player.outputs import FrameOutbox
from memgs_ros.nodes.params import NODE_CONFIGS, BagPlayerParams
from memgs_ros.ros import codecs, qos
from memgs_ros.ros.camera_params import declare_calibration
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats, RollingMedian
from memgs_ros.ros.node_main import run_node

__all__ = ["LINGER_S", "BagPlayer", "main"]

# The tick sleeps until the next frame is due (real time; at least MIN_TICK_S) or, in lockstep,
# where frames go out from the ack callback, only watches for timeouts. A fixed 5 ms tick cost an
# idle player 11 % of a core, 14 s of CPU over a 156 s replay on 2 cores.
MIN_TICK_S = 0.001
MAX_TICK_S = 0.05
SETTLE_S = 0.5  # subscriber counts must be steady this long before the first frame goes out
LINGER_S = 0.5  # keep the latched "done" publisher alive so matched readers receive it
PROGRESS_EVERY_S = 5.0


CONFIGS = NODE_CONFIGS["bag_player"]


class PlayerStats(NodeStats, PlayerFields):
    stats_name = "player"


class BagPlayer(Node):
    """Replays ``frames`` (or ``open_source(source)`` when None); ``finished`` completes at the end
    (True: every frame was played)."""

    def __init__(self, frames: Iterable[Frame] | None = None, **node_kwargs: Any) -> None:  # rclpy Node kwargs
        super().__init__("bag_player", **node_kwargs)
        self.cfg = cfg = declare_config(self, BagPlayerParams, "")
        frames = self._open(declare_calibration(self), frames)  # the camera of a TUM folder that names none
        self.feed = ReplayFeed(frames, cfg.loop, cfg.max_frames, cfg.strict)
        self.finished: Future = Future()
        self.ok = True
        self.outbox = FrameOutbox(self, cfg.frame_id, cfg.world_frame_id, cfg.depth_encoding)
        self._pub_done = self.create_publisher(Bool, "memgs/player/done", qos.latched())
        self.stats = PlayerStats(self)
        # Frames this replay will publish (0 = unknown: looping, or a source of unknown length): a watcher's ETA.
        self.stats.frames_total = 0 if cfg.loop else frames_total(frames, cfg.max_frames)
        self._ack_sub = (self.create_subscription(Header, cfg.ack_topic, self._on_ack, qos.reliable(10))
                         if cfg.replay.acknowledged else None)
        self.acks = AckWait(cfg.ack_timeout_s)
        self._ack_wait_ms = RollingMedian()
        self.stats.compute(PlayerStats.ack_wait_ms_median, self._ack_wait_ms)  # acknowledged pacing: sent to acked
        self._gate = StartGate(SETTLE_S, cfg.start_delay_s, time.monotonic(), f"a publisher on '{cfg.ack_topic}'")
        self._wait_for = tuple(n.strip() for n in cfg.wait_for_readers.split(",") if n.strip())
        self._next: tuple[Frame, int] | None = None  # the next frame and its replay stamp
        self._last_sent_ns = 0
        self.clock = RealTimeClock(cfg.rate)  # also marks the start when acknowledged (clock.t0)
        self._last_progress = 0.0
        self._finish_at: float | None = None
        self._timer = self.create_timer(MAX_TICK_S, self._tick)
        count = f"{len(frames)} frames, " if hasattr(frames, "__len__") else ""  # type: ignore[arg-type]
        self.get_logger().info(f"replaying '{cfg.source or type(frames).__name__}' ({count}"
                               f"{cfg.pacing if cfg.replay.acknowledged else f'real time x{cfg.rate:g}'}"
                               f"{', looping' if cfg.loop else ''})")

    def _open(self, folder_camera: PinholeCamera | None, frames: Iterable[Frame] | None) -> Iterable[Frame]:
        """``frames``, or the ``source`` parameter opened; preloaded and repeated (``replay_frames``)."""
        c = self.cfg
        frames, note = replay_frames(open_frames(c.source, folder_camera, c.strict, c.bag_topics) if frames is None
                                     else frames, c.preload_mb, c.max_frames, c.loop, c.repeat, c.repeat_forward)
        if note:
            self.get_logger().info(note)
        return frames

    # ------------------------------------------------------------------ pacing
    def _tick(self) -> None:
        now = time.monotonic()
        if self._finish_at is not None:
            if now >= self._finish_at and not self.finished.done():
                self.finished.set_result(self.ok)
            return
        if self.clock.t0 is None and not self._start(now):
            return
        if self.cfg.replay.acknowledged:
            expired = self.acks.expire(now)
            if expired is not None:
                self.get_logger().warning(f"no ack for stamp {expired} within {self.cfg.ack_timeout_s:g} s on "
                                          f"'{self.cfg.ack_topic}' ({self.acks.timeouts} timeouts so far); going on")
            if self.acks.awaiting_ns is None:
                self._publish_next()
        else:
            assert self._next is not None  # after the start only the end, which finishes, clears it
            due = self.clock.due(self._next[1])
            if now >= due:
                # How late the frame goes out: a reader too slow for the source shows up here.
                self.stats.late_ms = round((now - due) * 1e3, 1)
                self._publish_next()
            if self._next is not None and self._finish_at is None:
                self._sleep_until(self.clock.due(self._next[1]))
        if now - self._last_progress >= PROGRESS_EVERY_S:
            self._last_progress = now
            self._log_progress(now)

    def _start(self, now: float) -> bool:
        """Start the replay when the gate opens (the first frame is read then); False to wait."""
        has_acker = self._ack_sub is None or self._ack_sub.get_publisher_count() > 0
        ready, missing = self._gate.ready(now, self.outbox.match_counts(), has_acker,
                                          self.outbox.unmatched_readers(self._wait_for))
        if missing:
            self.get_logger().warning(f"starting without {'; '.join(missing)} after {self.cfg.start_delay_s:g} s")
        if not ready:
            return False
        self._last_progress = now
        self._prefetch()
        if self._next is None:
            self.get_logger().warning("the source has no frames")
            self._finish(ok=self.ok)
            return False
        self.outbox.prepare(self._next[0])
        self.clock.start(time.monotonic(), self._next[1])  # after the first frame was read
        return True

    def _sleep_until(self, t: float) -> None:
        """Make the next tick come at ``t`` (within [MIN_TICK_S, MAX_TICK_S] from now)."""
        self._timer.timer_period_ns = int(min(max(t - time.monotonic(), MIN_TICK_S), MAX_TICK_S) * 1e9)
        self._timer.reset()  # count the new period from now, not from the last call

    def _on_ack(self, msg: Header) -> None:
        stamp_ns = codecs.stamp_to_ns(msg.stamp)
        waited = self.acks.ack(stamp_ns, time.monotonic())
        if waited is None:
            self.get_logger().debug(f"ignoring ack for stamp {stamp_ns} (waiting for {self.acks.awaiting_ns})")
            return
        self._ack_wait_ms.add(waited * 1e3)
        if self._finish_at is None:
            self._publish_next()

    # ------------------------------------------------------------------ frames
    def _prefetch(self) -> None:
        """The next good frame into self._next (None at the end or when the source fails)."""
        try:
            self._next = self.feed.next()
        except MemgsError as err:
            self.get_logger().error(f"cannot read the next frame: {err}")
            self._next, self.ok = None, False
        self._count_skips()

    def _count_skips(self) -> None:
        for kind, n in self.feed.skipped().items():  # totals (Counter.update would add them)
            self.stats.skipped[kind] = n

    def _publish_next(self) -> None:
        if self._next is None:
            self._finish(ok=self.ok)
            return
        frame, stamp_ns = self._next
        self.outbox.publish(frame, stamp_ns)
        self.stats.frames_published += 1
        self.stats.ack_timeouts = self.acks.timeouts
        self._last_sent_ns = stamp_ns
        if self.cfg.replay.acknowledged:
            self.acks.sent(stamp_ns, time.monotonic())
        self._prefetch()
        if self._next is None and not self.cfg.replay.acknowledged:
            self._finish(ok=self.ok)

    def _finish(self, ok: bool) -> None:
        if self._finish_at is not None:
            return
        now, self.ok = time.monotonic(), ok
        self._count_skips()
        self.stats.publish()  # the final counts before "done": the runner's summary reads them
        self._pub_done.publish(Bool(data=ok))
        self._log_progress(now, final=True)
        self._finish_at = now + LINGER_S

    def _log_progress(self, now: float, final: bool = False) -> None:
        n, elapsed = self.stats.frames_published, max(now - (self.clock.t0 or now), 1e-9)
        rate, last_s = n / elapsed, self._last_sent_ns * 1e-9
        self.get_logger().info(f"{'done: ' if final else ''}{n} frames in {elapsed:.1f} s ({rate:.1f} frames/s), "
                               f"last stamp {last_s:.3f} s, ack timeouts {self.acks.timeouts}")


def main(args: list[str] | None = None) -> int:
    """Exit 0 when every frame was played (or on Ctrl-C / SIGTERM: a clean stop; the runner tells
    a whole source by "done"), 1 when the source failed, 2 on a refused parameter."""
    return run_node(BagPlayer, "bag_player", args, until=lambda nodes: nodes[0].finished)


if __name__ == "__main__":
    sys.exit(main())
