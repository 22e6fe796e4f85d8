"""NodeStats with several writer threads: what they post is applied by one thread, in order,
with nothing lost, while stats messages are built (the mapper writes from four callback groups)."""
from __future__ import annotations

import threading

import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from collections.abc import Mapping  # noqa: E402
from dataclasses import dataclass  # noqa: E402

from memgs_ros.core.runtime.stat_fields import Family, Stat  # noqa: E402
from memgs_ros.core.runtime.telemetry import NodeTelemetry, StatsError  # noqa: E402
from memgs_ros.core.runtime.telemetry_fields import NodeFields  # noqa: E402
from memgs_ros.nodes.tracker.stats import TrackerStats  # noqa: E402
from memgs_ros.ros.diagnostics import NodeStats, stats_values  # noqa: E402


@dataclass(frozen=True)
class _TestTelemetry(NodeTelemetry):
    posted: int = 0
    g0: Mapping[str, int] = None  # type: ignore[assignment]  # families g0.* .. g3.*
    g1: Mapping[str, int] = None  # type: ignore[assignment]
    g2: Mapping[str, int] = None  # type: ignore[assignment]
    g3: Mapping[str, int] = None  # type: ignore[assignment]


class _TestFields(NodeFields):  # what stat_fields would generate for _TestTelemetry
    posted = Stat[int](0)
    g0, g1, g2, g3 = (Family[int](f"g{k}", 0) for k in range(4))


class _TestStats(NodeStats, _TestFields):
    pass


def test_posts_from_many_threads_are_applied_whole(context) -> None:  # noqa: ANN001
    node = rclpy.create_node("stats_test", context=context)
    try:
        stats = _TestStats(node, "stats_test", period_s=3600.0, record=_TestTelemetry)
        n_threads, n_posts = 4, 2000
        families = (_TestStats.g0, _TestStats.g1, _TestStats.g2, _TestStats.g3)
        stop = threading.Event()
        errors: list[BaseException] = []

        def writer(k: int) -> None:
            for i in range(n_posts):
                stats.post_add(_TestStats.posted)
                stats.post_member(families[k], str(i % 50), i)  # new keys appear while messages are built
            stats.post_problem(f"kind{k}", "a problem")

        def reader() -> None:
            try:
                while not stop.is_set():
                    stats.message()
            except BaseException as err:  # noqa: BLE001 - the test reports it
                errors.append(err)

        r = threading.Thread(target=reader)
        r.start()
        writers = [threading.Thread(target=writer, args=(k,)) for k in range(n_threads)]
        for w in writers:
            w.start()
        for w in writers:
            w.join()
        stop.set()
        r.join()
        values = stats_values(stats.message())
        assert errors == []
        assert int(values["posted"]) == n_threads * n_posts
        assert all(int(values[f"problem.kind{k}"]) == 1 for k in range(n_threads))
        assert int(values["g0.49"]) == n_posts - 1  # the last value posted wins
        assert stats.posted == n_threads * n_posts and stats.g0["49"] == n_posts - 1  # read back by attribute
    finally:
        node.destroy_node()


def test_fields_written_by_attribute_reach_the_message_and_a_handed_key_is_checked(context) -> None:  # noqa: ANN001
    """Typed writes (mypy checks the names: test_telemetry) reach the message as keys; a mapping
    handed over whole (``assign``: the mapping session's counters) is checked key by key."""
    node = rclpy.create_node("stats_keys", context=context)
    try:
        stats = TrackerStats(node)
        stats.frames_in += 1
        stats.skipped["stale"] += 1  # a member of the skipped.* family
        stats.frame_cpu_ms = 1.5
        stats.assign({"keyframes": 2, "state.OK": 3})
        for bad in ({"frames_received": 1}, {"frame_cpu": 1.0}, {"skipped": 1}):  # a family needs a member
            with pytest.raises(StatsError, match="TrackerTelemetry has no stats key"):
                stats.assign(bad)
        with pytest.raises(ValueError, match="needs a name"):
            stats.skipped[""] = 1
        values = stats_values(stats.message())
        assert values["frames_in"] == "1" and values["skipped.stale"] == "1" and values["frame_cpu_ms"] == "1.5"
        assert values["keyframes"] == "2" and values["state.OK"] == "3"
        assert "tracking_state" not in values  # a field never written is not reported
        assert stats.values["frames_in"] == 1 and stats.values["poses_out"] == 0  # unwritten: 0, as a Counter
        with pytest.raises(StatsError, match="no telemetry record"):
            NodeStats(node, "no_such_node")
    finally:
        node.destroy_node()


def test_outside_the_tests_an_unnamed_key_is_counted_and_dropped(context, monkeypatch) -> None:  # noqa: ANN001
    """On a robot a misspelt key handed over must not stop the node: the value is dropped, the problem counted."""
    monkeypatch.delenv("MEMGS_STRICT_STATS")
    node = rclpy.create_node("stats_lenient", context=context)
    try:
        stats = TrackerStats(node)
        stats.assign({"frames_received": 1, "warmup_s": 1.0})
        stats.assign({"frame_cpu_ms": 1.5, "frame_cpu": 2.0})
        values = stats_values(stats.message())
        assert "frames_received" not in values and "warmup_s" not in values and "frame_cpu" not in values
        assert values["frame_cpu_ms"] == "1.5" and values["problem.stats_key"] == "3"
    finally:
        node.destroy_node()
