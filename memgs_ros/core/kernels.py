"""Every compiled kernel of the package, compiled (or loaded from numba's disk cache) in one go.

The nodes warm their own kernels at start (the tracker on a thread beside its executor, the
mapper on its session's worker) and report ``kernels_warm``; ``memgs run`` starts the player once
every node has. On a fresh install that first compile takes a while (a minute or so on 2 cores):
``memgs doctor --warm`` runs it ahead, once, into the cache (``NUMBA_CACHE_DIR``, by default
``~/.cache/memgs_ros/numba``; see ``memgs_ros/__init__.py``), so that no node pays it when frames
matter.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["KernelGroup", "numba_cache_dir", "warm_kernels"]


@dataclass(frozen=True)
class KernelGroup:
    """What one group of kernels took to load or compile."""

    name: str
    seconds: float
    error: str | None = None


def numba_cache_dir() -> str:
    """Where numba caches compiled kernels for this process."""
    return os.environ.get("NUMBA_CACHE_DIR", "")


def _tracking() -> None:
    from memgs_ros.core.tracking import warm_up

    warm_up()


def _rasterizer(device: str, backend: str) -> Callable[[], None]:
    def run() -> None:
        from memgs_ros.core.raster import warm_up

        warm_up(device, backend)
    return run


def _losses(device: str) -> Callable[[], None]:
    def run() -> None:
        from memgs_ros.core.mapping import losses

        losses.warm_up(device)
    return run


def warm_kernels(device: str = "cpu", raster_backend: str = "auto",
                 on_group: Callable[[KernelGroup], None] | None = None) -> list[KernelGroup]:
    """Compile or load every kernel the nodes run: the tracker's (ORB, matching, pose), the
    rasterizer's for ``device`` / ``raster_backend`` (numba on a CPU; gsplat's CUDA build on a
    GPU), SSIM's. A group that fails is reported (its ``error``), not raised: the others still
    warm. ``on_group`` is called after each group (progress)."""
    groups = [("tracker", _tracking), ("rasterizer", _rasterizer(device, raster_backend)),
              ("SSIM loss", _losses(device))]
    out = []
    for name, fn in groups:
        t0 = time.perf_counter()
        error = None
        try:
            fn()
        except Exception as err:  # noqa: BLE001 - one group's failure is reported with the others
            error = f"{type(err).__name__}: {err}"
        group = KernelGroup(name, round(time.perf_counter() - t0, 2), error)
        out.append(group)
        if on_group is not None:
            on_group(group)
    return out
