"""The runner's trajectory files: a pose the tracker published that never reached the runner is
reported, not silently left out of the trajectory that evaluation scores."""
from __future__ import annotations

import logging
import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from memgs_ros.orchestration.pipeline import _write_trajectories


class _Observer:
    """What _write_trajectories reads of a GraphObserver: the poses received, the tracker's count sent."""

    def __init__(self, received: int, sent: int) -> None:
        self._lock = threading.Lock()
        self.trajectory = [(10**9 * (k + 1), np.eye(4)) for k in range(received)]
        self.keyframes: list[tuple[int, np.ndarray]] = []
        self.timeline: list[dict[str, Any]] = []
        self._sent = sent

    def corrected_poses(self) -> dict[int, np.ndarray]:
        return {}

    def telemetry(self, node: str) -> SimpleNamespace:
        assert node == "tracker"
        return SimpleNamespace(poses_out=self._sent)


def test_every_pose_received_writes_no_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        assert _write_trajectories(_Observer(5, 5), tmp_path) == 5  # type: ignore[arg-type]
    assert caplog.records == []
    assert len([r for r in (tmp_path / "trajectory.txt").read_text().splitlines() if not r.startswith("#")]) == 5


def test_a_pose_lost_on_the_way_is_reported(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        assert _write_trajectories(_Observer(199, 200), tmp_path) == 199  # type: ignore[arg-type]
    assert [r.getMessage() for r in caplog.records] == [
        "trajectory.txt holds 199 of the 200 poses the tracker published"]
