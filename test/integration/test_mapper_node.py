"""The mapper node in-process (private rclpy context, real DDS): what its services leave unanswered
still reaches its stats."""
from __future__ import annotations

import pytest

rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_spin import spin_until  # noqa: E402

from memgs_ros.errors import DataError  # noqa: E402

pytestmark = pytest.mark.ros


# Only one of them runs within the test: the other's first tick is 100 s away (or never).
PERIODIC = {"delta": [Parameter("delta_rate_hz", value=20.0)],
            "snapshot": [Parameter("delta_rate_hz", value=0.01), Parameter("snapshot_period_s", value=0.05)]}


@pytest.mark.parametrize("kind", sorted(PERIODIC))
def test_a_failed_periodic_delta_or_snapshot_is_counted(context, kind: str) -> None:  # noqa: ANN001
    from memgs_ros.nodes.mapper.node import MapperNode

    node = MapperNode(context=context, parameter_overrides=[
        Parameter("device", value="cpu"), Parameter("render_rate_hz", value=0.0), *PERIODIC[kind]])
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    c = node.stats.values
    try:
        def unreadable(m):  # noqa: ANN001, ANN202 - runs on the session's worker
            def snapshot():  # noqa: ANN202
                raise DataError("the map cannot be read")
            m.snapshot = snapshot

        node.session.call(unreadable).result(120)  # behind the kernels' warm-up
        assert spin_until(ex, lambda: c["problem.command_failed"] >= 1), dict(c)  # each cuts the map
    finally:
        node.close()
        ex.shutdown()
        node.destroy_node()
