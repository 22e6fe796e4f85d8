"""Warm from the first frame: the warm-ups compile the very kernel signatures a run uses, so that no
frame compiles one (a second signature for a read-only or strided array cost a live run's first
frame 1.7 s and 49 frames). Runs the real kernels on synthetic frames, each check in a fresh
process (another test's calls would have compiled signatures of their own)."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from memgs_ros.core.runtime.cpu import numba_available

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not installed")

SIGNATURES = """
def signatures(*modules):
    return {f"{m.__name__}.{n}": len(getattr(m, n).signatures) for m in modules for n in dir(m)
            if len(getattr(getattr(m, n), "signatures", ()) or ()) > 0}
"""

TRACKING = SIGNATURES + """
from memgs_ros.core.tracking import TrackerConfig, _compiled, make_tracker, warm_up
from memgs_ros.core.tracking.features import orb
from memgs_ros.io.synthetic import generate_frames, parse_spec

warm_up()
before = signatures(_compiled, orb)
assert before and all(v == 1 for v in before.values()), before
frames = list(generate_frames(parse_spec("synthetic:w=320,h=240,n=8,seed=4")))
tracker = make_tracker(TrackerConfig(mode="rgbd", ba_threaded=False), frames[0].camera)
for f in frames:
    tracker.track(f)
tracker.close()
after = signatures(_compiled, orb)
assert after == before, (before, after)
print("OK", sorted(before))
"""

# The tracker node's way: its frames are views on the messages, the depth the camera's 16-bit
# units read at the keypoints (a read-only array: a signature of its own unless warmed).
TRACKER_NODE = SIGNATURES + """
from memgs_ros.core.geometry import view
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.core.tracking import TrackerConfig, _compiled, make_tracker, warm_up
from memgs_ros.core.tracking.features import orb
from memgs_ros.io.image_decoding import depth_view, rgb_view
from memgs_ros.io.synthetic import generate_frames, parse_spec
from memgs_ros.ros import images

def depth_kernels():
    return {f"view._depth_kernels[{i}]": len(k.signatures) for i, k in enumerate(view._depth_kernels)}

frames = list(generate_frames(parse_spec("synthetic:w=320,h=240,n=8,seed=4")))
msgs = [(images.numpy_to_image(f.rgb, "rgb8", f.stamp_ns, "cam"),
         images.depth_to_image(f.depth_m, "16UC1", f.stamp_ns, "cam", 5000.0)) for f in frames]
warm_up()
before = {**signatures(_compiled, orb), **depth_kernels()}
assert before and all(v == 1 for v in before.values()), before
tracker = make_tracker(TrackerConfig(mode="rgbd", ba_threaded=False), frames[0].camera)
for f, (color, depth) in zip(frames, msgs):
    units = DepthUnits(*depth_view(depth, 5000.0))
    assert not units.raw.flags.writeable and units.has_valid()
    tracker.track(Frame(f.stamp_ns, rgb_view(color), units, f.camera))
tracker.close()
after = {**signatures(_compiled, orb), **depth_kernels()}
assert after == before, (before, after)
print("OK", sorted(before))
"""

MAPPING = SIGNATURES + """
import numpy as np, torch
from memgs_ros.core.mapping import losses
from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
from memgs_ros.core.metrics import _ssim_numba
from memgs_ros.core.raster import _composite_kernels, _projection_kernels, warm_up
from memgs_ros.io.synthetic import generate_frames, parse_spec
from frame_seeds import grid_seeds

warm_up("cpu", "numba")
losses.warm_up("cpu")
before = signatures(_composite_kernels, _projection_kernels, _ssim_numba)
assert before and all(v == 1 for v in before.values()), before
frames = list(generate_frames(parse_spec("synthetic:w=160,h=120,n=4,seed=4")))
m = GaussianMapper(MappingConfig(min_keyframes=1, raster_backend="numba"))
for i, f in enumerate(frames):
    m.add_keyframe(i, f.stamp_ns, f.T_wc_gt, f.rgb, f.depth_m, f.camera, *grid_seeds(f, 4))
for _ in range(12):
    m.step()
with torch.no_grad():
    m.render(frames[0].T_wc_gt, m.keyframes.all()[0].camera)
assert np.isfinite(m.gmap.means.detach().numpy()).all()
after = signatures(_composite_kernels, _projection_kernels, _ssim_numba)
assert after == before, (before, after)
print("OK", sorted(before))
"""


@pytest.mark.parametrize("check", [TRACKING, TRACKER_NODE, MAPPING], ids=["tracking", "tracker_node", "mapping"])
def test_a_run_compiles_nothing_after_the_warm_up(check: str) -> None:
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(check)], capture_output=True, text=True,
                          timeout=600, cwd=Path(__file__).resolve().parents[1])  # test/: its helpers (frame_seeds)
    assert proc.returncode == 0 and proc.stdout.startswith("OK"), proc.stdout[-2000:] + proc.stderr[-3000:]
