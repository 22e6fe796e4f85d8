"""recorder node: the graph's outputs, as published, into a ROS 2 mcap file.

Subscribes to each topic in ``topics`` (default :data:`DEFAULT_TOPICS`: every memgs output) once a
publisher of it is seen, with the message type and QoS its publishers offer (RELIABLE and
TRANSIENT_LOCAL only when every publisher offers them, so a latched map arrives whole and a
best-effort one is heard at all). Subscriptions are raw: the serialised CDR bytes go to the file
as they came, never decoded and encoded again, written by a thread of their own
(:class:`~memgs_ros.io.bag_stream.BackgroundBagStream`, so a Ctrl-C cannot cut a record in half).
Bag time is the receive time on the node's clock.

The file (``path``, ``.mcap``: ros2msg schemas, cdr encoding, the rosbag2 metadata record) is
written under a hidden temporary name beside ``path`` and moved into place when the node stops
(Ctrl-C, SIGTERM, or the runner's SIGINT), with its summary and footer: Foxglove, ``ros2 bag``
and rosbags open it without ``metadata.yaml``. An existing file at ``path`` is replaced only
then. ``memgs/recorder/stats`` counts ``messages`` and ``bytes``; the shutdown log line gives
the messages, size and the process's CPU time.

    ros2 run memgs_ros recorder --ros-args -p path:=/data/run.mcap -r __ns:=/uav1
"""
from __future__ import annotations

import functools
import importlib
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.topic_endpoint_info import TopicEndpointInfo

from memgs_ros.core.runtime.telemetry_fields import RecorderFields
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.bag_stream import BackgroundBagStream, ros2_typestore
from memgs_ros.nodes.params import DEFAULT_TOPICS, NODE_CONFIGS, RecorderParams
from memgs_ros.ros.config_params import declare_config
from memgs_ros.ros.diagnostics import NodeStats
from memgs_ros.ros.node_main import run_node

__all__ = ["CONFIGS", "DEFAULT_TOPICS", "RecorderNode", "RecorderParams", "main"]



CONFIGS = NODE_CONFIGS["recorder"]

# A RELIABLE subscription keeps this many messages while the callback catches up; the callback
# only appends bytes to a file, so the queue stays near empty.
_QUEUE_DEPTH = 100
_INT32_MAX, _UINT32_MAX = 2**31 - 1, 2**32 - 1


def _message_class(msgtype: str) -> type:
    """``pkg/msg/Name`` -> the rclpy message class (ImportError/AttributeError when not installed)."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def subscription_qos(publishers: Sequence[TopicEndpointInfo]) -> QoSProfile:
    """The QoS that hears every publisher of a topic (what ``ros2 bag record`` picks): RELIABLE
    only if all publishers are (a RELIABLE reader gets nothing from a BEST_EFFORT writer), and
    TRANSIENT_LOCAL only if all are (it cannot match a VOLATILE writer), to get latched samples."""
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=_QUEUE_DEPTH,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _bag_qos(profile: QoSProfile) -> Any:
    """An offered rclpy QoS as the rosbags ``Qos`` the bag's metadata keeps (so a player re-offers it)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    def t(duration: Any) -> QosTime:
        sec, nsec = divmod(int(duration.nanoseconds), 1_000_000_000)
        # "infinite" comes back as ~2**63 ns: rosbag2 writes it as the largest Time there is.
        return QosTime(sec, nsec) if sec <= _INT32_MAX else QosTime(_INT32_MAX, _UINT32_MAX)

    return Qos(history=QosHistory(int(profile.history)), depth=int(profile.depth),
               reliability=QosReliability(int(profile.reliability)),
               durability=QosDurability(int(profile.durability)),
               deadline=t(profile.deadline), lifespan=t(profile.lifespan),
               liveliness=QosLiveliness(int(profile.liveliness)),
               liveliness_lease_duration=t(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


class RecorderStats(NodeStats, RecorderFields):
    stats_name = "recorder"


class RecorderNode(Node):
    """Records ``topics`` into ``path`` (module docstring); the file is finished by :meth:`close`."""

    def __init__(self, **node_kwargs: Any) -> None:  # rclpy Node's keyword arguments
        # The type store is the slow part of starting (rosbags builds it): load it before the node
        # shows in the graph, so whoever sees the node sees it ready moments later.
        typestore = ros2_typestore()
        super().__init__("recorder", **node_kwargs)
        v = declare_config(self, RecorderParams, "")
        path, topics, period = v.path, v.topics, v.discovery_period_s
        if not isinstance(topics, (list, tuple)) or not topics or not all(
                isinstance(t, str) and t.strip() for t in topics):
            raise ConfigError(f"parameter 'topics' must be a non-empty list of topic names, got {topics!r}")
        if not path:
            raise ConfigError("parameter 'path' is required: the .mcap file to record into")
        if Path(path).suffix != ".mcap":
            raise ConfigError(f"parameter 'path' = {path!r} must end in .mcap")
        self.stats = RecorderStats(self)
        # Absolute names, as the graph and the bag name topics (remaps and namespace applied).
        try:
            self.pending: list[str] = list(dict.fromkeys(self.resolve_topic_name(t.strip()) for t in topics))
        except Exception as err:  # rclpy's InvalidTopicNameException and kin: a typo in a name
            raise ConfigError(f"parameter 'topics': {err}") from err
        self.recorded: dict[str, str] = {}  # topic -> message type
        self.bag = BackgroundBagStream(path, overwrite=True, typestore=typestore)
        try:
            self._discovery = self.create_timer(period, self._discover)
            self._discover()
            self.startup_cpu_s = time.process_time()
            self.get_logger().info(f"recording {len(self.pending) + len(self.recorded)} topics into {path}")
        except BaseException:  # stopped (Ctrl-C) or failed while starting: no file, no temporary one
            self.bag.abort()
            raise

    def _discover(self) -> None:
        """Subscribe to every wanted topic that has publishers now; stop looking once all have."""
        if not self.bag.is_open:  # stopping
            return
        for topic in list(self.pending):
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue
            types = sorted({p.topic_type for p in publishers})
            self.pending.remove(topic)
            if len(types) > 1:
                self.stats.problem("type_conflict", f"{topic} is published with several types {types}: not recorded")
                continue
            try:
                msg_class = _message_class(types[0])
                self.bag.add_topic(topic, types[0], [_bag_qos(p.qos_profile) for p in publishers])
            except (ImportError, AttributeError, ValueError, DataError) as err:
                self.stats.problem("unknown_type", f"{topic} ({types[0]}) cannot be recorded: {err}")
                continue
            self.create_subscription(msg_class, topic, functools.partial(self._on_message, topic),
                                     subscription_qos(publishers), raw=True)
            self.recorded[topic] = types[0]
        self.stats.topics = len(self.recorded)
        if not self.pending:
            self._discovery.cancel()

    def _on_message(self, topic: str, data: bytes) -> None:
        # A DataError (disk full) leaves the spin: main() logs it as fatal and the node exits 2.
        if self.bag.write(topic, self.get_clock().now().nanoseconds, data):
            self.stats.messages += 1
            self.stats.bytes += len(data)

    def close(self) -> None:
        """Close the file (summary, footer) and move it into place."""
        if not self.bag.is_open:
            return
        size = self.bag.close()
        counts = self.bag.counts
        cpu = time.process_time()
        self.get_logger().info(
            f"recorded {sum(counts.values())} messages on {sum(1 for n in counts.values() if n)} topics into "
            f"{self.bag.path} ({size / 1e6:.2f} MB); cpu_s={cpu:.2f} startup_cpu_s={self.startup_cpu_s:.2f}")


def main(args: list[str] | None = None) -> int:
    return run_node(RecorderNode, "recorder", args)


if __name__ == "__main__":
    sys.exit(main())
