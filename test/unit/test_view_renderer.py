"""The merger's view renderer without ROS: renders on its own thread, keeps the render inputs of
one map version, and drops a request that a newer one replaced before it ran."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from memgs_ros.core.gaussians.records import GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.map_io.view_renderer import ViewRenderer


def _wall(n: int = 200) -> GaussianRecords:
    """Gaussians on a wall 2 m in front of a camera at the origin looking down +z."""
    rng = np.random.default_rng(0)
    xyz = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), np.full(n, 2.0)], axis=1)
    return GaussianRecords.from_arrays(np.arange(n), xyz, rng.uniform(-1, 1, (n, 3)), np.zeros((n, 45)),
                                       np.full(n, 3.0), np.full((n, 3), -3.0), np.tile([1.0, 0, 0, 0], (n, 1)))


def test_renders_off_the_callers_thread_and_the_latest_request_wins() -> None:
    pytest.importorskip("torch")
    renderer = ViewRenderer(PinholeCamera(32, 24, 25.0, 25.0, 15.5, 11.5))
    try:
        gate = threading.Event()
        busy = renderer.submit("block", gate.wait)  # the worker is busy: the next requests queue
        records = _wall()
        replaced = renderer.render(records, "v1", np.eye(4), stamp_ns=1)
        latest = renderer.render(records, "v1", np.eye(4), stamp_ns=2)
        assert replaced.cancelled()  # a newer request came before it ran
        gate.set()
        assert busy.result(10)
        view = latest.result(120)  # the first render loads torch and the rasterizer
        assert view.stamp_ns == 2 and view.rgb.shape == (24, 32, 3) and view.rgb.dtype == np.uint8
        assert view.depth_m.shape == (24, 32) and view.depth_m.dtype == np.float32
        assert view.rgb.std() > 5.0 and np.nanmax(view.depth_m) == pytest.approx(2.0, abs=0.2)
        assert renderer.cache_bytes > 0
    finally:
        assert renderer.close()
