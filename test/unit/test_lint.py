"""Lint as a habit: ruff with the rules in pyproject.toml finds nothing in memgs_ros/, and mypy
finds nothing in what a node runs: memgs_ros/core, io, ros and nodes (the test extra installs both, pinned)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _run(*cmd: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *cmd], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_ruff_finds_nothing() -> None:
    r = _run("ruff", "check", "--no-cache", "memgs_ros")
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]


def test_mypy_finds_nothing_in_what_a_node_runs() -> None:
    """core/, io/, ros/ and nodes/: a node's code, so a renamed field or config is caught here."""
    r = _run("mypy", "memgs_ros/core", "memgs_ros/io", "memgs_ros/ros", "memgs_ros/nodes")
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
