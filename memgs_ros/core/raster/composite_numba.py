"""Per-pixel CPU compositor compiled with numba (optional dependency), behind :func:`composite`'s signature.

Twin of :func:`memgs_ros.core.raster.composite.composite` (torch, dense padded tile chunks) and of
:func:`memgs_ros.core.raster.reference._composite_reference` (brute force): same rules, same
inputs and outputs, gradients w.r.t. every tensor input including the background.

Where the torch compositor evaluates every (pixel, Gaussian) pair of a padded chunk, this one
walks each pixel's front-to-back list and stops at its own early termination, visits only the
pixels where each Gaussian can reach alpha >= 1/255, and keeps two numbers per pixel (final T
and how many list entries were used) for a 3DGS-style back-to-front backward pass. Per-pair
gradients are summed per Gaussian afterwards, in a fixed order (deterministic).

Threads: the kernels release the GIL and each call takes a set of tiles, so tiles are spread
over Python threads (``cpu_threads()``: the cores in this process's affinity, up to 4), as the
torch compositor spreads its chunks. numba's own threading layers are not used: on 2 shared
cores its OpenMP layer made a 20k-Gaussian step ~15x slower whenever another process was busy
(a parallel region waits for its descheduled thread), and its workqueue layer may not be
entered from two Python threads at once, which the mapper and the view publisher do. Plain
Python threads have neither problem.
"""
from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch
from torch import Tensor

from memgs_ros.core.raster.composite_autograd import CompositeBackward, apply_compositor
from memgs_ros.core.raster.rules import MIN_ALPHA
from memgs_ros.core.raster.tiles import BIN_MARGIN, TilePlan
from memgs_ros.core.raster.values import Splats2D
from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.core.runtime.pool import cpu_threads, parallel_map
from memgs_ros.errors import ConfigError

__all__ = ["NUMBA_TILE_SIZE", "composite_numba"]

# px. Per-pixel early termination and per-Gaussian pixel boxes make list padding irrelevant;
# larger tiles mean fewer (tile, Gaussian) pairs to bin and reduce and longer runs per pixel
# row. Measured at 20k Gaussians, 320x240: compositor CPU 66 ms at 16 px, 79 ms at 8 px.
NUMBA_TILE_SIZE = 16

# Tile jobs per thread: interleaved tile sets of similar cost, several per thread so that a
# thread slowed by another process hands its share to the others.
JOBS_PER_THREAD = 4


def _tile_jobs(plan: TilePlan, threads: int) -> list[np.ndarray]:
    """The non-empty tiles as interleaved id sets ([T_k] int64 each), JOBS_PER_THREAD per thread."""
    tiles = np.flatnonzero(plan.tile_count.numpy())
    n_jobs = min(len(tiles), 1 if threads <= 1 else threads * JOBS_PER_THREAD)
    # contiguous: the kernels are compiled for one layout (a strided set compiled a second one)
    return [np.ascontiguousarray(tiles[k::n_jobs]) for k in range(n_jobs)]


def _run_tiles(kernel: Any, jobs: list[np.ndarray], threads: int, *args: Any) -> None:
    """kernel(tiles, *args) for every tile set in ``jobs``, on up to ``threads`` Python threads."""
    parallel_map(lambda tiles: kernel(tiles, *args), jobs, threads)


def _plan_args(table: Tensor, plan: TilePlan) -> tuple[Any, ...]:
    """The kernels' ``plan`` argument: the Gaussian table and the tile plan's arrays and sizes."""
    return (table.numpy(), plan.pair_gid.numpy(), plan.tile_start.numpy(), plan.tile_count.numpy(), plan.tiles_x,
            plan.tile_size, plan.width, plan.height)


def _kernels() -> Any:
    if not numba_available():
        raise ConfigError("rasterize: backend 'numba' was asked for but numba is not installed")
    from memgs_ros.core.raster import _composite_kernels

    return _composite_kernels


def _gaussian_table(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    depths: Tensor,  # [N]
) -> Tensor:
    """[N, 14] float64 rows (mean x, mean y, conic a, b, c, opacity, r, g, b, z,
    ln(1/255 / opacity), half width and half height of the alpha >= 1/255 box, exp(-a))."""
    f64 = torch.float64
    conics = conics.detach().to(f64)
    op = opacities.detach().to(f64)
    a, b, c = conics.unbind(-1)
    det = (a * c - b * b).clamp_min(1e-300)
    r2 = 2.0 * torch.log(op.clamp_min(1e-300) / MIN_ALPHA) * (BIN_MARGIN * BIN_MARGIN)
    ok = r2 > 0
    half_x = torch.where(ok, torch.sqrt(r2.clamp_min(0.0) * c / det), torch.full_like(r2, -1.0))
    half_y = torch.where(ok, torch.sqrt(r2.clamp_min(0.0) * a / det), torch.full_like(r2, -1.0))
    lncut = torch.log(MIN_ALPHA / op.clamp_min(1e-300))
    cols = [
        means2d.detach().to(f64),
        conics,
        op[:, None],
        colors.detach().to(f64),
        depths.detach().to(f64)[:, None],
        lncut[:, None],
        half_x[:, None],
        half_y[:, None],
        torch.exp(-conics[:, :1]),
    ]
    return torch.cat(cols, dim=1).contiguous()


def _composite_numba_forward(splats: Splats2D, background: Tensor, plan: TilePlan,
                             threads: int) -> tuple[Tensor, Tensor, Tensor, CompositeBackward]:
    """The numba compositor behind :func:`apply_compositor`: colour, depth, alpha and the backward pass."""
    k = _kernels()
    dtype = splats.means2d.dtype
    n = splats.means2d.shape[0]
    h, w = plan.height, plan.width
    table = _gaussian_table(*splats)  # [N, 14]
    # Tiles without Gaussians are not visited: they keep these values.
    out = torch.zeros(5, h, w, dtype=torch.float64)  # r, g, b, depth, sum of weights
    t_end = torch.ones(h, w, dtype=torch.float64)
    n_used = torch.zeros(h, w, dtype=torch.int32)
    jobs = _tile_jobs(plan, threads)
    _run_tiles(k.composite_forward, jobs, threads, _plan_args(table, plan), out.numpy(), t_end.numpy(),
               n_used.numpy())
    bg = background.detach().to(torch.float64)
    color = out[:3] + t_end.unsqueeze(0) * bg.view(3, 1, 1)

    def backward(image_grads: Tensor, background_needed: bool) -> tuple[Tensor, Tensor | None]:
        grads = image_grads.to(torch.float64).contiguous()  # dL/d (r, g, b, depth, alpha), [5, H, W]
        # d/dT_end of (T_end bg . v_C - T_end v_A): what lies behind the last Gaussian.
        behind = (grads[:3] * bg.view(3, 1, 1)).sum(0) - grads[4]  # [H, W]
        v_pair = torch.empty(plan.num_pairs, k.V_COLS, dtype=torch.float64)  # [M, 10]
        _run_tiles(k.composite_backward, jobs, threads, _plan_args(table, plan), t_end.numpy(),
                   n_used.numpy(), grads.numpy(), behind.numpy(), v_pair.numpy())
        v_gauss = torch.from_numpy(k.reduce_pairs(plan.pair_gid.numpy(), v_pair.numpy(), n))  # [N, 10]
        v_bg = None
        if background_needed:
            v_bg = (grads[:3] * t_end.unsqueeze(0)).sum((1, 2)).to(background.dtype)
        return v_gauss.to(dtype), v_bg

    return color.to(dtype), out[3].to(dtype), (1.0 - t_end).to(dtype), backward


def composite_numba(
    splats: Splats2D,
    background: Tensor,  # [3]
    plan: TilePlan,
    threads: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite binned Gaussians into colour [3, H, W], expected depth [H, W] and alpha [H, W].

    Same arguments and results as :func:`memgs_ros.core.raster.composite.composite` (CPU
    tensors only; float32 or float64, computed in float64); threads: Python threads (default
    :func:`cpu_threads`). Memory: 12 B per pixel plus
    80 B per (tile, Gaussian) pair in the backward pass.
    """
    for name, t in (("means2d", splats.means2d), ("background", background)):
        if t.device.type != "cpu":
            raise ValueError(f"composite_numba: {name} must be a CPU tensor, got {t.device}")
    run = functools.partial(_composite_numba_forward, threads=cpu_threads() if threads is None else threads)
    return apply_compositor(run, splats, background, plan)
