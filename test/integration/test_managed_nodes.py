"""Managed nodes (ros/lifecycle.py) driven with lifecycle_msgs/srv/ChangeState over real DDS:
configure builds the node, activate takes frames, deactivate pauses (frames answered and counted,
none tracked), cleanup removes what configure made and a second configure starts again."""
from __future__ import annotations

import itertools
import threading
import time

import numpy as np
import pytest


def test_the_tracker_is_configured_activated_paused_and_resumed_by_service(context) -> None:  # noqa: ANN001
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from lifecycle_msgs.msg import State, Transition
    from lifecycle_msgs.srv import ChangeState, GetState
    from rclpy.parameter import Parameter
    from tracker_harness import TrackerFeed

    from memgs_ros.io.synthetic import generate_frames, parse_spec

    feed = TrackerFeed(context, [Parameter("autostart", value=False)])
    node, sup = feed.node, feed.peer
    change = sup.create_client(ChangeState, "tracker/change_state")
    get = sup.create_client(GetState, "tracker/get_state")

    def call(client, request):  # noqa: ANN001, ANN202
        future = client.call_async(request)
        assert feed.spin_until(future.done, 30.0), f"{client.srv_name} did not answer"
        return future.result()

    def transition(tid: int) -> bool:
        return call(change, ChangeState.Request(transition=Transition(id=tid))).success

    def state() -> int:
        return call(get, GetState.Request()).current_state.id

    frames = list(itertools.islice(generate_frames(parse_spec("synthetic:w=320,h=240,n=60,seed=3")), 15))

    def send(fs) -> None:  # noqa: ANN001
        for f in fs:
            feed.send(f.rgb, f.depth_m, f.stamp_ns)

    try:
        assert feed.spin_until(lambda: change.service_is_ready() and get.service_is_ready())
        assert state() == State.PRIMARY_STATE_UNCONFIGURED and not node.configured
        assert feed.color.get_subscription_count() == 0  # nothing subscribed before configure
        t0 = time.perf_counter()
        assert transition(Transition.TRANSITION_CONFIGURE) and state() == State.PRIMARY_STATE_INACTIVE
        assert transition(Transition.TRANSITION_ACTIVATE) and state() == State.PRIMARY_STATE_ACTIVE
        feed.wait_for_inputs()
        print(f"configure -> active, kernels warm: {time.perf_counter() - t0:.2f} s")
        feed.camera(frames[0].camera, frames[0].stamp_ns)
        send(frames[:5])
        tracked = node.stats.values["state.OK"]
        assert tracked >= 4
        # Paused: every frame answered and counted, none tracked.
        assert transition(Transition.TRANSITION_DEACTIVATE) and state() == State.PRIMARY_STATE_INACTIVE
        send(frames[5:10])
        assert node.stats.values["skipped.inactive"] == 5 and node.stats.values["state.OK"] == tracked
        # Resumed: tracking goes on from the map it kept.
        assert transition(Transition.TRANSITION_ACTIVATE)
        send(frames[10:])
        assert node.stats.values["state.OK"] == tracked + 5
        # Cleanup removes the topics configure made; a second configure makes them again.
        assert transition(Transition.TRANSITION_DEACTIVATE) and transition(Transition.TRANSITION_CLEANUP)
        assert state() == State.PRIMARY_STATE_UNCONFIGURED and node.tracker is None
        assert feed.spin_until(lambda: feed.color.get_subscription_count() == 0)
        assert transition(Transition.TRANSITION_CONFIGURE) and transition(Transition.TRANSITION_ACTIVATE)
        assert feed.spin_until(lambda: feed.color.get_subscription_count() == 1)
        assert transition(Transition.TRANSITION_ACTIVE_SHUTDOWN) and state() == State.PRIMARY_STATE_FINALIZED
    finally:
        feed.close()


def test_a_bad_parameter_refuses_the_node_and_autostart_keeps_one_command_behaviour(
        context, ros_domain_id: int) -> None:  # noqa: ANN001
    rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from rclpy.parameter import Parameter

    from memgs_ros.errors import ConfigError
    from memgs_ros.nodes.merger.node import MergerNode

    with pytest.raises(ConfigError):
        MergerNode(context=context, parameter_overrides=[Parameter("render_width", value=-3)])
    node = MergerNode(context=context)  # autostart: configured and active from the constructor
    try:
        assert node.configured and node.active and node.configure_s is not None
        assert node._state_machine.current_state[1] == "active"
        assert np.isfinite(node.configure_s)
    finally:
        node.close()
        node.destroy_node()
    # Destroyed means gone from the graph (rclpy's lifecycle state machine held the node's handle,
    # which kept it discoverable while the Python object lived).
    watcher_ctx = rclpy.Context()
    rclpy.init(context=watcher_ctx, domain_id=ros_domain_id)
    watcher = rclpy.create_node("watcher", context=watcher_ctx)
    try:
        end = time.monotonic() + 10.0
        # neither the refused node nor the destroyed one
        while time.monotonic() < end and "merger" in dict(watcher.get_node_names_and_namespaces()):
            time.sleep(0.05)
        assert "merger" not in dict(watcher.get_node_names_and_namespaces())
    finally:
        watcher.destroy_node()
        rclpy.try_shutdown(context=watcher_ctx)


def test_the_runner_brings_managed_nodes_up_and_names_one_that_refuses(context) -> None:  # noqa: ANN001
    rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from memgs_ros.errors import ConfigError, PipelineError
    from memgs_ros.nodes.merger.node import MergerNode
    from memgs_ros.orchestration.bring_up import bring_up
    from memgs_ros.ros.lifecycle import ManagedNode

    class Refuses(ManagedNode):
        def __init__(self, **kw: object) -> None:
            super().__init__("refuses", **kw)
            self.start_lifecycle(False)

        def configure_node(self) -> None:
            raise ConfigError("no camera here")

    merger = MergerNode(context=context, parameter_overrides=[Parameter("autostart", value=False)])
    refuses = Refuses(context=context)
    runner = rclpy.create_node("runner", context=context)
    ex = SingleThreadedExecutor(context=context)
    for n in (merger, refuses, runner):
        ex.add_node(n)
    spinning = True

    def spin() -> None:
        while spinning:
            ex.spin_once(timeout_sec=0.02)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        assert not merger.configured
        seconds = bring_up(runner, ["merger"], lambda: None, time.monotonic() + 30)
        assert merger.configured and merger.active and 0 < seconds < 30
        with pytest.raises(PipelineError, match="refuses refused to configure"):
            bring_up(runner, ["refuses"], lambda: None, time.monotonic() + 30)
        with pytest.raises(PipelineError, match="nobody offered no lifecycle service"):
            bring_up(runner, ["nobody"], lambda: None, time.monotonic() + 0.5)
    finally:
        spinning = False
        thread.join(5)
        ex.shutdown()
        for n in (merger, refuses, runner):
            n.destroy_node()
