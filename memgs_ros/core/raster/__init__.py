"""Differentiable Gaussian rasterization (project -> bin into tiles -> composite).

``rasterize`` is the one entry point: :class:`Gaussians` in, :class:`RenderOutput` out, on the
backend the registry (:mod:`.backends`) picks or the caller names. The torch backend runs anywhere (CPU tests, CUDA
users without gsplat): projection and SH are plain autograd (O(N)); compositing is a custom
autograd Function over small tiles (:mod:`.composite`) whose memory is 8 B per pixel-Gaussian
pair. ``_rasterize_reference`` (:mod:`.reference`) is its brute-force twin for tests; gsplat
(:mod:`.gsplat_backend`) is an optional CUDA backend behind the same signature. With the
numba compositor, projection and SH run compiled as well (:mod:`.projection_numba`, twin of
:func:`.projection.project_gaussians`).

On a small shared CPU call :func:`memgs_ros.core.runtime.cpu.configure_cpu_runtime` once from the
entry point: it keeps freed memory in the heap and sets torch to one intra-op thread, which
makes the compositor spread its chunks over Python threads (one per core, up to 4).
"""
from __future__ import annotations

import torch
from torch import Tensor

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.raster.backend_choice import choose_backend
from memgs_ros.core.raster.backends import REGISTRY
from memgs_ros.core.raster.reference import _rasterize_reference
from memgs_ros.core.raster.values import RenderOutput
from memgs_ros.errors import ConfigError

__all__ = ["Gaussians", "RenderOutput", "_rasterize_reference", "rasterize", "warm_up"]


def rasterize(
    gaussians: Gaussians,
    T_cw: Tensor,  # [4, 4]
    camera: PinholeCamera,
    sh_degree: int,
    background: Tensor | None = None,  # [3]
    near: float = 0.01,
    backend: str = "auto",
) -> RenderOutput:
    """Render N Gaussians into ``camera`` (undistorted; its width/height are the output size).

    gaussians: the raw parameters (:class:`Gaussians`: means [N, 3], quats_wxyz [N, 4],
    log_scales [N, 3], opacity_logits [N, 1], sh_dc [N, 1, 3], sh_rest [N, K, 3]); T_cw: [4, 4]
    world-to-camera; sh_degree: active degree (bands above it are ignored); background: [3]
    (black when None); near: camera-z culling plane in metres; backend: "auto" (gsplat when
    importable and the tensors are on CUDA, else numba when importable and they are on the CPU,
    else torch) or a name in the registry (:mod:`.backends`: "torch", the pure torch compositor;
    "numba", the compiled per-pixel CPU compositor; "gsplat"). MEMGS_DISABLE_NUMBA=1 makes numba
    count as not importable.

    Returns a :class:`RenderOutput` (color [3, H, W], depth [H, W], alpha [H, W], means2d [N, 2],
    radii [N], visible [N]). Differentiable w.r.t. every Gaussian tensor, T_cw and background.
    """
    gaussians.check(sh_degree)
    means = gaussians.means
    if tuple(T_cw.shape) != (4, 4):
        raise ValueError(f"rasterize: T_cw must have shape [4, 4], got {list(T_cw.shape)}")
    if T_cw.device != means.device:
        raise ValueError(f"rasterize: T_cw is on {T_cw.device}, means on {means.device}")
    if background is not None and tuple(background.shape) != (3,):
        raise ValueError(f"rasterize: background must have shape [3], got {list(background.shape)}")
    if backend != "auto" and backend not in REGISTRY:
        raise ValueError(f"rasterize: backend must be one of {('auto', *REGISTRY)}, got {backend!r}")
    if backend != "auto" and (why := REGISTRY[backend].why_not(means.device)):
        raise ConfigError(f"rasterize: backend '{backend}' was asked for but {why}")
    T_cw = T_cw.to(means.dtype)
    if background is not None:
        background = background.to(device=means.device, dtype=means.dtype)
    chosen = REGISTRY[choose_backend(means.device, backend).backend]
    return chosen.render(gaussians, T_cw, camera, sh_degree, background, near)


def warm_up(device: torch.device | str = "cpu", backend: str = "auto", sh_degree: int = 3) -> None:
    """Render a tiny scene forward and backward once, so that the compiled kernels are loaded
    (numba: ~0.5 s from its cache, ~7 s when compiling) before the first real step, and a
    process's memory after start-up includes its code (the mapper's memory baseline)."""
    dev = torch.device(device)
    n, k = 8, (sh_degree + 1) ** 2 - 1
    gen = torch.Generator().manual_seed(0)
    means = (torch.randn(n, 3, generator=gen) * 0.2 + torch.tensor([0.0, 0.0, 2.0])).to(dev)
    params = [means, torch.randn(n, 4, generator=gen).to(dev), torch.full((n, 3), -2.5, device=dev),
              torch.zeros(n, 1, device=dev), torch.rand(n, 1, 3, generator=gen).to(dev),
              torch.zeros(n, k, 3, device=dev)]
    for t in params:
        t.requires_grad_(True)
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    out = rasterize(Gaussians(*params), torch.eye(4, device=dev), cam, sh_degree, backend=backend)
    (out.color.sum() + out.depth.sum()).backward()
