"""Each node process loads the heavy modules it runs and no others: numba costs a process ~100 MB
of RSS and torch ~200 MB, which the keyframe sampler, the merger and the player do without.

Each case starts a fresh interpreter (the suite's own process has loaded everything), imports a
node's module, runs the work that node does on every keyframe or frame without ROS, and reports the
heavy modules it loaded and its peak RSS."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("numba", "llvmlite", "torch", "scipy", "matplotlib")

# What each node's every-keyframe (or every-frame) work runs, after importing the node module.
_SAMPLER = """
import numpy as np
from memgs_ros.core.geometry.camera import TUM_FR1
from memgs_ros.core.geometry.view import view_preparation, depth_to_metres
from memgs_ros.core.sampling import PatchGridConfig, seeds_rgbd
rgb = np.full((480, 640, 3), 90, np.uint8)
units = np.full((480, 640), 5000, np.uint16)
prep = view_preparation(TUM_FR1)
image, depth = prep(rgb, units, 5000.0)
uv = np.array([[100.0, 100.0], [300.0, 200.0]], np.float32)
seeds_rgbd(image, depth, prep.camera, np.eye(4), 0, uv, np.array([1.0, 1.0], np.float32), PatchGridConfig())
depth_to_metres(units, 5000.0)
"""
_PLAYER = """
import numpy as np
from memgs_ros.core.geometry.camera import TUM_FR1
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.ros import images
frame = Frame(1, np.zeros((480, 640, 3), np.uint8), DepthUnits(np.ones((480, 640), np.uint16), 5000.0), TUM_FR1)
images.numpy_to_image(frame.rgb, "rgb8", 1, "cam")
images.numpy_to_image(frame.depth_m.raw, "16UC1", 1, "cam")
"""
_MERGER = """
from memgs_ros.core.map_io.follower import MapFollower
"""

CASES = {
    # node module: (work, heavy modules allowed, RSS ceiling MB)
    "memgs_ros.nodes.keyframe_sampler.node": (_SAMPLER, set(), 140),
    "memgs_ros.nodes.bag_player.node": (_PLAYER, set(), 140),
    "memgs_ros.nodes.merger.node": (_MERGER, set(), 140),
    "memgs_ros.nodes.tracker.node": ("", {"scipy"}, 200),
}

# VmHWM, not getrusage's ru_maxrss: a child started by exec keeps its parent's (the suite's) peak there.
_PROBE = """
import importlib, json, sys
importlib.import_module({module!r})
{work}
hwm = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
print(json.dumps({{"heavy": sorted(m for m in {heavy!r} if m in sys.modules), "rss_mb": hwm / 1024}}))
"""


def _probe(module: str, work: str) -> dict:
    code = _PROBE.format(module=module, work=work, heavy=HEAVY)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("module", sorted(CASES))
def test_a_node_loads_only_the_heavy_modules_it_runs(module: str) -> None:
    pytest.importorskip("rclpy", reason="the node modules import rclpy")
    work, allowed, ceiling_mb = CASES[module]
    got = _probe(module, work)
    assert set(got["heavy"]) <= allowed, f"{module} loaded {sorted(set(got['heavy']) - allowed)}"
    assert got["rss_mb"] < ceiling_mb, f"{module}: {got['rss_mb']:.0f} MB after import and its work"


def test_the_tracker_warm_up_loads_the_depth_kernels() -> None:
    """The tracker converts every frame's depth: its warm-up compiles the passes (the others do not)."""
    pytest.importorskip("numba")
    code = ("from memgs_ros.core.geometry import view\nassert view._depth_kernels is None\n"
            "from memgs_ros.core.tracking import warm_up\nwarm_up()\nassert view._depth_kernels is not None\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_decoding_a_pose_loads_no_scipy() -> None:
    """Every node's executor decodes poses (keyframe poses, TF, corrected paths). A first scipy
    import there, beside a worker importing scipy's linear algebra (numba's compile does), stopped a
    resumed mapper with Python's import _DeadlockError: the conversion is numpy's."""
    pytest.importorskip("rclpy", reason="the message types come from rclpy's packages")
    code = ("import sys\nfrom geometry_msgs.msg import Pose\nfrom memgs_ros.ros.codecs import pose_to_matrix\n"
            "p = Pose()\np.orientation.x, p.orientation.w = 0.6, 0.8\nT = pose_to_matrix(p)\n"
            "assert abs(T[1, 2] + 0.96) < 1e-12, T\nassert 'scipy' not in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
