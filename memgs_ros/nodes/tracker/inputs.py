"""The tracker's camera input (subscribed by ``ros/images.subscribe_camera``): colour/depth pairing
with the colour it could not pair counted and explained, and compressed messages turned into the
Images the frame path reads."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from sensor_msgs.msg import Image

from memgs_ros.errors import MessageError
from memgs_ros.nodes.tracker.stats import TrackerStats
from memgs_ros.ros.codecs import stamp_to_ns
from memgs_ros.ros.images import compressed_to_image
from memgs_ros.ros.stamp_sync import NearestPairer, UnpairedWatch

__all__ = ["RgbdPairing", "decompressed"]


def decompressed(color: Any, depth: Any | None, depth_scale: float, stats: TrackerStats
                 ) -> tuple[Image, Image | None] | None:
    """A compressed colour (and depth) message pair as the Images the tracker reads; None when one
    does not decode (counted in ``stats``: frames_in, problem.bad_image). Decoded only once a frame
    is taken: a stale one is never decoded."""
    try:
        return (compressed_to_image(color, depth_scale),
                None if depth is None else compressed_to_image(depth, depth_scale))
    except MessageError as err:
        stats.frames_in += 1
        stats.problem("bad_image", f"compressed frame {stamp_to_ns(color.header.stamp)} refused: {err}")
        return None


class RgbdPairing:
    """Colour and depth of a tracker node (``params``: its TrackerParams) paired by stamp
    (``NearestPairer``; each pair goes to ``handle``), the colour frames it dropped unpaired counted
    (``skipped.unpaired``), and the reason said when colour has found no depth for
    ``unpaired_warn_s`` (``UnpairedWatch``, ``problem.unpaired_color``)."""

    def __init__(self, node: Any, params: Any, handle: Callable[[tuple[int, Any, Any]], None]) -> None:
        self.pairer: NearestPairer[Any] = NearestPairer(
            max_dt_ns=0 if params.sync == "exact" else int(params.max_sync_dt_s * 1e9), queue_size=5)
        self.watch = UnpairedWatch(params.unpaired_warn_s)
        self._where = (node.resolve_topic_name(params.color_topic), node.resolve_topic_name(params.depth_topic),
                       params.max_sync_dt_s)
        self._node, self._handle = node, handle  # its stats are made after this

    def color(self, stamp_ns: int, msg: Any) -> None:
        self._done(self.pairer.dropped_a, self.pairer.add_a(stamp_ns, msg))

    def depth_message(self, msg: Any) -> None:
        """A depth Image (or compressedDepth) as it arrives: the depth subscription's callback."""
        self.watch.depth_seen = True
        self._done(self.pairer.dropped_a, self.pairer.add_b(stamp_to_ns(msg.header.stamp), msg), colour=False)

    def _done(self, dropped_before: int, pair: tuple[int, Any, Any] | None, colour: bool = True) -> None:
        stats = self._node.stats
        stats.skipped["unpaired"] += self.pairer.dropped_a - dropped_before
        if pair is not None:
            self.watch.paired()
            self._handle(pair)
        elif colour and (why := self.watch.waiting(time.monotonic(), *self._where)) is not None:
            stats.problem("unpaired_color", why)
