"""The mapper's inputs (nodes/mapper/inputs.py) from messages built in the test, without DDS: a
keyframe's parts gathered and decoded once complete, refusals by kind, keyframe poses of a Path."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="the ROS extra is not installed")

from keyframe_bundles import SPEC, Bundle, _bundle, _without_field  # noqa: E402
from nav_msgs.msg import Path  # noqa: E402

from memgs_ros.io.synthetic import generate_frames, parse_spec  # noqa: E402
from memgs_ros.nodes.mapper.inputs import KeyframeReceiver, keyframe_poses  # noqa: E402
from memgs_ros.ros.codecs import matrix_to_pose_stamped  # noqa: E402

PARTS = {"color": "color", "depth": "depth", "camera_info": "info", "pose": "pose", "seeds": "seeds"}


@pytest.fixture
def bundle() -> Bundle:
    """A fresh bundle each test: a test breaks its messages in place."""
    f = next(iter(generate_frames(parse_spec(SPEC))))
    return _bundle(f, f.stamp_ns)


def _feed(rx: KeyframeReceiver, b: Bundle, pose_sent_ns: int = 0):  # noqa: ANN202 - ReceivedKeyframe | None
    got = None
    for part, field in PARTS.items():
        info = {"source_timestamp": pose_sent_ns} if part == "pose" else {}
        got = rx.add(part, getattr(b, field), info)
        if part != "seeds":
            assert got is None, f"complete before its {part}"
    return got


def test_a_complete_bundle_is_one_keyframe_with_its_seeds_and_decision_time(bundle: Bundle) -> None:
    rx = KeyframeReceiver(set(PARTS), frozenset())
    got = _feed(rx, bundle, pose_sent_ns=123)
    assert got is not None and got.keyframe is not None and got.problem == ""
    kf = got.keyframe
    assert got.stamp_ns == kf.stamp_ns == bundle.stamp and kf.decided_ns == 123
    assert kf.points_w is not None and kf.colors is not None and len(kf.points_w) == len(kf.colors) == 50
    assert _feed(rx, bundle) is None and rx.intake.duplicate_parts == 5  # a replay of the same keyframe


def test_a_keyframe_known_from_a_checkpoint_is_not_taken_again(bundle: Bundle) -> None:
    rx = KeyframeReceiver(set(PARTS), frozenset({bundle.stamp}))
    assert _feed(rx, bundle) is None and rx.intake.duplicate_parts == 5


def test_a_bad_bundle_is_refused_whole_by_kind(bundle: Bundle) -> None:
    rx = KeyframeReceiver(set(PARTS), frozenset())
    bad = Bundle(**{**bundle.__dict__, "seeds": _without_field(bundle.seeds, "rgb")})
    got = _feed(rx, bad)
    assert got is not None and got.keyframe is None and got.problem == "bad_seeds"
    assert got.message.startswith(f"keyframe {bundle.stamp} refused: ")
    pose = matrix_to_pose_stamped(np.eye(4), bundle.stamp, "map")
    pose.pose.orientation.w = float("nan")
    got = _feed(KeyframeReceiver(set(PARTS), frozenset()), Bundle(**{**bundle.__dict__, "pose": pose}))
    assert got is not None and got.keyframe is None and got.problem == "bad_pose"


def test_keyframe_poses_keep_the_good_and_name_the_refused() -> None:
    bad = matrix_to_pose_stamped(np.eye(4), 7, "map")
    bad.pose.orientation.w = float("nan")
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    poses, refused = keyframe_poses(Path(poses=[matrix_to_pose_stamped(T, 5, "map"), bad]))
    assert list(poses) == [5] and np.allclose(poses[5], T)
    assert len(refused) == 1 and refused[0].startswith("refined pose of keyframe 7 ignored: ")
