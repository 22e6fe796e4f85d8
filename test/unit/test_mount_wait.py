"""When the camera's mount in the body is settled (core/geometry/frames.py: MountWait): TF's as soon
as it has one, the parameters' once the wait is over, nothing to wait for where the node publishes
the mount itself."""
from __future__ import annotations

import numpy as np

from memgs_ros.core.geometry.frames import MountWait


def test_tf_settles_the_mount_as_soon_as_it_has_it() -> None:
    wait = MountWait(wait_ns=1_000, settled=False)
    assert wait.settle(5_000, None) is None and not wait.settled  # asked at 5000: waits
    assert wait.settle(5_900, None) is None
    assert wait.settle(5_950, np.eye(4)) == "tf" and wait.settled
    assert wait.settle(9_000, np.eye(4)) is None  # settled before: nothing new


def test_the_parameters_stand_in_once_the_wait_is_over() -> None:
    wait = MountWait(wait_ns=1_000, settled=False)
    assert wait.settle(5_000, None) is None
    assert wait.settle(6_000, None) == "parameters" and wait.settled
    assert wait.settle(6_001, np.eye(4)) is None  # TF too late: the parameters' mount is kept


def test_nothing_to_wait_for() -> None:
    wait = MountWait(wait_ns=1_000, settled=True)
    assert wait.settled and wait.settle(0, None) is None
