"""rviz/memgs.rviz shows what the nodes publish: map as the fixed frame, TF, the latched viewer cloud
subscribed Transient Local (a volatile display would miss a map published before RViz started),
the corrected path, the body odometry and the merged map's rendered view."""
from __future__ import annotations

from pathlib import Path

import yaml

from memgs_ros.nodes.params import DEFAULT_TOPICS, TrackerParams

RVIZ = Path(__file__).resolve().parents[2] / "rviz" / "memgs.rviz"


def test_the_rviz_view_matches_the_nodes_topics_frames_and_qos() -> None:
    cfg = yaml.safe_load(RVIZ.read_text())
    manager = cfg["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == TrackerParams().map_frame
    displays = {d["Class"].split("/")[-1]: d for d in manager["Displays"]}
    assert {"TF", "PointCloud2", "Path", "Odometry", "Image"} <= set(displays)
    topics = {d["Name"]: d["Topic"] for d in manager["Displays"] if d.get("Enabled") and "Topic" in d}
    for name, topic in topics.items():
        assert topic["Value"].lstrip("/") in DEFAULT_TOPICS, (name, topic["Value"])
    cloud = displays["PointCloud2"]
    assert cloud["Topic"]["Value"] == "/memgs/map/points" and cloud["Color Transformer"] == "RGB8"
    assert cloud["Topic"]["Durability Policy"] == "Transient Local"  # the merger latches it (qos.latched)
    assert displays["Odometry"]["Topic"]["Value"] == "/memgs/odom"
