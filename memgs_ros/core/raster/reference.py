"""Brute-force reference rasterizer: every pixel against every Gaussian, plain autograd.

Twin of :func:`memgs_ros.core.raster.composite.composite` / :func:`memgs_ros.core.raster.rasterize`
with the same semantics (1/255 skip, 0.99 clamp, early termination at T < 1e-4, depth-sorted
front-to-back, power clamped at 0), but no tiles, no chunks and no hand-written gradient.
Memory is O(H W N): for tests on small images only.
"""
from __future__ import annotations

import torch
from torch import Tensor

from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.raster.projection import project_gaussians, screen_radii
from memgs_ros.core.raster.rules import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE
from memgs_ros.core.raster.values import RenderOutput, Splats2D


def _composite_reference(
    splats: Splats2D,
    background: Tensor,  # [3]
    active: Tensor,  # [N] bool
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Reference compositing. Returns color [3, H, W], depth [H, W], alpha [H, W], hit [N] bool.

    splats: the projected Gaussians; background: [3]; active: [N] bool (Gaussians allowed to contribute, e.g. in front).
    ``hit`` marks Gaussians with alpha >= 1/255 at some pixel.
    """
    means2d, conics, opacities, colors, depths = splats
    dtype, device = means2d.dtype, means2d.device
    idx = torch.nonzero(active).squeeze(1)
    idx = idx[torch.argsort(depths.detach()[idx], stable=True)]  # [G] front to back
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # [HW, 2]
    d = pix[:, None, :] - means2d[idx][None, :, :]  # [HW, G, 2]
    a, b, c = conics[idx].unbind(-1)  # [G] each
    dx, dy = d[..., 0], d[..., 1]
    power = -0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)  # [HW, G]
    power = power.clamp(max=0.0)
    alpha = torch.clamp(opacities[idx] * torch.exp(power), max=MAX_ALPHA)  # [HW, G]
    alpha = torch.where(alpha >= MIN_ALPHA, alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        keep = torch.cumprod(1.0 - alpha, dim=1) >= MIN_TRANSMITTANCE  # [HW, G]
    alpha = alpha * keep
    trans = torch.cumprod(1.0 - alpha, dim=1)  # [HW, G] inclusive
    ones = torch.ones_like(trans[:, :1])
    t_before = torch.cat([ones, trans[:, :-1]], dim=1)  # [HW, G] exclusive
    t_end = trans[:, -1] if trans.shape[1] > 0 else ones[:, 0]  # [HW]
    w = alpha * t_before  # [HW, G]
    color = w @ colors[idx] + t_end[:, None] * background.to(dtype)  # [HW, 3]
    depth = w @ depths[idx]  # [HW]
    hit = torch.zeros(means2d.shape[0], dtype=torch.bool, device=device)
    hit[idx] = (alpha.detach() > 0).any(dim=0)
    return (
        color.T.reshape(3, height, width),
        depth.reshape(height, width),
        (1.0 - t_end).reshape(height, width),
        hit,
    )


def _rasterize_reference(gaussians: Gaussians, T_cw: Tensor, camera: PinholeCamera, sh_degree: int,
                         background: Tensor | None = None, near: float = 0.01) -> RenderOutput:
    """Reference twin of :func:`memgs_ros.core.raster.rasterize` (torch backend), for tests.

    Same arguments and :class:`RenderOutput`; ``visible`` is "alpha >= 1/255 at some pixel".
    """
    means = gaussians.means
    proj = project_gaussians(gaussians, T_cw, camera, sh_degree, near)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    if background is None:
        background = torch.zeros(3, dtype=means.dtype, device=means.device)
    color, depth, alpha, hit = _composite_reference(
        proj.splats(),
        background,
        proj.in_front,
        camera.width,
        camera.height,
    )
    radii = torch.where(hit, screen_radii(proj.cov2d), torch.zeros_like(hit, dtype=torch.int32))
    return RenderOutput(color=color, depth=depth, alpha=alpha, means2d=proj.means2d, radii=radii, visible=hit)
