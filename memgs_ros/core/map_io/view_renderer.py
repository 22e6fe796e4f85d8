"""Views of a map held as records, rendered on a thread of their own (the merger's view requests).

The merger's executor must keep taking deltas while a view renders: the first request loads torch
and the rasterizer (seconds), and every render costs tens of milliseconds more. :class:`ViewRenderer`
is an actor (:class:`CommandWorker`): requests queue to its one thread, which alone holds the
render inputs of the last map version it was given (torch tensors, no training state).
Importing this module does not import torch; the worker loads it on its first render.
"""
from __future__ import annotations

from collections.abc import Hashable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from memgs_ros.core.gaussians.records import GaussianRecords
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.runtime.worker import CommandWorker

if TYPE_CHECKING:
    from memgs_ros.core.raster import Gaussians

__all__ = ["RenderedView", "ViewRenderer"]


@dataclass(frozen=True)
class RenderedView:
    """One rendered view. rgb: [H, W, 3] uint8; depth_m: [H, W] float32 metres along the axis."""

    stamp_ns: int
    rgb: np.ndarray
    depth_m: np.ndarray


class ViewRenderer(CommandWorker):
    """Renders views of a map at ``camera``'s size with SH degree ``sh_degree``.

    ``render`` queues a request; one still queued when a newer one comes is dropped (its future
    cancelled): a viewer wants the latest view, and renders must not pile up behind a slow one.
    """

    def __init__(self, camera: PinholeCamera, sh_degree: int = 3) -> None:
        super().__init__("view_renderer")
        self.camera = camera
        self.sh_degree = sh_degree
        self._cache: tuple[Hashable, Gaussians] | None = None  # worker thread only
        self._cache_bytes = 0  # an int the worker replaces: read from any thread
        self.start()

    @property
    def cache_bytes(self) -> int:
        """Bytes of the render inputs held for the last map version rendered."""
        return self._cache_bytes

    def render(self, records: GaussianRecords, version: Hashable, T_wc: np.ndarray,  # [4, 4]
               stamp_ns: int) -> Future[RenderedView]:
        """Render ``records`` (never modified afterwards: the inputs share their memory) seen from
        camera-to-world ``T_wc``; ``version`` names the map so its inputs are built once."""
        stale = self._drop_queued(lambda cmd: cmd.name == "render")
        if stale is not None:
            stale.future.cancel()
        return self.submit("render", lambda: self._render(records, version, T_wc, stamp_ns))

    def _render(self, records: GaussianRecords, version: Hashable, T_wc: np.ndarray, stamp_ns: int) -> RenderedView:
        import torch

        from memgs_ros.core.gaussians.gaussian_map import render_tensors
        from memgs_ros.core.raster import rasterize

        if self._cache is None or self._cache[0] != version:
            inputs = render_tensors(records)
            self._cache = (version, inputs)
            self._cache_bytes = sum(t.numel() * t.element_size() for t in inputs)
        T_cw = torch.from_numpy(np.linalg.inv(T_wc)).float()
        with torch.no_grad():
            out = rasterize(self._cache[1], T_cw, self.camera, sh_degree=self.sh_degree)
        rgb = (out.color.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        return RenderedView(stamp_ns, np.ascontiguousarray(rgb), out.depth.numpy().astype(np.float32))
