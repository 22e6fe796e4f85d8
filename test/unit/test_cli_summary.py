"""What ``memgs run`` prints after a run: the ATE line when the source has ground truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from memgs_ros.cli.run import print_trajectory_error
from memgs_ros.core.geometry.poses import pose_to_tq
from memgs_ros.io.sources import open_source

SPEC = "synthetic:w=32,h=24,n=12,seed=2"


def _write_tum(path: Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    lines = [f"{s * 1e-9:.9f} " + " ".join(f"{v:.9f}" for v in np.concatenate(pose_to_tq(T)))
             for s, T in zip(stamps, poses)]
    path.write_text("\n".join(lines) + "\n")


def test_ate_line_measures_the_tracked_trajectory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    stamps, poses = open_source(SPEC).ground_truth()
    exact = tmp_path / "exact.txt"
    _write_tum(exact, stamps, poses)
    print_trajectory_error(SPEC, str(exact))
    assert "ATE           0.00 cm RMSE over 12 frames" in capsys.readouterr().out
    moved = poses.copy()
    moved[::2, 0, 3] += 0.05  # every other pose 5 cm off along x: no rigid alignment removes that
    off = tmp_path / "off.txt"
    _write_tum(off, stamps, moved)
    print_trajectory_error(SPEC, str(off))
    cm = float(capsys.readouterr().out.split()[1])
    assert 2.0 < cm < 3.0


def test_no_ate_line_without_ground_truth(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A source without ground truth (a live recording) prints no ATE line and no error."""
    import memgs_ros.io.sources as sources

    class NoTruth:
        def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))

    monkeypatch.setattr(sources, "open_source", lambda source, **_: NoTruth())
    traj = tmp_path / "t.txt"
    traj.write_text("0.0 0 0 0 0 0 0 1\n")
    print_trajectory_error("recording.mcap", str(traj))
    assert capsys.readouterr().out == ""
