"""Front-to-back alpha compositing over tiles, in torch, behind the compositors' one autograd boundary.

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
  The six coefficients k are computed per pair relative to the tile origin (small numbers).
- No autograd graph over pairs: only ``alpha`` and ``T`` are kept per pixel-Gaussian pair
  (8 B in float32; above SAVED_PAIRS_BUDGET_BYTES they are recomputed per chunk instead, so
  memory is then one chunk's worth). The backward pass gets the colour still to come behind
  Gaussian i as "total minus inclusive cumulative sum".
- No bool tensors in the per-pair work (comparisons and masked ops are several times slower
  than arithmetic on this CPU): the 1/255 skip is ``threshold_``, the termination mask a
  clamp + ceil; ``exp`` sees no argument below -30 (its slow path).
- Chunks can run on several Python threads (torch releases the GIL inside each op); used when
  torch's own intra-op pool is one thread (see :mod:`memgs_ros.core.runtime.cpu`).
"""
from __future__ import annotations

import functools

import torch
from torch import Tensor

from memgs_ros.core.raster.composite_autograd import CompositeBackward, apply_compositor
from memgs_ros.core.raster.rules import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE
from memgs_ros.core.raster.tiles import Chunk, TilePlan
from memgs_ros.core.raster.values import Splats2D
from memgs_ros.core.runtime.pool import cpu_threads, parallel_map

# exp() of very negative arguments takes a slow path (~14x); below -30 alpha is 0 anyway.
MIN_POWER = -30.0
# Above this, alpha and T are recomputed in the backward pass instead of kept (see _saves_pairs).
SAVED_PAIRS_BUDGET_BYTES = 512 * 1024 * 1024

def default_workers(device: torch.device) -> int:
    """Python threads for the chunk loop: >1 only on CPU when torch runs single-threaded ops."""
    if device.type != "cpu" or torch.get_num_threads() != 1:
        return 1
    return cpu_threads()


def _pixel_features(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[P, 6] rows (u^2, uv, v^2, u, v, 1) of tile-local pixel coordinates, P = tile_size^2, row-major."""
    r = torch.arange(tile_size, dtype=dtype, device=device)
    v, u = torch.meshgrid(r, r, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    return torch.stack([u * u, u * v, v * v, u, v, torch.ones_like(u)], dim=-1)


def _to_tiles(img: Tensor, plan: TilePlan) -> Tensor:
    """[C, H, W] image -> [n_tiles, C, P] tile-major layout (zero padded at the right/bottom)."""
    ch = img.shape[0]
    ts = plan.tile_size
    hp, wp = plan.tiles_y * ts, plan.tiles_x * ts
    img = torch.nn.functional.pad(img, (0, wp - plan.width, 0, hp - plan.height))
    img = img.reshape(ch, plan.tiles_y, ts, plan.tiles_x, ts).permute(1, 3, 0, 2, 4)
    return img.reshape(plan.tiles_y * plan.tiles_x, ch, ts * ts).contiguous()


def _from_tiles(buf: Tensor, plan: TilePlan) -> Tensor:
    """[n_tiles, C, P] tile-major buffer -> [C, H, W] image (padding cropped)."""
    ch = buf.shape[1]
    ts = plan.tile_size
    img = buf.reshape(plan.tiles_y, plan.tiles_x, ch, ts, ts).permute(2, 0, 3, 1, 4)
    img = img.reshape(ch, plan.tiles_y * ts, plan.tiles_x * ts)
    return img[:, : plan.height, : plan.width].contiguous()


# Rows of the per-slot table built by _slot_table.
_MX, _MY, _CA, _CB, _CC, _OP, _CR, _CG, _CBL, _Z = range(10)


def _slot_table(
    plan: TilePlan, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, depths: Tensor
) -> Tensor:
    """[10, S] per-slot copy of (mean x, mean y, conic a, b, c, opacity, r, g, b, z) of each slot's
    Gaussian; padding slots get a transparent one (opacity 0). One 1-D gather per row: several
    times faster than gathering [N, 10] rows."""
    n = means2d.shape[0]
    per_g = torch.zeros(10, n + 1, dtype=means2d.dtype, device=means2d.device)
    per_g[_MX : _MY + 1, :n] = means2d.detach().T
    per_g[_CA : _CC + 1, :n] = conics.detach().T
    per_g[_OP, :n] = opacities.detach()
    per_g[_CR : _CBL + 1, :n] = colors.detach().T
    per_g[_Z, :n] = depths.detach()
    out = torch.empty(10, plan.slot_gid.shape[0], dtype=means2d.dtype, device=means2d.device)
    for j in range(10):
        torch.index_select(per_g[j], 0, plan.slot_gid, out=out[j])
    return out


def _chunk_geometry(plan: TilePlan, chunk: Chunk, x: Tensor) -> tuple[Tensor, ...]:
    """The chunk's (mu, mv, a, b, c, k3, k4), each [T, K]: the mean relative to its tile's origin,
    the conic, and the linear-term coefficients of the exponent. Relative coordinates keep every
    number small, so the input dtype is enough (float32 loses ~1e-4 in the exponent only for
    needle-thin Gaussians tens of pixels from their centre, as a direct evaluation does)."""
    ox = (chunk.tiles % plan.tiles_x).to(x.dtype).unsqueeze(1) * plan.tile_size  # [T, 1]
    oy = torch.div(chunk.tiles, plan.tiles_x, rounding_mode="floor").to(x.dtype).unsqueeze(1) * plan.tile_size
    mu, mv = x[_MX] - ox, x[_MY] - oy
    a, b, c = x[_CA], x[_CB], x[_CC]
    return mu, mv, a, b, c, a * mu + b * mv, b * mu + c * mv


def _chunk_block(table: Tensor, chunk: Chunk) -> Tensor:
    """[10, S] slot table -> the chunk's [10, T, K] block (a view)."""
    return table[:, chunk.slot_start : chunk.slot_start + chunk.num_slots].view(table.shape[0], -1, chunk.k)


def _float_below(x: float, dtype: torch.dtype) -> float:
    """The largest ``dtype`` value below x: ``F.threshold`` keeps values strictly above its
    threshold, and the rules here keep values >= x."""
    t = torch.tensor(x, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))


def _forward_chunk(
    plan: TilePlan, chunk: Chunk, table: Tensor, feat: Tensor, alpha_floor: float, t_floor: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite one chunk. Returns ([T, 5, P] r, g, b, depth, sum of weights; alpha [T, P, K]
    after the skip/termination rules; transmittance before each Gaussian [T, P, K])."""
    x = _chunk_block(table, chunk)  # [10, T, K]
    mu, mv, a, b, c, k3, k4 = _chunk_geometry(plan, chunk, x)
    coef = torch.stack([-0.5 * a, -b, -0.5 * c, k3, k4, -0.5 * (mu * k3 + mv * k4)], dim=1)  # [T, 6, K]
    czT = torch.stack([x[_CR], x[_CG], x[_CBL], x[_Z], torch.ones_like(mu)], dim=1)  # [T, 5, K]
    alpha = torch.matmul(feat, coef)  # [T, P, K] exponent
    alpha.clamp_(MIN_POWER, 0.0).exp_().mul_(x[_OP].unsqueeze(1)).clamp_max_(MAX_ALPHA)
    torch.nn.functional.threshold_(alpha, alpha_floor, 0.0)  # type: ignore[attr-defined]  # alpha < 1/255 -> 0
    one_minus = 1.0 - alpha
    trans = torch.cumprod(one_minus, dim=-1)  # inclusive
    t_excl = trans / one_minus  # 1 - alpha >= 0.01
    # Early termination: Gaussians whose inclusive T fell below 1e-4 (a suffix of each
    # list) are dropped. (x - floor) clamped to [0, 1] and ceiled is the 0/1 mask,
    # several times cheaper than a bool tensor and a masked op.
    alpha.mul_(trans.sub_(t_floor).clamp_(0.0, 1.0).ceil_())
    w = alpha * t_excl
    out = torch.matmul(czT, w.transpose(1, 2))  # [T, 5, P] r, g, b, z, sum w
    return out, alpha, t_excl


def _saves_pairs(plan: TilePlan, dtype: torch.dtype) -> bool:
    """Keep alpha and T per pixel-Gaussian pair for the backward pass (no recomputation) unless that
    would exceed SAVED_PAIRS_BUDGET_BYTES; above it the backward pass recomputes them per chunk,
    so memory stays at one chunk's worth."""
    slots = int(plan.slot_gid.shape[0])
    item = torch.tensor([], dtype=dtype).element_size()
    return 2 * item * slots * plan.tile_size * plan.tile_size <= SAVED_PAIRS_BUDGET_BYTES


def _composite_forward(splats: Splats2D, background: Tensor, plan: TilePlan, workers: int,
                       differentiable: bool) -> tuple[Tensor, Tensor, Tensor, CompositeBackward]:
    """The torch compositor behind :func:`apply_compositor`: colour, depth, alpha and the backward pass."""
    means2d = splats.means2d
    dtype, device = means2d.dtype, means2d.device
    table = _slot_table(plan, *splats)  # [10, S]
    feat = _pixel_features(plan.tile_size, dtype, device)  # [P, 6]
    alpha_floor = _float_below(MIN_ALPHA, dtype)
    t_floor = _float_below(MIN_TRANSMITTANCE, dtype)

    keep = differentiable and _saves_pairs(plan, dtype)

    def run(chunk: Chunk) -> tuple[Tensor, Tensor | None, Tensor | None]:
        out, alpha, t_excl = _forward_chunk(plan, chunk, table, feat, alpha_floor, t_floor)
        return (out, alpha, t_excl) if keep else (out, None, None)

    results = parallel_map(run, plan.chunks, workers)
    n_tiles = plan.tiles_x * plan.tiles_y
    p = plan.tile_size * plan.tile_size
    buf = torch.zeros(n_tiles, 5, p, dtype=dtype, device=device)  # r, g, b, depth, sum w
    if results:
        tiles = torch.cat([ch.tiles for ch in plan.chunks])
        buf.index_copy_(0, tiles, torch.cat([r[0] for r in results]))
    t_end = 1.0 - buf[:, 4]  # [n_tiles, P]
    buf[:, :3] += t_end.unsqueeze(1) * background.detach().to(dtype).view(1, 3, 1)
    buf[:, 4] = t_end
    img = _from_tiles(buf, plan)  # [5, H, W]
    saved_pairs = [r[1:] for r in results]
    n = means2d.shape[0]

    def backward(image_grads: Tensor, background_needed: bool) -> tuple[Tensor, Tensor | None]:
        grads = _to_tiles(image_grads, plan)  # [n_tiles, 5, P]
        bg = background.detach().to(dtype)
        # d/dT_end of (T_end bg . v_C - T_end v_A): what lies "behind the last Gaussian".
        behind = t_end * ((grads[:, :3] * bg.view(1, 3, 1)).sum(1) - grads[:, 4])  # [n_tiles, P]
        feat_t = feat.T.contiguous()  # [6, P]
        # Per slot: dL/d (mean x, mean y, conic a, b, c, opacity, r, g, b, z).
        v_table = torch.empty_like(table)

        def run(job: tuple[Chunk, tuple[Tensor | None, Tensor | None]]) -> None:
            chunk, (alpha, t_excl) = job
            if alpha is None or t_excl is None:
                _, alpha, t_excl = _forward_chunk(plan, chunk, table, feat, alpha_floor, t_floor)
            x = _chunk_block(table, chunk)  # [10, T, K]
            vx = _chunk_block(v_table, chunk)  # [10, T, K]
            g4T = grads.index_select(0, chunk.tiles)[:, :4]  # [T, 4, P] v_color, v_depth
            cz = torch.stack([x[_CR], x[_CG], x[_CBL], x[_Z]], dim=1)  # [T, 4, K]
            v = torch.matmul(g4T.transpose(1, 2), cz)  # [T, P, K]
            w = alpha * t_excl
            vx[_CR : _Z + 1] = torch.matmul(g4T, w).transpose(0, 1)
            # dL/d alpha_i = T_i v_i - (sum_{j>i} w_j v_j + behind) / (1 - alpha_i), with the sum
            # over j > i as "total minus inclusive cumulative sum".
            cum = torch.cumsum(w.mul_(v), dim=-1)  # [T, P, K]
            cum.sub_(cum[..., -1:] + behind.index_select(0, chunk.tiles).unsqueeze(-1)).div_(1.0 - alpha)
            v_alpha_p = cum.addcmul_(t_excl, v)  # [T, P, K] dL/d alpha_i
            # d alpha / d power = alpha, except where clamped at 0.99: -alpha below it, 0 above
            # (the sign is undone below), again without bool tensors.
            d_alpha = torch.nn.functional.threshold_(alpha.neg(), -MAX_ALPHA, 0.0)  # type: ignore[attr-defined]
            v_power = v_alpha_p.mul_(d_alpha)  # = -dL/d power
            vx[_OP] = v_power.sum(1).div_(x[_OP].clamp_min(1e-30)).neg_()
            g0, g1, g2, g3, g4, g5 = torch.matmul(feat_t, v_power).neg_().unbind(1)  # dL/d coef, [T, K] each
            mu, mv, a, b, c, k3, k4 = _chunk_geometry(plan, chunk, x)
            vx[_MX] = g3 * a + g4 * b - g5 * k3
            vx[_MY] = g3 * b + g4 * c - g5 * k4
            vx[_CA] = -0.5 * g0 + g3 * mu - 0.5 * g5 * mu * mu
            vx[_CB] = -g1 + g3 * mv + g4 * mu - g5 * mu * mv
            vx[_CC] = -0.5 * g2 + g4 * mv - 0.5 * g5 * mv * mv

        parallel_map(run, list(zip(plan.chunks, saved_pairs)), workers)
        v_gauss = torch.zeros(10, n + 1, dtype=dtype, device=device)
        v_gauss.index_add_(1, plan.slot_gid, v_table)
        v_bg = None
        if background_needed:
            v_bg = (grads[:, :3] * t_end.unsqueeze(1)).sum((0, 2)).to(background.dtype)
        return v_gauss[:, :n].T, v_bg

    return img[:3], img[3].contiguous(), (1.0 - img[4]).contiguous(), backward


def composite(
    splats: Splats2D,
    background: Tensor,  # [3]
    plan: TilePlan,
    workers: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite binned Gaussians into colour [3, H, W], expected depth [H, W] and alpha [H, W].

    splats: the projected Gaussians (:class:`Splats2D`); background: [3]; plan: the tile binning
    of these Gaussians (front-to-back within each tile). Differentiable w.r.t. all tensor inputs.
    Memory: 8 B per pixel-Gaussian pair (up to SAVED_PAIRS_BUDGET_BYTES, then recomputed) plus one
    chunk per worker.
    """
    if workers is None:
        workers = default_workers(splats.means2d.device)
    inputs = (*splats, background)
    # Nothing to keep for a render without gradients (e.g. the published views); inside
    # forward() grad mode is always off, so this is decided here.
    differentiable = torch.is_grad_enabled() and any(t.requires_grad for t in inputs)
    run = functools.partial(_composite_forward, workers=workers, differentiable=differentiable)
    return apply_compositor(run, splats, background, plan)
