"""Lint as a habit: ruff with the rules in pyproject.toml finds nothing in memgs_ros/, and mypy
finds nothing in memgs_ros/core (the test extra installs both, pinned)."""
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


def test_mypy_core_is_clean() -> None:
    r = _run("mypy", "memgs_ros/core")
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
