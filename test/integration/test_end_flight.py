"""The flight's last view made a keyframe over real DDS: ``memgs/tracker/end_flight`` (the runner
calls it at the source's end) publishes the last tracked frame's keyframe messages, once."""
from __future__ import annotations

import pytest


@pytest.mark.ros
def test_end_flight_publishes_the_last_frame_as_a_keyframe_once(context) -> None:  # noqa: ANN001
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from geometry_msgs.msg import PoseStamped
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image
    from std_srvs.srv import Trigger
    from tracker_harness import TrackerFeed

    from memgs_ros.io.synthetic import SyntheticSpec, generate_frames
    from memgs_ros.ros import qos
    from memgs_ros.ros.codecs import stamp_to_ns

    # Any view apart from every keyframe is uncovered: whether the last frame becomes one is up to it alone.
    feed = TrackerFeed(context, [Parameter("tracker.keyframe_weak_cover_m", value=0.001),
                                 Parameter("tracker.keyframe_weak_cover_deg", value=0.01)])
    poses: list[int] = []
    colors: list[int] = []
    feed.peer.create_subscription(PoseStamped, "memgs/keyframe/pose",
                                  lambda m: poses.append(stamp_to_ns(m.header.stamp)), qos.reliable(100))
    feed.peer.create_subscription(Image, "memgs/keyframe/color",
                                  lambda m: colors.append(stamp_to_ns(m.header.stamp)), qos.reliable(100))
    client = feed.peer.create_client(Trigger, "memgs/tracker/end_flight")

    def call() -> str:
        assert feed.spin_until(client.service_is_ready, 10.0)
        future = client.call_async(Trigger.Request())
        assert feed.spin_until(future.done, 20.0), "end_flight did not answer"
        res = future.result()
        assert res is not None and res.success
        return str(res.message)

    try:
        assert call() == "none"  # nothing tracked yet
        feed.wait_for_inputs()
        frames = list(generate_frames(SyntheticSpec(width=320, height=240, n_frames=12, seed=0, supersample=1)))
        feed.camera(frames[0].camera, frames[0].stamp_ns)
        for f in frames:
            feed.send(f.rgb, f.depth_m, f.stamp_ns)
            if feed.processed[-1].frame_id.startswith("frame"):  # tracked, not a keyframe: the last view
                last = f.stamp_ns
                if len(feed.processed) >= 4:
                    break
        assert feed.processed[-1].frame_id.startswith("frame") and stamp_to_ns(feed.processed[-1].stamp) == last
        assert feed.spin_until(lambda: len(poses) == feed.node.stats.values["keyframes"] and len(colors) == len(poses))
        before = len(poses)
        assert call() == f"keyframe {last}"
        assert feed.spin_until(lambda: len(poses) == before + 1 and len(colors) == before + 1), (poses, colors)
        assert poses[-1] == colors[-1] == last
        assert call() == "none"  # once: the view is a keyframe now
        assert not feed.spin_until(lambda: len(poses) > before + 1, 0.5)
    finally:
        feed.close()
