"""The mapping loss (reference section 5; paper Eq. 12 plus the RGB-D depth term).

    L = (1 - lambda) |I_r - I_gt|_1 + lambda (1 - SSIM(I_r, I_gt))
        + w_iso mean|s - mean_axis(s)| + w_depth |D_r - D_gt|_1 (valid depth pixels)

L1 terms are means over pixels (and channels); ``s`` are the activated scales exp(log_scales).
An optional validity mask ([H, W] bool, e.g. the pixels of an undistorted image that map inside
the source image) restricts the photometric means (L1 and the SSIM map) and the depth term to
valid pixels; without one every pixel counts.
"""
from __future__ import annotations

import torch

from memgs_ros.core.metrics.ssim import ssim, ssim_map


def _masked_mean(x: torch.Tensor,  # [C, H, W]
                 mask: torch.Tensor | None) -> torch.Tensor:  # [H, W] bool
    """Mean of ``x`` over the pixels where ``mask`` is True (all channels); plain mean without one."""
    if mask is None:
        return x.mean()
    w = mask.to(x.dtype)
    return (x * w).sum() / (w.sum() * x.shape[0]).clamp_min(1.0)


def photometric_loss(rendered: torch.Tensor,  # [3, H, W]
                     target: torch.Tensor,  # [3, H, W]
                     ssim_lambda: float = 0.2,
                     mask: torch.Tensor | None = None,  # [H, W] bool
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(1 - lambda) L1 + lambda (1 - SSIM), means over ``mask`` pixels when given.

    Returns (loss [], l1 [], ssim []).
    """
    assert rendered.shape == target.shape, f"rendered {tuple(rendered.shape)} vs target {tuple(target.shape)}"
    l1 = _masked_mean((rendered - target).abs(), mask)
    s = ssim(rendered, target) if mask is None else _masked_mean(ssim_map(rendered, target), mask)
    return (1.0 - ssim_lambda) * l1 + ssim_lambda * (1.0 - s), l1, s


def isotropic_loss(log_scales: torch.Tensor) -> torch.Tensor:  # [N, 3]
    """MonoGS-style isotropy: mean over Gaussians and axes of |s - mean_axis(s)|, s = exp(log_scales).

    Returns a scalar []; 0 for an empty map.
    """
    if log_scales.shape[0] == 0:
        return log_scales.sum() * 0.0
    s = torch.exp(log_scales)
    return (s - s.mean(dim=1, keepdim=True)).abs().mean()


def depth_l1_loss(rendered_depth: torch.Tensor,  # [H, W]
                  target_depth: torch.Tensor,  # [H, W]
                  mask: torch.Tensor | None = None) -> torch.Tensor:  # [H, W] bool
    """Mean |D_r - D_gt| over pixels whose target depth is finite and > 0 (and ``mask`` is True
    when given); 0 when none is valid."""
    assert rendered_depth.shape == target_depth.shape, (
        f"rendered depth {tuple(rendered_depth.shape)} vs target {tuple(target_depth.shape)}")
    valid = torch.isfinite(target_depth) & (target_depth > 0)
    if mask is not None:
        valid = valid & mask
    if not bool(valid.any()):
        return rendered_depth.sum() * 0.0
    return (rendered_depth[valid] - target_depth[valid]).abs().mean()


def mapping_loss(rendered: torch.Tensor,  # [3, H, W]
                 target: torch.Tensor,  # [3, H, W]
                 log_scales: torch.Tensor,  # [N, 3]
                 rendered_depth: torch.Tensor | None = None,  # [H, W]
                 target_depth: torch.Tensor | None = None,  # [H, W]
                 ssim_lambda: float = 0.2, iso_weight: float = 1.0,
                 depth_weight: float = 0.0,
                 mask: torch.Tensor | None = None,  # [H, W] bool
                 ) -> tuple[torch.Tensor, dict[str, float]]:
    """The full mapping loss. Returns (total [], terms) where terms holds floats for logging:
    ``l1``, ``ssim``, ``photometric``, ``iso``, ``depth`` (0 when not used) and ``total``.

    The depth term is used when ``depth_weight > 0`` and both depths are given. ``mask``: valid
    pixels for the photometric and depth terms (None: all).
    """
    photo, l1, s = photometric_loss(rendered, target, ssim_lambda, mask)
    total = photo
    iso = torch.zeros((), device=rendered.device)
    if iso_weight > 0:
        iso = isotropic_loss(log_scales)
        total = total + iso_weight * iso
    depth = torch.zeros((), device=rendered.device)
    if depth_weight > 0 and rendered_depth is not None and target_depth is not None:
        depth = depth_l1_loss(rendered_depth, target_depth, mask)
        total = total + depth_weight * depth
    terms = {"l1": float(l1.detach()), "ssim": float(s.detach()), "photometric": float(photo.detach()),
             "iso": float(iso.detach()),
             "depth": float(depth.detach()), "total": float(total.detach())}
    return total, terms


def warm_up(device: torch.device | str = "cpu") -> None:
    """Run the photometric loss forward and backward once on a tiny image, with and without a
    mask, so SSIM's compiled kernels (numba: ~0.7 s from its cache, ~4 s compiling) load at start,
    not inside the first training step."""
    gen = torch.Generator().manual_seed(0)
    rendered = torch.rand(3, 16, 16, generator=gen).to(device).requires_grad_(True)
    target = torch.rand(3, 16, 16, generator=gen).to(device)
    mask = torch.ones(16, 16, dtype=torch.bool, device=device)
    (photometric_loss(rendered, target)[0] + photometric_loss(rendered, target, mask=mask)[0]).backward()
