"""Front-to-back alpha compositing over tiles as one custom autograd Function.

Twin of :func:`memgs_ros.core.raster.reference._composite_reference` (brute force, plain
autograd, same semantics). Per pixel p and depth-sorted Gaussian i:

    power_i = min(0, -0.5 d^T Sigma2D_i^-1 d)          d = p - mean2d_i
    alpha_i = min(0.99, opacity_i exp(power_i)), set to 0 when < 1/255
    T_i     = prod_{j<i} (1 - alpha_j)                 (transmittance before i)
    Gaussian i and all behind it are dropped once T_i (1 - alpha_i) < 1e-4 (3DGS early stop)
    w_i = alpha_i T_i;  C = sum w_i c_i + T_end bg;  D = sum w_i z_i;  A = 1 - T_end

How it stays fast and small on a CPU:
- For one (tile, Gaussian) pair the exponent is a quadratic in the tile-local pixel
  coordinates (u, v): power = [u^2, uv, v^2, u, v, 1] . k, so a chunk of tiles is a single
  ``[P, 6] @ [T, 6, K]`` matrix product (P pixels per tile, K padded list length, K innermost).
  The six coefficients k are computed per pair in float64 (they cancel for far-off pixels).
- Only ``alpha`` and ``T`` are kept per pixel-Gaussian pair (8 B in float32); the backward
  pass gets the colour still to come behind i as "total minus inclusive cumulative sum",
  so there is no autograd graph over pairs.
- Chunks can run on several Python threads (torch releases the GIL inside each op); used when
  torch's own intra-op pool is one thread (see :mod:`memgs_ros.core.runtime`).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Sequence, TypeVar

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from memgs_ros.core.raster.tiles import Chunk, TilePlan

MIN_ALPHA = 1.0 / 255.0
MAX_ALPHA = 0.99
MIN_TRANSMITTANCE = 1e-4
# exp() of very negative arguments takes a slow path (~14x); below -30 alpha is 0 anyway.
MIN_POWER = -30.0

_T = TypeVar("_T")


def default_workers(device: torch.device) -> int:
    """Python threads for the chunk loop: >1 only on CPU when torch runs single-threaded ops."""
    if device.type != "cpu" or torch.get_num_threads() != 1:
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, 4))


def _map(fn: Callable[[Chunk], _T], chunks: Sequence[Chunk], workers: int) -> list[_T]:
    if workers <= 1 or len(chunks) <= 1:
        return [fn(c) for c in chunks]
    with ThreadPoolExecutor(max_workers=min(workers, len(chunks))) as pool:
        return list(pool.map(fn, chunks))


def _pixel_features(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[P, 6] rows (u^2, uv, v^2, u, v, 1) of tile-local pixel coordinates, P = tile_size^2, row-major."""
    r = torch.arange(tile_size, dtype=dtype, device=device)
    v, u = torch.meshgrid(r, r, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    return torch.stack([u * u, u * v, v * v, u, v, torch.ones_like(u)], dim=-1)


def _pair_geometry(plan: TilePlan, means2d: Tensor, conics: Tensor) -> tuple[Tensor, ...]:
    """Float64 per-pair (mu, mv, a, b, c): the mean relative to the pair's tile origin, and the conic."""
    gid, tile = plan.pair_gid, plan.pair_tile
    ox = (tile % plan.tiles_x).to(torch.float64) * plan.tile_size
    oy = torch.div(tile, plan.tiles_x, rounding_mode="floor").to(torch.float64) * plan.tile_size
    m = means2d.detach()[gid].to(torch.float64)  # [M, 2]
    a, b, c = conics.detach()[gid].to(torch.float64).unbind(-1)
    return m[:, 0] - ox, m[:, 1] - oy, a, b, c


def _to_tiles(img: Tensor, plan: TilePlan) -> Tensor:
    """[C, H, W] image -> [n_tiles, P, C] tile-major layout (zero padded at the right/bottom)."""
    ch = img.shape[0]
    ts = plan.tile_size
    hp, wp = plan.tiles_y * ts, plan.tiles_x * ts
    img = torch.nn.functional.pad(img, (0, wp - plan.width, 0, hp - plan.height))
    img = img.reshape(ch, plan.tiles_y, ts, plan.tiles_x, ts).permute(1, 3, 2, 4, 0)
    return img.reshape(plan.tiles_y * plan.tiles_x, ts * ts, ch).contiguous()


def _from_tiles(buf: Tensor, plan: TilePlan) -> Tensor:
    """[n_tiles, P, C] tile-major buffer -> [C, H, W] image (padding cropped)."""
    ch = buf.shape[-1]
    ts = plan.tile_size
    img = buf.reshape(plan.tiles_y, plan.tiles_x, ts, ts, ch).permute(4, 0, 2, 1, 3)
    img = img.reshape(ch, plan.tiles_y * ts, plan.tiles_x * ts)
    return img[:, : plan.height, : plan.width].contiguous()


def _chunk_index(plan: TilePlan, chunk: Chunk, dummy: int) -> Tensor:
    """[T, K] pair indices of the chunk's tiles, padded with the dummy (transparent) row."""
    ar = torch.arange(chunk.k, device=chunk.tiles.device)
    start = plan.tile_start[chunk.tiles].unsqueeze(1)
    count = plan.tile_count[chunk.tiles].unsqueeze(1)
    return torch.where(ar < count, start + ar, torch.full_like(start, dummy))


class _CompositeFn(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Tensor,  # [N, 2]
        conics: Tensor,  # [N, 3]
        opacities: Tensor,  # [N]
        colors: Tensor,  # [N, 3]
        depths: Tensor,  # [N]
        background: Tensor,  # [3]
        plan: TilePlan,
        workers: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        dtype, device = means2d.dtype, means2d.device
        m_pairs = plan.num_pairs
        mu, mv, a, b, c = _pair_geometry(plan, means2d, conics)
        k3 = a * mu + b * mv
        k4 = b * mu + c * mv
        coef = torch.stack([-0.5 * a, -b, -0.5 * c, k3, k4, -0.5 * (mu * k3 + mv * k4)], dim=-1)
        gid = plan.pair_gid
        # One row per pair: 6 exponent coefficients, opacity, r, g, b, z; the last row is the
        # transparent pad (opacity 0) that short tile lists point to.
        table = torch.zeros(m_pairs + 1, 11, dtype=dtype, device=device)
        table[:m_pairs, :6] = coef.to(dtype)
        table[:m_pairs, 6] = opacities.detach()[gid]
        table[:m_pairs, 7:10] = colors.detach()[gid]
        table[:m_pairs, 10] = depths.detach()[gid]
        feat = _pixel_features(plan.tile_size, dtype, device)  # [P, 6]

        def run(chunk: Chunk) -> tuple[Tensor, Tensor, Tensor, Tensor]:
            idx = _chunk_index(plan, chunk, m_pairs)  # [T, K]
            tab = table[idx]  # [T, K, 11]
            power = torch.matmul(feat, tab[..., :6].transpose(1, 2))  # [T, P, K]
            power.clamp_(MIN_POWER, 0.0)
            alpha = power.exp_().mul_(tab[..., 6].unsqueeze(1)).clamp_max_(MAX_ALPHA)
            alpha.masked_fill_(alpha < MIN_ALPHA, 0.0)
            one_minus = 1.0 - alpha
            t_incl = torch.cumprod(one_minus, dim=-1)
            keep = t_incl >= MIN_TRANSMITTANCE  # early termination: a prefix of each list survives
            t_excl = t_incl.div_(one_minus)  # exclusive product; 1 - alpha >= 0.01
            alpha.mul_(keep)
            w = alpha * t_excl  # [T, P, K]
            rgbd = torch.matmul(w, tab[..., 7:11])  # [T, P, 4]
            t_end = 1.0 - w.sum(-1)  # [T, P]
            return rgbd, t_end, alpha, t_excl

        results = _map(run, plan.chunks, workers)
        n_tiles = plan.tiles_x * plan.tiles_y
        p = plan.tile_size * plan.tile_size
        buf = torch.zeros(n_tiles, p, 5, dtype=dtype, device=device)  # r, g, b, depth, T_end
        buf[..., 4] = 1.0
        if results:
            tiles = torch.cat([ch.tiles for ch in plan.chunks])
            buf[tiles, :, :4] = torch.cat([r[0] for r in results])
            buf[tiles, :, 4] = torch.cat([r[1] for r in results])
        bg = background.detach().to(dtype)
        buf[..., :3] += buf[..., 4:5] * bg
        img = _from_tiles(buf, plan)  # [5, H, W]
        color, depth, t_end = img[:3], img[3], img[4]
        alpha_img = 1.0 - t_end

        ctx.plan = plan
        ctx.workers = workers
        ctx.table = table
        ctx.saved_pairs = [(r[2], r[3]) for r in results]
        ctx.t_end_tiles = buf[..., 4].clone()  # [n_tiles, P]
        ctx.save_for_backward(means2d, conics, opacities, background)
        return color, depth.contiguous(), alpha_img.contiguous()

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, v_color: Tensor, v_depth: Tensor, v_alpha: Tensor) -> tuple[Any, ...]:
        means2d, conics, opacities, background = ctx.saved_tensors
        plan: TilePlan = ctx.plan
        table: Tensor = ctx.table
        dtype, device = means2d.dtype, means2d.device
        m_pairs = plan.num_pairs
        h, w_ = plan.height, plan.width
        if v_color is None:
            v_color = torch.zeros(3, h, w_, dtype=dtype, device=device)
        if v_depth is None:
            v_depth = torch.zeros(h, w_, dtype=dtype, device=device)
        if v_alpha is None:
            v_alpha = torch.zeros(h, w_, dtype=dtype, device=device)
        grads = _to_tiles(torch.cat([v_color, v_depth[None], v_alpha[None]]), plan)  # [n_tiles, P, 5]
        t_end = ctx.t_end_tiles  # [n_tiles, P]
        bg = background.detach().to(dtype)
        # d/dT_end of (T_end bg . v_C + (1 - T_end) v_A): the colour/alpha "behind the last Gaussian".
        behind = t_end * ((grads[..., :3] * bg).sum(-1) - grads[..., 4])  # [n_tiles, P]
        feat_t = _pixel_features(plan.tile_size, dtype, device).T.contiguous()  # [6, P]

        def run(job: tuple[Chunk, tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor]:
            chunk, (alpha, t_excl) = job
            idx = _chunk_index(plan, chunk, m_pairs)  # [T, K]
            tab = table[idx]  # [T, K, 11]
            g = grads[chunk.tiles]  # [T, P, 5]
            g4 = g[..., :4]  # [T, P, 4] (v_color, v_depth)
            cz = tab[..., 7:11]  # [T, K, 4]
            v = torch.matmul(g4, cz.transpose(1, 2))  # [T, P, K] dL/d(feature) per pair
            w = alpha * t_excl
            wv = w * v
            after = wv.sum(-1, keepdim=True) - torch.cumsum(wv, dim=-1)  # sum_{j>i} w_j v_j
            after.add_(behind[chunk.tiles].unsqueeze(-1)).div_(1.0 - alpha)
            v_alpha_p = t_excl * v - after
            # alpha = opacity * exp(power): d alpha / d power = alpha; 0 where clamped or dropped.
            v_power = v_alpha_p.mul_(alpha).masked_fill_(alpha >= MAX_ALPHA, 0.0)
            out = torch.empty(idx.shape + (11,), dtype=dtype, device=device)  # [T, K, 11]
            out[..., :6] = torch.matmul(feat_t, v_power).transpose(1, 2)
            out[..., 6] = v_power.sum(1) / tab[..., 6].clamp_min(1e-30)
            out[..., 7:11] = torch.matmul(w.transpose(1, 2), g4)
            return idx, out

        results = _map(run, list(zip(plan.chunks, ctx.saved_pairs)), ctx.workers)  # type: ignore[arg-type]
        v_pairs = torch.zeros(m_pairs + 1, 11, dtype=dtype, device=device)
        for idx, out in results:
            v_pairs.index_copy_(0, idx.reshape(-1), out.reshape(-1, 11))
        v_pairs = v_pairs[:m_pairs]

        mu, mv, a, b, c = _pair_geometry(plan, means2d, conics)
        vk = v_pairs[:, :6].to(torch.float64)
        g0, g1, g2, g3, g4_, g5 = vk.unbind(-1)
        k3 = a * mu + b * mv
        k4 = b * mu + c * mv
        per_pair = torch.stack(
            [
                g3 * a + g4_ * b - g5 * k3,  # d/d mean_x
                g3 * b + g4_ * c - g5 * k4,  # d/d mean_y
                -0.5 * g0 + g3 * mu - 0.5 * g5 * mu * mu,  # d/d conic a
                -g1 + g3 * mv + g4_ * mu - g5 * mu * mv,  # d/d conic b
                -0.5 * g2 + g4_ * mv - 0.5 * g5 * mv * mv,  # d/d conic c
            ],
            dim=-1,
        ).to(dtype)
        n = means2d.shape[0]
        v_gauss = torch.zeros(n, 10, dtype=dtype, device=device)
        v_gauss.index_add_(0, plan.pair_gid, torch.cat([per_pair, v_pairs[:, 6:]], dim=-1))
        v_means2d = v_gauss[:, 0:2]
        v_conics = v_gauss[:, 2:5]
        v_opac = v_gauss[:, 5]
        v_colors = v_gauss[:, 6:9]
        v_depths = v_gauss[:, 9]
        v_bg = None
        if ctx.needs_input_grad[5]:
            v_bg = (grads[..., :3] * t_end.unsqueeze(-1)).sum((0, 1)).to(background.dtype)
        return v_means2d, v_conics, v_opac, v_colors, v_depths, v_bg, None, None


def composite(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    depths: Tensor,  # [N]
    background: Tensor,  # [3]
    plan: TilePlan,
    workers: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite binned Gaussians into colour [3, H, W], expected depth [H, W] and alpha [H, W].

    means2d: [N, 2] px; conics: [N, 3] (a, b, c) of Sigma2D^-1; opacities: [N]; colors: [N, 3];
    depths: [N] camera z (also the value blended into the depth image); background: [3];
    plan: the tile binning of these Gaussians (front-to-back within each tile).
    Differentiable w.r.t. all tensor inputs; memory is 8 B per pixel-Gaussian pair plus one chunk.
    """
    if workers is None:
        workers = default_workers(means2d.device)
    return _CompositeFn.apply(
        means2d.contiguous(),
        conics.contiguous(),
        opacities.contiguous(),
        colors.contiguous(),
        depths.contiguous(),
        background,
        plan,
        workers,
    )
