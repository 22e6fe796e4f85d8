"""Which device the mapper takes and which rasterizer ``backend="auto"`` runs on it.

One place for the choice: :func:`memgs_ros.core.raster.rasterize` makes it with
:func:`choose_backend` (the registry's ``auto`` order, :mod:`.backends`: gsplat on CUDA when
importable, numba on the CPU when importable, else the torch compositor), ``memgs doctor``
reports it and the mapper node logs it at start-up.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from memgs_ros.core.raster.backends import REGISTRY, auto_backend

__all__ = ["BackendChoice", "choose_backend", "device_label", "device_problem", "resolve_device"]

_INSTALL_GSPLAT = "pip install '.[gsplat]', or on a Jetson build it (README 'On a Jetson')"


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


def device_problem(device: str, backend: str = "auto") -> str:
    """Why a mapper with ``device`` and ``raster_backend`` cannot run here, in one line that names
    what to install or set; "" when it can. ``memgs run`` asks before any node starts, the mapper
    node at its start: a CPU-only torch or a missing gsplat is a line, not a node's traceback."""
    try:
        dev = torch.device(resolve_device(device))
    except RuntimeError:
        return f"mapper.device={device!r} is not a torch device (auto, cpu, cuda or cuda:N)"
    if dev.type == "cuda":
        if not torch.backends.cuda.is_built():
            return (f"mapper.device={device}: this torch ({torch.__version__}) is built without CUDA; install a "
                    "CUDA build of torch (on a Jetson NVIDIA's wheel, README 'On a Jetson') or set mapper.device=cpu")
        if not torch.cuda.is_available():
            return (f"mapper.device={device}: torch {torch.__version__} finds no CUDA device (driver, "
                    "CUDA_VISIBLE_DEVICES); or set mapper.device=cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            return f"mapper.device={device}: this machine has {torch.cuda.device_count()} CUDA device(s)"
    if backend == "auto":
        return ""
    entry = REGISTRY.get(backend)
    if entry is None:
        return f"mapping.raster_backend={backend!r}: no such rasterizer ({', '.join(['auto', *REGISTRY])})"
    why = entry.why_not(dev)
    if not why and backend.startswith("gsplat") and dev.type != "cuda":
        why = "gsplat renders on CUDA"
    if not why:
        return ""
    fix = _INSTALL_GSPLAT if why == "the gsplat package is not installed" else "or set mapping.raster_backend=auto"
    return f"mapping.raster_backend={backend} on {dev}: {why}; {fix}"


def choose_backend(device: str | torch.device, requested: str = "auto") -> BackendChoice:
    """The backend ``rasterize(..., backend=requested)`` uses for tensors on ``device``.

    A named backend is taken as asked (``rasterize`` refuses one that cannot run there).
    """
    dev = torch.device(device)
    if requested != "auto":
        return BackendChoice(str(dev), requested, requested, fallback_warning=False)
    backend = auto_backend(dev).name
    return BackendChoice(str(dev), backend, requested, fallback_warning=dev.type == "cuda" and backend == "torch")


def device_label(device: str | torch.device) -> str:
    """``cpu``, or ``cuda (NVIDIA Orin)``: the device with its CUDA name, for logs and reports."""
    dev = torch.device(device)
    if dev.type != "cuda" or not torch.cuda.is_available():
        return str(dev)
    return f"{dev} ({torch.cuda.get_device_name(dev)})"
