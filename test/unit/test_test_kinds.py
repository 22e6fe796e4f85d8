"""The suite's folders say what a test needs: test/unit runs in one process without DDS,
test/integration in one process over real DDS, test/system starts processes of the graph."""
from __future__ import annotations

import re
from pathlib import Path

TEST = Path(__file__).resolve().parents[1]
# What only an integration or system test does: a DDS participant in this process ...
DDS = re.compile(r"rclpy\.init\(|create_node\(|def \w+\([^)]*\bcontext\b|\bros_spin\b|tracker_harness")
# ... and what only a system test does: start the graph's processes (a node, the runner, the CLI's run).
PROCESSES = re.compile(r'"-m",\s*"memgs_ros\.nodes|_start\("memgs_ros\.nodes|"-m", "memgs_ros", "(?:run|eval)"|'
                       r'run_pipeline\(|colcon_prefix|from test_shutdown_saves import')


def _files(kind: str) -> list[Path]:
    return sorted((TEST / kind).glob("test_*.py"))


def test_every_test_file_is_in_a_kind_folder() -> None:
    assert sorted(p.name for p in TEST.glob("test_*.py")) == []
    assert all(_files(kind) for kind in ("unit", "integration", "system"))


def test_unit_tests_use_no_dds_and_start_no_graph() -> None:
    wrong = [p.name for p in _files("unit")
             if p.name != Path(__file__).name and (DDS.search(p.read_text()) or PROCESSES.search(p.read_text()))]
    assert wrong == [], f"not unit tests (move them to integration/ or system/): {wrong}"


def test_integration_tests_start_no_graph() -> None:
    wrong = [p.name for p in _files("integration") if PROCESSES.search(p.read_text())]
    assert wrong == [], f"system tests in test/integration: {wrong}"
