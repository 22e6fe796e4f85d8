"""Structural similarity (SSIM) as used by the mapping loss and the evaluation (reference sec. 5, 7).

Gaussian window 11x11, sigma 1.5, C1 = (0.01 L)^2, C2 = (0.03 L)^2 with data range L (1 for
images in [0, 1]). Borders use zero padding with 'same' output size, as the 3DGS training code
does, so the map has the image's size and every pixel contributes to the loss; near the border
the local statistics are therefore biased towards zero (the evaluation numbers in the 3DGS
family are computed this way, so we keep it for comparability).

:func:`ssim_map` has two fast paths, both with a hand-written backward, and one plain twin:

- CPU with numba (:func:`memgs_ros.core.runtime.cpu.numba_available`), float32/float64: compiled
  kernels (:mod:`memgs_ros.core.metrics._ssim_numba`) that filter the five local statistics
  (x1, x2, x1^2, x2^2, x1 x2) row by row through a ring of K rows, compute the map and the
  per-pixel factors of the backward pass in the same sweep, and get the image gradients in one
  more sweep over 3-4 factor planes. About 3.5x cheaper than the torch path at 320x240x3
  (benchmarks/bench_ssim.py).
- Otherwise (CUDA, no numba, half precision): the same statistics in one grouped, separable
  torch convolution (a 1xK pass then a Kx1 pass), backward one more grouped filter.
- The plain twin :func:`_ssim_map` uses an explicit KxK window per statistic and autograd;
  tests compare all three, forward and backward.
"""
from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.errors import ConfigError

__all__ = ["gaussian_window_1d", "ssim", "ssim_map"]

_REDUCTIONS = ("mean", "per_image", "none")


@functools.lru_cache(maxsize=32)
def gaussian_window_1d(window_size: int, sigma: float, dtype: torch.dtype,
                       device: torch.device) -> torch.Tensor:
    """Normalised 1-D Gaussian window: [window_size]. Cached per (size, sigma, dtype, device).

    The returned tensor is shared between callers: treat it as read-only.
    """
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"SSIM window_size must be a positive odd integer, got {window_size}")
    if not sigma > 0:
        raise ValueError(f"SSIM sigma must be positive, got {sigma}")
    x = torch.arange(window_size, dtype=torch.float64) - (window_size - 1) / 2.0
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _check_pair(img1: torch.Tensor, img2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Validate two images and lift them to [B, C, H, W]; returns (a, b, was_batched)."""
    assert img1.shape == img2.shape, f"SSIM inputs differ in shape: {tuple(img1.shape)} vs {tuple(img2.shape)}"
    assert img1.dim() in (3, 4), f"SSIM expects [C, H, W] or [B, C, H, W], got {tuple(img1.shape)}"
    assert img1.is_floating_point() and img2.is_floating_point(), (
        f"SSIM expects floating-point images, got {img1.dtype} and {img2.dtype}")
    assert img1.device == img2.device, f"SSIM inputs on different devices: {img1.device} vs {img2.device}"
    batched = img1.dim() == 4
    if not batched:
        img1, img2 = img1.unsqueeze(0), img2.unsqueeze(0)
    dtype = torch.promote_types(img1.dtype, img2.dtype)
    return img1.to(dtype).contiguous(), img2.to(dtype).contiguous(), batched


def _ssim_from_stats(mu1: torch.Tensor, mu2: torch.Tensor, e11: torch.Tensor, e22: torch.Tensor,
                     e12: torch.Tensor, c1: float, c2: float) -> torch.Tensor:
    """SSIM map from local means and second moments (all [B, C, H, W])."""
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    var1 = e11 - mu1_sq
    var2 = e22 - mu2_sq
    cov12 = e12 - mu12
    num = (2.0 * mu12 + c1) * (2.0 * cov12 + c2)
    den = (mu1_sq + mu2_sq + c1) * (var1 + var2 + c2)
    return num / den


def _filter(x: torch.Tensor,  # [B, n, H, W]
            k: torch.Tensor,  # [K] symmetric, normalised
            ) -> torch.Tensor:
    """Separable Gaussian filter of every plane, zero 'same' padding: [B, n, H, W].

    One grouped conv per direction over all n planes. Zero padding in each 1-D pass equals
    zero padding of the full 2-D window (a zero row stays zero after the row pass). Because
    the window is symmetric, this filter is its own adjoint, which the backward pass uses.
    """
    n, K = x.shape[1], k.numel()
    pad = K // 2
    if x.device.type == "cpu":
        # oneDNN's grouped conv is ~2.7x faster forward+backward in channels-last layout on
        # CPU (measured 37 ms vs 99 ms for 15 planes of 640x480); CUDA keeps the default layout.
        x = x.contiguous(memory_format=torch.channels_last)
    y = F.conv2d(x, k.view(1, 1, 1, K).expand(n, 1, 1, K), padding=(0, pad), groups=n)
    y = F.conv2d(y, k.view(1, 1, K, 1).expand(n, 1, K, 1), padding=(pad, 0), groups=n)
    # Back to the default layout: per-pixel arithmetic is slower on channel-strided views.
    return y.contiguous()


class _SsimMapFunction(torch.autograd.Function):
    """SSIM map with a hand-written backward (torch path of :func:`ssim_map`: CUDA, or CPU
    without numba).

    With S = A B / (C D), A = 2 mu1 mu2 + c1, B = 2 cov12 + c2, C = mu1^2 + mu2^2 + c1,
    D = var1 + var2 + c2 and g = dL/dS per pixel:
      dL/dmu1 = g 2 (mu2 (B - A) / (C D) - mu1 S (1/C - 1/D)),   dL/dE[x1^2] = -g S / D,
      dL/dE[x1 x2] = g 2 A / (C D);  and symmetrically for image 2.
    The image gradient is the (self-adjoint) filter applied to those maps:
      v_img1 = G*(dL/dmu1) + 2 img1 G*(dL/dE[x1^2]) + img2 G*(dL/dE[x1 x2]).
    So backward is one grouped filter over 3 planes per channel (4 when both images need
    gradients) instead of autograd's graph through 5 planes and ~20 elementwise ops.
    Not twice differentiable.
    """

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, a: torch.Tensor, b: torch.Tensor,
                k: torch.Tensor, c1: float, c2: float) -> torch.Tensor:
        C = a.shape[1]
        mu1, mu2, e11, e22, e12 = _filter(torch.cat([a, b, a * a, b * b, a * b], dim=1), k).split(C, dim=1)
        mu12 = mu1 * mu2
        mu1_sq, mu2_sq = mu1 * mu1, mu2 * mu2
        num_l = 2.0 * mu12 + c1  # A
        num_cs = 2.0 * (e12 - mu12) + c2  # B
        den_l = mu1_sq + mu2_sq + c1  # C
        den_cs = (e11 - mu1_sq) + (e22 - mu2_sq) + c2  # D
        s = num_l * num_cs / (den_l * den_cs)
        ctx.save_for_backward(a, b, k, mu1, mu2, num_l, num_cs, den_l, den_cs, s)
        return s

    @staticmethod
    def backward(ctx: Any,  # type: ignore[override]
                 v_s: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        a, b, k, mu1, mu2, num_l, num_cs, den_l, den_cs, s = ctx.saved_tensors
        need_a, need_b = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (need_a or need_b):
            return None, None, None, None, None
        C = a.shape[1]
        inv_cd = 1.0 / (den_l * den_cs)
        t = (num_cs - num_l) * inv_cd
        u = s * (1.0 / den_l - 1.0 / den_cs)
        maps = []
        if need_a:
            maps.append(v_s * 2.0 * (mu2 * t - mu1 * u))  # dL/dmu1
        if need_b:
            maps.append(v_s * 2.0 * (mu1 * t - mu2 * u))  # dL/dmu2
        maps.append(-v_s * s / den_cs)  # dL/dE[x1^2] = dL/dE[x2^2]
        maps.append(v_s * 2.0 * num_l * inv_cd)  # dL/dE[x1 x2]
        filt = list(_filter(torch.cat(maps, dim=1), k).split(C, dim=1))
        f_e12, f_sq = filt.pop(), filt.pop()
        v_a = v_b = None
        if need_a:
            v_a = filt.pop(0) + 2.0 * a * f_sq + b * f_e12
        if need_b:
            v_b = filt.pop(0) + 2.0 * b * f_sq + a * f_e12
        return v_a, v_b, None, None, None


class _SsimMapNumbaFunction(torch.autograd.Function):
    """SSIM map from the compiled kernels of :mod:`memgs_ros.core.metrics._ssim_numba` (CPU path of
    :func:`ssim_map` when numba is available; twins: :class:`_SsimMapFunction`, :func:`_ssim_map`).

    Forward is one sweep per plane giving the map and, when an image needs a gradient, the
    per-pixel factors dS/dE[x1^2], dS/dE[x1 x2], dS/dmu1 and/or dS/dmu2 (4 B per pixel and
    factor in float32); backward is one sweep over the cotangent times those factors.
    Only the gradients asked for are computed. Not twice differentiable.
    """

    @staticmethod
    def forward(ctx: Any, a: torch.Tensor,  # [B, C, H, W] contiguous, CPU, float32 or float64
                b: torch.Tensor,  # [B, C, H, W] same dtype
                k: torch.Tensor,  # [K] symmetric window, same dtype
                c1: float, c2: float) -> torch.Tensor:  # [B, C, H, W]
        from memgs_ros.core.metrics import _ssim_numba as kern

        B, C, H, W = a.shape
        need_a, need_b = bool(ctx.needs_input_grad[0]), bool(ctx.needs_input_grad[1])
        n_fac = 2 + int(need_a) + int(need_b) if (need_a or need_b) else 1  # 1: unused placeholder
        s = torch.empty(B * C, H, W, dtype=a.dtype)  # [P, H, W], P = B C planes
        fac = torch.empty(B * C if need_a or need_b else 1, n_fac, H, W, dtype=a.dtype)  # [P, F, H, W]
        kern.ssim_forward(a.detach().view(B * C, H, W).numpy(), b.detach().view(B * C, H, W).numpy(),
                          k.numpy(), np.array([c1, c2], dtype=k.numpy().dtype), s.numpy(), fac.numpy(),
                          need_a, need_b)
        if need_a or need_b:
            ctx.save_for_backward(a, b, k, fac)
        return s.view(B, C, H, W)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, v_s: torch.Tensor  # [B, C, H, W]
                 ) -> tuple[torch.Tensor | None, ...]:
        from memgs_ros.core.metrics import _ssim_numba as kern

        need_a, need_b = bool(ctx.needs_input_grad[0]), bool(ctx.needs_input_grad[1])
        if not (need_a or need_b):
            return None, None, None, None, None
        a, b, k, fac = ctx.saved_tensors
        B, C, H, W = a.shape
        P = B * C
        v_s = v_s.to(a.dtype).contiguous().view(P, H, W)
        v_a = torch.empty(P if need_a else 1, H, W, dtype=a.dtype)  # [P, H, W]
        v_b = torch.empty(P if need_b else 1, H, W, dtype=a.dtype)  # [P, H, W]
        kern.ssim_backward(a.detach().view(P, H, W).numpy(), b.detach().view(P, H, W).numpy(),
                           k.numpy(), fac.numpy(), v_s.numpy(), need_a, need_b, v_a.numpy(), v_b.numpy())
        return (v_a.view(B, C, H, W) if need_a else None, v_b.view(B, C, H, W) if need_b else None,
                None, None, None)


def _use_numba(a: torch.Tensor) -> bool:
    """Whether :func:`ssim_map` takes the compiled path for this (lifted) input."""
    return a.device.type == "cpu" and a.dtype in (torch.float32, torch.float64) and numba_available()


def ssim_map(img1: torch.Tensor,  # [B, C, H, W] or [C, H, W]
             img2: torch.Tensor,  # same shape as img1
             window_size: int = 11, sigma: float = 1.5, c1: float = 0.01 ** 2,
             c2: float = 0.03 ** 2, data_range: float = 1.0) -> torch.Tensor:
    """Per-pixel SSIM (fast path; plain twin: :func:`_ssim_map`).

    img1, img2: [B, C, H, W] or [C, H, W], floating point, same device.
    c1, c2 are the constants for data range 1; they are scaled by ``data_range**2``.
    Returns the SSIM map with the input's shape: [B, C, H, W] or [C, H, W]. Differentiable
    in both images (once: the backward is hand-written). Computed by the numba kernels on CPU
    (float32/float64, numba available: :class:`_SsimMapNumbaFunction`), otherwise by grouped
    torch convolutions (:class:`_SsimMapFunction`).
    """
    return _fast_ssim_map(img1, img2, window_size, sigma, c1, c2, data_range, compiled=None)


def _fast_ssim_map(img1: torch.Tensor,  # [B, C, H, W] or [C, H, W]
                   img2: torch.Tensor,  # same shape as img1
                   window_size: int, sigma: float, c1: float, c2: float, data_range: float,
                   *, compiled: bool | None) -> torch.Tensor:  # same shape as img1
    """:func:`ssim_map` on a chosen path: compiled True (numba kernels), False (torch
    convolutions) or None (numba where :func:`_use_numba` allows). Benchmarks compare the two."""
    a, b, batched = _check_pair(img1, img2)
    if compiled is None:
        compiled = _use_numba(a)
    elif compiled and not _use_numba(a):
        raise ConfigError(f"SSIM: the numba path needs numba and a float32/float64 CPU tensor, "
                          f"got {a.dtype} on {a.device} (numba available: {numba_available()})")
    k = gaussian_window_1d(int(window_size), float(sigma), a.dtype, a.device)
    scale = float(data_range) ** 2
    fn = _SsimMapNumbaFunction if compiled else _SsimMapFunction
    out = fn.apply(a, b, k, c1 * scale, c2 * scale)
    return out if batched else out.squeeze(0)


def _ssim_map(img1: torch.Tensor,  # [B, C, H, W] or [C, H, W]
              img2: torch.Tensor,  # same shape as img1
              window_size: int = 11, sigma: float = 1.5, c1: float = 0.01 ** 2,
              c2: float = 0.03 ** 2, data_range: float = 1.0) -> torch.Tensor:
    """Reference SSIM map with an explicit 2-D window per channel and statistic (slow twin of
    :func:`ssim_map`; same arguments and result)."""
    a, b, batched = _check_pair(img1, img2)
    C = a.shape[1]
    k = gaussian_window_1d(int(window_size), float(sigma), a.dtype, a.device)
    w2d = torch.outer(k, k).expand(C, 1, window_size, window_size)  # [C, 1, K, K]
    pad = window_size // 2

    def filt(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(x, w2d, padding=pad, groups=C)

    scale = float(data_range) ** 2
    out = _ssim_from_stats(filt(a), filt(b), filt(a * a), filt(b * b), filt(a * b),
                           c1 * scale, c2 * scale)
    return out if batched else out.squeeze(0)


def ssim(img1: torch.Tensor,  # [B, C, H, W] or [C, H, W]
         img2: torch.Tensor,  # same shape as img1
         window_size: int = 11, sigma: float = 1.5, c1: float = 0.01 ** 2, c2: float = 0.03 ** 2,
         data_range: float = 1.0, reduction: str = "mean") -> torch.Tensor:
    """SSIM between two images (reference sec. 5: 11x11 Gaussian window, sigma 1.5).

    img1, img2: [B, C, H, W] or [C, H, W] floating point in [0, data_range].
    reduction: "mean" -> scalar [] over everything; "per_image" -> [B] (or [] for an unbatched
    input); "none" -> the map, same shape as the input. Differentiable in both images.
    """
    if reduction not in _REDUCTIONS:
        raise ValueError(f"SSIM reduction must be one of {_REDUCTIONS}, got {reduction!r}")
    m = ssim_map(img1, img2, window_size, sigma, c1, c2, data_range)
    if reduction == "none":
        return m
    if reduction == "mean":
        return m.mean()
    return m.flatten(start_dim=m.dim() - 3).mean(dim=-1)
