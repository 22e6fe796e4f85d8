"""Differentiable Gaussian rasterization (project -> bin into tiles -> composite).

``rasterize`` is the one entry point. The torch backend runs anywhere (CPU tests, CUDA
users without gsplat): projection and SH are plain autograd (O(N)); compositing is a custom
autograd Function over small tiles (:mod:`.composite`) whose memory is 8 B per pixel-Gaussian
pair. ``_rasterize_reference`` (:mod:`.reference`) is its brute-force twin for tests; gsplat
(:mod:`.gsplat_backend`) is an optional CUDA backend behind the same signature. With the
numba compositor, projection and SH run compiled as well (:mod:`.projection_numba`, twin of
:func:`.projection.project_gaussians`).

On a small shared CPU call :func:`memgs_ros.core.runtime.configure_cpu_runtime` once from the
entry point: it keeps freed memory in the heap and sets torch to one intra-op thread, which
makes the compositor spread its chunks over Python threads (one per core, up to 4).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from memgs_ros.core.camera import PinholeCamera
from memgs_ros.core.raster.backend_choice import choose_backend
from memgs_ros.core.raster.composite import composite as _composite  # keep the submodule name free
from memgs_ros.core.raster.gsplat_backend import gsplat_available, rasterize_gsplat
from memgs_ros.core.raster.numba_backend import NUMBA_TILE_SIZE, composite_numba
from memgs_ros.core.raster.projection import alpha_cutoff_sq, project_gaussians, screen_radii
from memgs_ros.core.raster.projection_numba import project_gaussians_numba
from memgs_ros.core.raster.reference import _rasterize_reference
from memgs_ros.core.raster.rules import MIN_ALPHA
from memgs_ros.core.raster.tiles import TILE_SIZE, build_tile_plan, pairs_per_chunk_for
from memgs_ros.core.runtime import numba_available
from memgs_ros.errors import ConfigError

__all__ = ["RenderOutput", "_rasterize_reference", "rasterize", "warm_up"]

BACKENDS = ("auto", "torch", "numba", "gsplat")


@dataclass(frozen=True)
class RenderOutput:
    """One rendered view.

    color: [3, H, W]; depth: [H, W] alpha-blended camera z, sum_i w_i z_i (not divided by
    alpha); alpha: [H, W] accumulated opacity; means2d: [N, 2] screen-space means whose
    ``.grad`` holds dL/d(means2d) after backward (densification statistic); radii: [N] int32
    3-sigma screen radius in px, 0 where not visible; visible: [N] bool, the Gaussian is in
    front of the camera and can reach alpha >= 1/255 inside the image.
    """

    color: Tensor
    depth: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    visible: Tensor


def _check_inputs(
    means: Tensor,
    quats_wxyz: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    sh_dc: Tensor,
    sh_rest: Tensor,
    T_cw: Tensor,
    sh_degree: int,
    background: Tensor | None,
    backend: str,
) -> None:
    n = means.shape[0]
    expected = {
        "means": (means, (n, 3)),
        "quats_wxyz": (quats_wxyz, (n, 4)),
        "log_scales": (log_scales, (n, 3)),
        "opacity_logits": (opacity_logits, (n, 1)),
        "sh_dc": (sh_dc, (n, 1, 3)),
        "T_cw": (T_cw, (4, 4)),
    }
    for name, (t, shape) in expected.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"rasterize: {name} must have shape {list(shape)}, got {list(t.shape)}")
        if t.device != means.device:
            raise ValueError(f"rasterize: {name} is on {t.device}, means on {means.device}")
    if sh_rest.dim() != 3 or sh_rest.shape[0] != n or sh_rest.shape[2] != 3:
        raise ValueError(f"rasterize: sh_rest must have shape [{n}, K, 3], got {list(sh_rest.shape)}")
    if not 0 <= sh_degree <= 3 or sh_rest.shape[1] < (sh_degree + 1) ** 2 - 1:
        raise ValueError(
            f"rasterize: sh_degree {sh_degree} needs 0..3 and sh_rest with >= {(sh_degree + 1) ** 2 - 1} "
            f"coefficients, got {sh_rest.shape[1]}"
        )
    if background is not None and tuple(background.shape) != (3,):
        raise ValueError(f"rasterize: background must have shape [3], got {list(background.shape)}")
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")


def rasterize(
    means: Tensor,  # [N, 3]
    quats_wxyz: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N, 1]
    sh_dc: Tensor,  # [N, 1, 3]
    sh_rest: Tensor,  # [N, K, 3]
    T_cw: Tensor,  # [4, 4]
    camera: PinholeCamera,
    sh_degree: int,
    background: Tensor | None = None,  # [3]
    near: float = 0.01,
    backend: str = "auto",
) -> RenderOutput:
    """Render N Gaussians into ``camera`` (undistorted; its width/height are the output size).

    means: [N, 3] world; quats_wxyz: [N, 4] unnormalised; log_scales: [N, 3];
    opacity_logits: [N, 1]; sh_dc: [N, 1, 3]; sh_rest: [N, K, 3], K = (deg_max + 1)^2 - 1
    (may be 0); T_cw: [4, 4] world-to-camera; sh_degree: active degree (bands above it are
    ignored); background: [3] (black when None); near: camera-z culling plane in metres;
    backend: "auto" (gsplat when importable and the tensors are on CUDA, else numba when
    importable and they are on the CPU, else torch), "torch" (the pure torch compositor),
    "numba" (the compiled per-pixel CPU compositor) or "gsplat". The environment variable
    MEMGS_DISABLE_NUMBA=1 makes numba count as not importable.

    Returns a :class:`RenderOutput` (color [3, H, W], depth [H, W], alpha [H, W], means2d [N, 2],
    radii [N], visible [N]). Differentiable w.r.t. means, quats, log_scales, opacity_logits,
    sh_dc, sh_rest, T_cw and background.
    """
    _check_inputs(means, quats_wxyz, log_scales, opacity_logits, sh_dc, sh_rest, T_cw, sh_degree, background, backend)
    T_cw = T_cw.to(means.dtype)
    if background is not None:
        background = background.to(device=means.device, dtype=means.dtype)
    if backend == "gsplat" and not gsplat_available():
        raise ConfigError("rasterize: backend 'gsplat' was asked for but the gsplat package is not installed")
    chosen = choose_backend(means.device, backend).backend
    if chosen == "gsplat":
        return rasterize_gsplat(
            means, quats_wxyz, log_scales, opacity_logits, sh_dc, sh_rest, T_cw, camera, sh_degree, background, near
        )

    use_numba = chosen == "numba"
    if backend == "numba" and (means.is_cuda or not numba_available()):
        why = "the tensors are on CUDA" if means.is_cuda else "numba is not importable (or MEMGS_DISABLE_NUMBA is set)"
        raise ConfigError(f"rasterize: backend 'numba' was asked for but {why}")

    # The compiled projection goes with the compiled compositor (same CPU, same dependency).
    project_fn = project_gaussians_numba if use_numba else project_gaussians
    proj = project_fn(
        means, quats_wxyz, log_scales, opacity_logits, sh_dc, sh_rest, T_cw, camera, sh_degree, near
    )
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    plan = build_tile_plan(
        proj.means2d,
        proj.cov2d,
        alpha_cutoff_sq(proj.opacities.detach(), MIN_ALPHA),
        proj.depths,
        proj.in_front,
        camera.width,
        camera.height,
        NUMBA_TILE_SIZE if use_numba else TILE_SIZE,
        pairs_per_chunk_for(means.device),  # only the torch compositor reads it
    )
    if background is None:
        background = torch.zeros(3, dtype=means.dtype, device=means.device)
    composite_fn = composite_numba if use_numba else _composite
    color, depth, alpha = composite_fn(
        proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths, background, plan
    )
    visible = plan.gaussian_hit
    radii = torch.where(visible, screen_radii(proj.cov2d), torch.zeros_like(visible, dtype=torch.int32))
    return RenderOutput(color=color, depth=depth, alpha=alpha, means2d=proj.means2d, radii=radii, visible=visible)


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
    means, quats, log_scales, opacity_logits, sh_dc, sh_rest = params
    out = rasterize(means, quats, log_scales, opacity_logits, sh_dc, sh_rest, torch.eye(4, device=dev), cam,
                    sh_degree, backend=backend)
    (out.color.sum() + out.depth.sum()).backward()
