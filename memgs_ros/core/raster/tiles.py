"""Binning of projected Gaussians into small square tiles, and chunking of the tile lists.

A Gaussian can only reach ``alpha >= 1/255`` inside the ellipse
``d^T Sigma2D^-1 d <= r^2`` with ``r^2 = 2 ln(255 opacity)``. Each Gaussian is assigned to
exactly the tiles whose pixel centres that ellipse can touch: per tile row the ellipse's
x-range over the row band is found in closed form (the left/right boundary curves are convex
in y, so their extremes are at the tangent point clamped to the band). This is tighter than
3DGS's bounding square, and because nothing with ``alpha >= 1/255`` is left out, the rendered
image does not depend on the tile size (the brute-force reference needs no tiles at all).

Within a tile the Gaussians are in front-to-back order (stable sort by camera z). For the torch
compositor the tiles are then sorted by list length and grouped into chunks of about
``pairs_per_chunk`` pixel-Gaussian pairs, each padded to its longest list, so that compositing
is a handful of dense tensor ops per chunk (built on first use: the numba compositor reads the
per-tile lists directly).

The per-row expansion into (tile, Gaussian) pairs and the sort by tile run in a compiled
kernel where numba imports (:func:`memgs_ros.core.raster._composite_kernels.bin_pairs`: the same
float64 formulas, a counting sort instead of a comparison sort), else in torch
(:func:`_bin_pairs_torch`); both give identical plans.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.errors import ConfigError

# px. Pixel-Gaussian pairs per pixel on the benchmark scene (20k, 320x240, exact binning):
# 27 at 2 px, 38 at 4 px, 62 at 8 px, 130 at 16 px; 4 px balances pairs against per-tile overhead.
TILE_SIZE = 4
PAIRS_PER_CHUNK = 1 << 18  # pixel-Gaussian pairs per compositing chunk on a CPU (~1 MB per float32 buffer)
# On a GPU each chunk costs ~50 kernel launches whatever its size: at the CPU's chunk size the
# bench_raster scene (100k Gaussians, 640x480) took 56 chunks, ~3000 launches, and the launches
# were the render's time. 4M pairs (16 MB float32 buffers) make it 5 chunks (18 at 500k) for
# 17 % more padded pairs; a chunk's transient buffers stay near 100 MB (a Jetson shares that
# memory with the CPU).
CUDA_PAIRS_PER_CHUNK = 1 << 22
CHUNK_PAIRS_ENV = "MEMGS_RASTER_CHUNK_PAIRS"  # overrides both (tuning on a new device)
BIN_MARGIN = 1.001  # widen the cutoff ellipse a little: binning must never miss a pixel


def pairs_per_chunk_for(device: torch.device) -> int:
    """The torch compositor's chunk size on ``device``: ``CUDA_PAIRS_PER_CHUNK`` on a GPU,
    ``PAIRS_PER_CHUNK`` elsewhere, or the positive integer in $MEMGS_RASTER_CHUNK_PAIRS."""
    value = os.environ.get(CHUNK_PAIRS_ENV, "").strip()
    if value:
        try:
            pairs = int(value)
        except ValueError:
            pairs = 0
        if pairs <= 0:
            raise ConfigError(f"{CHUNK_PAIRS_ENV} must be a positive integer, got {value!r}")
        return pairs
    return CUDA_PAIRS_PER_CHUNK if device.type == "cuda" else PAIRS_PER_CHUNK


@dataclass(frozen=True)
class Chunk:
    """Tiles composited together.

    tiles: [T] int64 tile ids; k: padded list length; slot_start: offset of the chunk's
    T * k slots in ``TilePlan.slot_gid`` (row-major [T, k]).
    """

    tiles: Tensor
    k: int
    slot_start: int

    @property
    def num_slots(self) -> int:
        return int(self.tiles.shape[0]) * self.k


@dataclass(frozen=True)
class TilePlan:
    """Which Gaussian touches which tile, in compositing order.

    pair_gid: [M] int64 Gaussian index of each (tile, Gaussian) pair, grouped by tile and
    front-to-back inside a tile; pair_tile: [M] int64 tile id of each pair;
    tile_start, tile_count: [tiles_y * tiles_x] int64 offsets into the pair arrays;
    gaussian_hit: [N] bool, the Gaussian touches at least one tile; pairs_per_chunk: chunk
    size of the torch compositor's schedule (``chunks`` and ``slot_gid``, built on first use).
    """

    width: int
    height: int
    tile_size: int
    tiles_x: int
    tiles_y: int
    pair_gid: Tensor
    pair_tile: Tensor
    tile_start: Tensor
    tile_count: Tensor
    gaussian_hit: Tensor
    pairs_per_chunk: int = PAIRS_PER_CHUNK

    @property
    def num_pairs(self) -> int:
        return int(self.pair_gid.shape[0])

    @cached_property
    def _schedule(self) -> tuple[tuple[Chunk, ...], Tensor]:
        return _chunk_schedule(self)

    @property
    def chunks(self) -> tuple[Chunk, ...]:
        """The torch compositor's schedule: every tile with a non-empty list in exactly one chunk."""
        return self._schedule[0]

    @property
    def slot_gid(self) -> Tensor:
        """[S] int64, the padded per-chunk lists laid end to end (chunk by chunk, [T, k]
        row-major), with N (one past the last Gaussian) in the padding slots."""
        return self._schedule[1]


def _chunk_schedule(plan: TilePlan) -> tuple[tuple[Chunk, ...], Tensor]:
    """Group the tiles, longest list first, into chunks of about ``plan.pairs_per_chunk``
    pixel-Gaussian pairs, each padded to its longest list. Returns (chunks, slot_gid [S])."""
    tile_count, tile_start, pair_gid = plan.tile_count, plan.tile_start, plan.pair_gid
    device = tile_count.device
    n = int(plan.gaussian_hit.shape[0])
    n_tiles = int(tile_count.shape[0])
    with torch.no_grad():
        counts_sorted, order = torch.sort(tile_count, descending=True, stable=True)
        counts_list = counts_sorted.tolist()
        chunks: list[Chunk] = []
        slot_parts: list[Tensor] = []
        pix = plan.tile_size * plan.tile_size
        i = 0
        n_slots = 0
        while i < n_tiles and counts_list[i] > 0:
            k = counts_list[i]
            take = max(1, plan.pairs_per_chunk // (pix * k))
            j = min(i + take, n_tiles)
            while counts_list[j - 1] == 0:
                j -= 1
            tiles = order[i:j]
            chunks.append(Chunk(tiles=tiles, k=k, slot_start=n_slots))
            ar = torch.arange(k, device=device)
            pos = tile_start[tiles].unsqueeze(1) + ar  # [T, k]
            valid = ar < tile_count[tiles].unsqueeze(1)
            gids = pair_gid.index_select(0, pos.clamp_max(pair_gid.shape[0] - 1).reshape(-1)).view(pos.shape)
            slot_parts.append(torch.where(valid, gids, torch.full_like(gids, n)).reshape(-1))
            n_slots += (j - i) * k
            i = j
        empty = torch.zeros(0, dtype=torch.long, device=device)
        slot_gid = torch.cat(slot_parts) if slot_parts else empty
    return tuple(chunks), slot_gid


def build_tile_plan(
    means2d: Tensor,  # [N, 2]
    cov2d: Tensor,  # [N, 3]
    cutoff_sq: Tensor,  # [N]
    depths: Tensor,  # [N]
    active: Tensor,  # [N] bool
    width: int,
    height: int,
    tile_size: int = TILE_SIZE,
    pairs_per_chunk: int = PAIRS_PER_CHUNK,
) -> TilePlan:
    """Bin Gaussians into tiles (no gradients).

    means2d: [N, 2] px; cov2d: [N, 3] (xx, xy, yy) px^2; cutoff_sq: [N] squared Mahalanobis
    radius of the support (<= 0: never visible); depths: [N] sort key; active: [N] bool
    (in front of the camera). Returns a :class:`TilePlan`.
    """
    device = means2d.device
    n = means2d.shape[0]
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    with torch.no_grad():
        # float64: the per-row extents subtract nearly equal numbers for thin, far-off ellipses.
        # (index_select rather than x[idx] throughout: several times faster on CPU.)
        m = means2d.detach().to(torch.float64)
        cov = cov2d.detach().to(torch.float64)
        r2 = cutoff_sq.detach().to(torch.float64) * (BIN_MARGIN * BIN_MARGIN)
        ok = active & (r2 > 0)
        sxx, sxy, syy = cov.unbind(-1)
        r = torch.sqrt(r2.clamp_min(0.0))
        half_x = r * torch.sqrt(sxx)
        half_y = r * torch.sqrt(syy)
        mx, my = m[:, 0], m[:, 1]
        row_lo = torch.ceil(my - half_y).clamp_min(0)
        row_hi = torch.floor(my + half_y).clamp_max(height - 1)
        ok &= (row_lo <= row_hi) & (torch.ceil(mx - half_x) <= width - 1) & (torch.floor(mx + half_x) >= 0)

        # Front-to-back order first; every later expansion keeps it (repeat_interleave, stable sort).
        idx = torch.nonzero(ok).squeeze(1)
        idx = idx.index_select(0, torch.argsort(depths.detach().index_select(0, idx), stable=True))
        if _numba_binning(device):
            from memgs_ros.core.raster._composite_kernels import bin_pairs

            # One row per Gaussian, gathered in compositing order: the kernel reads it sequentially.
            gauss = torch.stack([mx, my, sxx, sxy, syy, r, r2, row_lo, row_hi], dim=1).index_select(0, idx)  # [G, 9]
            pair_tile_np, pair_gid_np, tile_count_np, hit_np = bin_pairs(
                idx.numpy(), gauss.numpy(), n, width, tile_size, tiles_x, n_tiles
            )
            pair_tile, pair_gid = torch.from_numpy(pair_tile_np), torch.from_numpy(pair_gid_np)
            tile_count, gaussian_hit = torch.from_numpy(tile_count_np), torch.from_numpy(hit_np)
        else:
            pair_tile, pair_gid, tile_count, gaussian_hit = _bin_pairs_torch(
                idx, mx, my, sxx, sxy, syy, r, r2, row_lo, row_hi, width, tile_size, tiles_x, n_tiles, n
            )
        tile_start = torch.cumsum(tile_count, 0) - tile_count
    return TilePlan(
        width=width,
        height=height,
        tile_size=tile_size,
        tiles_x=tiles_x,
        tiles_y=tiles_y,
        pair_gid=pair_gid,
        pair_tile=pair_tile,
        tile_start=tile_start,
        tile_count=tile_count,
        gaussian_hit=gaussian_hit,
        pairs_per_chunk=pairs_per_chunk,
    )


def _numba_binning(device: torch.device) -> bool:
    return device.type == "cpu" and numba_available()


def _bin_pairs_torch(
    idx: Tensor,  # [G] Gaussian ids, front to back
    mx: Tensor,  # [N] float64
    my: Tensor,  # [N]
    sxx: Tensor,  # [N]
    sxy: Tensor,  # [N]
    syy: Tensor,  # [N]
    r: Tensor,  # [N] cutoff radius (Mahalanobis)
    r2: Tensor,  # [N] its square
    row_lo: Tensor,  # [N] first pixel row inside the ellipse (float64)
    row_hi: Tensor,  # [N] last pixel row
    width: int,
    tile_size: int,
    tiles_x: int,
    n_tiles: int,
    n: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Expand the Gaussians into (tile, Gaussian) pairs sorted by tile, front to back within a
    tile. Returns pair_tile [M] int64, pair_gid [M] int64, tile_count [n_tiles] int64, hit [N] bool."""
    device = idx.device
    g_row_lo, g_row_hi = row_lo.index_select(0, idx), row_hi.index_select(0, idx)
    ty0 = torch.div(g_row_lo.long(), tile_size, rounding_mode="floor")
    ty1 = torch.div(g_row_hi.long(), tile_size, rounding_mode="floor")
    n_rows = ty1 - ty0 + 1  # [G]
    rg = torch.repeat_interleave(n_rows)  # [R] index into idx
    first_row = torch.cumsum(n_rows, 0) - n_rows
    ty = ty0.index_select(0, rg) + (torch.arange(rg.shape[0], device=device) - first_row.index_select(0, rg))

    # Per tile row: the band of pixel-centre rows inside the ellipse's y-range, relative to the mean.
    gi = idx.index_select(0, rg)  # [R] Gaussian ids

    def at(x: Tensor) -> Tensor:
        return x.index_select(0, gi)

    gmy = at(my)
    band_lo = torch.maximum((ty * tile_size).to(torch.float64), at(row_lo)) - gmy
    band_hi = torch.minimum((ty * tile_size + tile_size - 1).to(torch.float64), at(row_hi)) - gmy
    gxx, gxy, gyy, gr, gr2 = at(sxx), at(sxy), at(syy), at(r), at(r2)
    det = gxx * gyy - gxy * gxy
    slope = gxy / gyy  # centre line of the horizontal chords: x = slope * dy
    dy_tan = gr * gxy / torch.sqrt(gxx)  # dy of the right-most point (left-most is -dy_tan)

    def chord_half(dy: Tensor) -> Tensor:
        return torch.sqrt((det * (gr2 * gyy - dy * dy)).clamp_min(0.0)) / gyy

    dy_l = torch.minimum(torch.maximum(-dy_tan, band_lo), band_hi)
    dy_r = torch.minimum(torch.maximum(dy_tan, band_lo), band_hi)
    gmx = at(mx)
    x_lo = gmx + slope * dy_l - chord_half(dy_l)
    x_hi = gmx + slope * dy_r + chord_half(dy_r)
    c_lo = torch.ceil(x_lo).clamp_min(0).long()
    c_hi = torch.floor(x_hi).clamp_max(width - 1).long()
    tx0 = torch.div(c_lo, tile_size, rounding_mode="floor")
    tx1 = torch.div(c_hi, tile_size, rounding_mode="floor")
    n_cols = torch.where(c_lo <= c_hi, tx1 - tx0 + 1, torch.zeros_like(tx0))  # [R]
    pr = torch.repeat_interleave(n_cols)  # [M] index into rows
    first_col = torch.cumsum(n_cols, 0) - n_cols
    tx = tx0.index_select(0, pr) + (torch.arange(pr.shape[0], device=device) - first_col.index_select(0, pr))
    pair_tile = ty.index_select(0, pr) * tiles_x + tx  # [M]
    # int32 keys: the stable sort is ~3x faster than on int64.
    pair_tile, perm = torch.sort(pair_tile.to(torch.int32), stable=True)
    pair_tile = pair_tile.long()
    pair_gid = gi.index_select(0, pr.index_select(0, perm))

    tile_count = torch.bincount(pair_tile, minlength=n_tiles)  # [n_tiles]
    gaussian_hit = torch.zeros(n, dtype=torch.bool, device=device)
    gaussian_hit[pair_gid] = True
    return pair_tile, pair_gid, tile_count, gaussian_hit
