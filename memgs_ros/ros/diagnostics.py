"""Node statistics as diagnostic_msgs/DiagnosticArray on ``memgs/<node>/stats``, and the node's
health on ``/diagnostics`` (one DiagnosticStatus per node, its level judged on the current window
by ``core/runtime/health.assess``: what diagnostic_aggregator and rqt read).

Every node's stats carry ``peak_rss_mb``, ``rss_mb``, ``cpu_s`` (its process's CPU time so far) and
``nice`` (its scheduling priority) beside the node's own counters and gauges; every key is a field
of the node's telemetry record (``core/runtime/telemetry.py``), and a key the record does not name
is refused where it is written."""
from __future__ import annotations

import os
import queue
import resource
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from typing import Any, TypeVar

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from std_msgs.msg import Header

from memgs_ros.core.runtime.cpu import release_free_memory
from memgs_ros.core.runtime.health import assess
from memgs_ros.core.runtime.stat_fields import Family, Stat
from memgs_ros.core.runtime.telemetry import TELEMETRY, NodeTelemetry, StatsError, check_key
from memgs_ros.core.runtime.telemetry_fields import NodeFields
from memgs_ros.ros import qos


class RollingMedian:
    """The median of the last ``window`` values, for a computed gauge (``NodeStats.computed``):
    per-event costs are appended as they happen and the median taken once a second."""

    def __init__(self, window: int = 300) -> None:
        self._values: deque[float] = deque(maxlen=window)

    def add(self, value: float) -> None:
        self._values.append(float(value))

    def __call__(self) -> float:
        if not self._values:
            return 0.0
        ordered = sorted(self._values)
        n = len(ordered)
        mid = ordered[n // 2] if n % 2 else 0.5 * (ordered[n // 2 - 1] + ordered[n // 2])
        return round(mid, 2)


STRICT_ENV = "MEMGS_STRICT_STATS"  # "1": a stats key no record names raises (the test suite sets it)
F = TypeVar("F")


class _StatsView(Mapping[str, Any]):
    """A read-only view of the values written; a key not written yet reads 0 (as in a Counter)."""

    def __init__(self, values: dict[str, Any]) -> None:
        self._values = values

    def __getitem__(self, key: str) -> Any:  # noqa: ANN401 - a stats value
        return self._values.get(key, 0)

    def __contains__(self, key: object) -> bool:
        return key in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._values))

    def __len__(self) -> int:
        return len(self._values)


class NodeStats(NodeFields):
    """Counters and gauges a node publishes once a second, plus warn-once logging per problem kind.

    A node writes its fields by attribute through its subclass (``nodes/<name>``'s, e.g.
    ``class TrackerStats(NodeStats, TrackerFields)``: the record's generated twin,
    ``core/runtime/stat_fields.py``): ``stats.frames_in += 1``. The values belong
    to the node's default callback group (where the publish timer runs). A node whose callbacks
    run in several groups at once posts from the others (``post_add``, ``post_set``,
    ``post_member``, ``post_problem``, each naming the field on the class, e.g.
    ``MapperStats.checkpoints``): the updates queue up and ``apply_posted`` (called by ``message``,
    or by a default-group callback) applies them in order, so the values never have two writers.
    """

    stats_name = ""  # a subclass's default ``name``

    def __init__(self, node: Node, name: str = "", period_s: float = 1.0, trim_period_s: float = 30.0,
                 record: type[NodeTelemetry] | None = None) -> None:
        name = name or self.stats_name
        if record is None and name not in TELEMETRY:
            raise StatsError(f"no telemetry record for node {name!r} (core/runtime/telemetry.py)")
        self.record = record or TELEMETRY[name]
        self._node = node
        self._trim_period_s = trim_period_s  # release_free_memory this often (0 = never)
        self._last_trim = time.monotonic()
        self._name = name
        self._strict = os.environ.get(STRICT_ENV, "") == "1"
        self._values: dict[str, Any] = {}  # key -> value, in the order first written
        # Gauges computed when the message is built, for those too costly to update per frame.
        self._gauge_fns: dict[str, Callable[[], float | int | str]] = {}
        self._warned: set[str] = set()
        self._accepted: set[str] = set()  # keys of ``assign`` checked once
        self._posted: queue.SimpleQueue[tuple[str, str, object]] = queue.SimpleQueue()
        self._pub = node.create_publisher(DiagnosticArray, f"memgs/{name}/stats", qos.reliable(5))
        # /diagnostics: absolute (every node of the robot on one topic), the aggregator's QoS
        self._diag_pub = node.create_publisher(DiagnosticArray, "/diagnostics", qos.reliable(10))
        self._before: dict[str, object] | None = None  # the values of the previous window
        self._timer = node.create_timer(period_s, self.publish)

    def _stat(self, key: str, default: Any) -> Any:  # noqa: ANN401 - the field's type (stat_fields)
        return self._values.get(key, default)

    def _set_stat(self, key: str, value: Any) -> None:  # noqa: ANN401
        self._values[key] = value

    @property
    def values(self) -> Mapping[str, Any]:
        """What has been written so far, by stats key: a read-only view (write by attribute) that,
        like a Counter, reads 0 for a key not written yet."""
        return _StatsView(self._values)

    def _accepts(self, key: str) -> bool:
        """Whether ``key`` (of a mapping handed to :meth:`assign`) is a field of the node's record.
        A key it does not name is a bug in the node: the test suite (``MEMGS_STRICT_STATS=1``)
        fails on it; a robot's node drops the value and counts ``problem.stats_key`` rather than stop."""
        if key in self._accepted:
            return True
        try:
            check_key(self.record, key)
        except StatsError as err:
            if self._strict:
                raise
            self.post_problem("stats_key", str(err))
            return False
        self._accepted.add(key)
        return True

    def assign(self, values: Mapping[str, Any]) -> None:
        """Set each of ``values`` (totals kept by code that reports through this node, e.g. the
        mapping session's ``StatValues``), each key checked against the record."""
        for key, value in values.items():
            if self._accepts(key):
                self._values[key] = value

    def compute(self, stat: Stat[F], compute: Callable[[], F]) -> None:
        """Set ``stat`` from ``compute()`` each time the message is built (a rolling median)."""
        self._gauge_fns[stat.key] = compute  # type: ignore[assignment]

    def problem(self, kind: str, message: str) -> None:
        """Count a problem; log it once per kind (then only the counter grows)."""
        self.problem_counts[kind] += 1
        if kind not in self._warned:
            self._warned.add(kind)
            self._node.get_logger().warning(f"{message} (further '{kind}' problems are only counted)")

    def post_add(self, stat: Stat[int], n: int = 1) -> None:
        """From any thread: add ``n`` to counter ``stat``."""
        self._posted.put(("add", stat.key, n))

    def post_set(self, stat: Stat[F], value: F) -> None:
        """From any thread: set ``stat`` (a gauge, or a total kept elsewhere)."""
        self._posted.put(("set", stat.key, value))

    def post_member(self, family: Family[F], member: str, value: F) -> None:
        """From any thread: set ``family[member]``."""
        if not member:
            raise ValueError(f"a member of {family.key}.* needs a name")
        self._posted.put(("set", f"{family.key}.{member}", value))

    def post_problem(self, kind: str, message: str) -> None:
        """From any thread: :meth:`problem`."""
        self._posted.put(("problem", kind, message))

    def apply_posted(self) -> None:
        """Apply what other threads posted, in order (on the default callback group)."""
        while True:
            try:
                op, key, value = self._posted.get_nowait()
            except queue.Empty:
                return
            if op == "add":
                self._values[key] = self._values.get(key, 0) + int(value)  # type: ignore[call-overload]
            elif op == "set":
                self._values[key] = value
            else:
                self.problem(key, str(value))

    def message(self) -> DiagnosticArray:
        self.apply_posted()
        if self._trim_period_s > 0 and time.monotonic() - self._last_trim >= self._trim_period_s:
            self._last_trim = time.monotonic()
            release_free_memory()  # so rss_mb is what the node uses, not its heap's high-water mark
        for key, compute in self._gauge_fns.items():
            self._values[key] = compute()
        self.peak_rss_mb = round(peak_rss_mb(), 1)
        self.rss_mb = round(rss_mb(), 1)
        self.cpu_s = round(time.process_time(), 2)  # of the process (in one process: of all nodes)
        if hasattr(os, "getpriority"):
            self.nice = os.getpriority(os.PRIO_PROCESS, 0)  # the Rerun view runs at 15 under memgs run
        values = {k: v for k, v in self._values.items() if v is not None}  # None: not reported yet
        health = assess(self._name, values, self._before)
        self._before = dict(values)
        status = DiagnosticStatus(
            level=bytes([int(health.level)]), name=f"memgs/{self._name}",
            hardware_id=self._node.get_fully_qualified_name(), message=health.message,
            values=[KeyValue(key=k, value=str(v)) for k, v in sorted(values.items())])
        return DiagnosticArray(header=Header(stamp=self._node.get_clock().now().to_msg()), status=[status])

    def publish(self) -> None:
        """The stats now, on ``memgs/<node>/stats`` and ``/diagnostics`` (also called at once on a
        change a robot must hear of sooner than the next second, e.g. tracking lost)."""
        msg = self.message()
        self._pub.publish(msg)
        self._diag_pub.publish(msg)


def rss_mb() -> float:
    """This process's resident memory now (MB); 0 where /proc is missing."""
    return _proc_status_mb("VmRSS:")


def _proc_status_mb(key: str) -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB).

    VmHWM belongs to this process's own address space; ``ru_maxrss`` is carried over from the
    parent across fork/exec on Linux, so a node started by a big process would report its size.
    """
    peak = _proc_status_mb("VmHWM:")
    if peak > 0:
        return peak
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux, non-/proc systems


def stats_values(msg: DiagnosticArray) -> dict[str, str]:
    """The key/values of the first status of a stats message."""
    return {kv.key: kv.value for kv in msg.status[0].values} if msg.status else {}
