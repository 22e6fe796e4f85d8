"""The package built with colcon into an ament prefix, as on a robot (shared by the tests that
need the install: test_colcon.py, test_launch.py; conftest.py builds it once per session)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PKG = "memgs_ros"


def build(ws: Path) -> Path:
    """colcon build of the repository in ``ws``; returns the install prefix (isolated layout:
    ``<prefix>/memgs_ros/...``)."""
    colcon = shutil.which("colcon")
    assert colcon, "colcon is not on PATH (pip install colcon-core colcon-ros colcon-python-setup-py)"
    proc = subprocess.run(
        [colcon, "--log-base", str(ws / "log"), "build", "--base-paths", str(REPO),
         "--build-base", str(ws / "build"), "--install-base", str(ws / "install")],
        cwd=ws, capture_output=True, text=True, timeout=180, check=False,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    return ws / "install"


def install_env(prefix: Path, domain_id: int) -> dict[str, str]:
    """What sourcing <prefix>/setup.sh sets for this package, plus a private DDS domain."""
    site = prefix / PKG / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join([str(prefix / PKG), env.get("AMENT_PREFIX_PATH", "")]).rstrip(os.pathsep)
    return env
