"""The run tier of the evaluation reads what a run recorded: summary, parameters, stats timeline.

No ROS here: a finished run is a folder of files (see memgs_ros.orchestration.run_files).
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from memgs_ros.errors import DataError
from memgs_ros.evaluation.timeline import MapSample, map_samples, node_peak_rss_mb, training_rate
from memgs_ros.orchestration.run_files import (
    NODE_NAMES,
    RunSummary,
    read_params,
    read_stats_timeline,
    read_summary,
)

TIMELINE = [
    {"t_s": 0.5, "node": "mapper", "iteration": "0", "peak_rss_mb": "300.0"},  # no map gauges yet
    {"t_s": 1.0, "node": "tracker", "peak_rss_mb": "210.5"},
    {"t_s": 1.5, "node": "mapper", "iteration": "10", "gaussians": "1200", "model_bytes": "4000",
     "peak_rss_mb": "410.0"},
    {"t_s": 2.0, "node": "player", "peak_rss_mb": "90.0"},
    {"t_s": 2.5, "node": "mapper", "iteration": "30", "gaussians": "1500", "model_bytes": "5000",
     "cuda_max_allocated": "7000", "peak_rss_mb": "405.0"},
    {"t_s": 3.0, "node": "tracker", "peak_rss_mb": "not a number"},
]


def _summary(tmp_path: Path) -> RunSummary:
    return RunSummary(
        source="synthetic:n=3", frames=3, poses=3, keyframes=1, gaussians=10, tracking_fps=20.0, wall_s=4.0,
        ply_path=str(tmp_path / "map.ply"), trajectory_path=str(tmp_path / "trajectory.txt"), delta_messages=2,
        delta_bytes=100, delta_bytes_per_s=25.0, lost_frames=0, merger_seq=2, namespace="", domain_id=7,
        mapping_iterations=30, model_bytes_peak=5000, gaussians_peak=12, peak_rss_mb={"mapper": 405.0},
        merger_resyncs=0, restarts={}, replica_identical=True, replica_max_abs_diff=0.0, render_size=(64, 48),
        render_std=3.0)


def test_map_samples_and_peak_rss_come_from_the_stats_timeline() -> None:
    samples = map_samples(TIMELINE)
    assert samples == (MapSample(1.5, 10, 1200, 4000, None), MapSample(2.5, 30, 1500, 5000, 7000))
    assert training_rate(samples) == pytest.approx(20.0)  # 20 iterations in 1 s
    # The largest VmHWM each node reported (not the last), the player under its node name.
    assert node_peak_rss_mb(TIMELINE) == {"mapper": 410.0, "tracker": 210.5, "bag_player": 90.0}
    assert map_samples([]) == () and node_peak_rss_mb([]) == {}


def test_run_files_round_trip_and_name_the_file_when_broken(tmp_path: Path) -> None:
    s = _summary(tmp_path)
    (tmp_path / "summary.json").write_text(json.dumps(s.as_dict()))
    assert read_summary(tmp_path) == s
    (tmp_path / "stats_timeline.jsonl").write_text("".join(json.dumps(r) + "\n" for r in TIMELINE))
    assert read_stats_timeline(tmp_path) == TIMELINE
    (tmp_path / "params.yaml").write_text("/**/mapper:\n  ros__parameters:\n    mapping.resolution_scale: 0.5\n")
    assert read_params(tmp_path) == {"mapper": {"mapping.resolution_scale": 0.5}}
    assert read_stats_timeline(tmp_path / "nowhere") == []
    with pytest.raises(DataError, match=r"run summary .*nowhere.summary\.json"):
        read_summary(tmp_path / "nowhere")
    (tmp_path / "stats_timeline.jsonl").write_text('{"t_s": 1.0, "node": "mapper"}\n[1, 2]\n')
    with pytest.raises(DataError, match=r"stats_timeline\.jsonl: line 2 is not a stats row"):
        read_stats_timeline(tmp_path)
    (tmp_path / "summary.json").write_text('{"source": "x"}')
    with pytest.raises(DataError, match=r"summary\.json"):
        read_summary(tmp_path)


def test_the_runner_starts_one_imported_module_per_node_name() -> None:
    pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")
    from memgs_ros.orchestration.pipeline import GRAPH_NODES, NODE_MODULES

    assert set(NODE_MODULES) == set(NODE_NAMES) and set(GRAPH_NODES) < set(NODE_NAMES)
    for name, module in NODE_MODULES.items():
        assert module.__name__ == f"memgs_ros.nodes.{name}.node" and callable(module.main)
