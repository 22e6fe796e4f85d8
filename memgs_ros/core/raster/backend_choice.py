"""Which device the mapper takes and which rasterizer ``backend="auto"`` runs on it.

One place for the choice: :func:`memgs_ros.core.raster.rasterize` makes it with
:func:`choose_backend`, ``memgs doctor`` reports it and the mapper node logs it at start-up
(gsplat on CUDA when importable, numba on the CPU when importable, else the torch compositor).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from memgs_ros.core.raster.gsplat_backend import gsplat_available
from memgs_ros.core.runtime import numba_available

__all__ = ["BackendChoice", "choose_backend", "device_label", "resolve_device"]


@dataclass(frozen=True)
class BackendChoice:
    """The rasterizer a device gets.

    device: the torch device string; backend: "gsplat", "numba" or "torch"; requested: what the
    config asked for ("auto" or a backend name); fallback_warning: ``auto`` on CUDA found no
    gsplat and fell back to the torch compositor, several times slower (README "On a Jetson").
    """

    device: str
    backend: str
    requested: str
    fallback_warning: bool


def resolve_device(requested: str = "auto") -> str:
    """The torch device for the mapper's ``device`` parameter: ``auto`` is CUDA when torch sees one."""
    if requested != "auto":
        return requested
    return "cuda" if torch.cuda.is_available() else "cpu"


def choose_backend(device: str | torch.device, requested: str = "auto") -> BackendChoice:
    """The backend ``rasterize(..., backend=requested)`` uses for tensors on ``device``.

    A named backend is taken as asked (``rasterize`` refuses one that cannot run there).
    """
    dev = torch.device(device)
    if requested != "auto":
        return BackendChoice(str(dev), requested, requested, fallback_warning=False)
    on_cuda = dev.type == "cuda"
    if on_cuda and gsplat_available():
        backend = "gsplat"
    elif not on_cuda and numba_available():
        backend = "numba"
    else:
        backend = "torch"
    return BackendChoice(str(dev), backend, requested, fallback_warning=on_cuda and backend == "torch")


def device_label(device: str | torch.device) -> str:
    """``cpu``, or ``cuda (NVIDIA Orin)``: the device with its CUDA name, for logs and reports."""
    dev = torch.device(device)
    if dev.type != "cuda" or not torch.cuda.is_available():
        return str(dev)
    return f"{dev} ({torch.cuda.get_device_name(dev)})"
