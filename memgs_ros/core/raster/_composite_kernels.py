"""Compiled per-pixel compositing kernels (numba); imported only by :mod:`.composite_numba`.

Same rules as :mod:`.composite` (1/255 skip, 0.99 clamp, power clamped at 0, early
termination once T (1 - alpha) < 1e-4), evaluated per pixel over its tile's front-to-back
list, in float64 whatever the input dtype. Each call composites the tiles it is given and
releases the GIL (``nogil``): callers run disjoint tile sets on several Python threads, and a
tile's pixels and pairs are written by that one call only, so there are no write races.

Per (tile, Gaussian) pair only the pixels where the Gaussian can reach alpha >= 1/255 are
visited: per pixel row of its bounding box, the run of pixels inside the cutoff ellipse is found
in closed form (a quadratic in x, widened by POWER_SLACK), and along the run exp(power) is
updated by two multiplications per pixel (the exponent is quadratic in x, so its forward
difference is linear: e(x + 1) = e(x) r(x), r(x + 1) = r(x) exp(-a)); exp is called twice per
run instead of once per pixel (it is most of the cost otherwise). The relative error of that
recurrence is ~1e-15 after a 16-pixel run; the exact alpha >= 1/255 and termination tests then
decide as before. Forward and backward pass run the identical recurrence, so both see
bit-identical alphas.

Per-Gaussian table ``g`` ([N, G_COLS] float64), built by the backend: (mean x, mean y, conic
a, b, c, opacity, r, g, b, z, ln(1/255 / opacity), half box x, half box y, exp(-a)).
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from memgs_ros.core.raster.rules import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE

G_MX, G_MY, G_A, G_B, G_C, G_OP, G_R, G_G, G_BL, G_Z, G_LNCUT, G_HX, G_HY, G_EXPA = range(14)
G_COLS = 14
# Gradient columns per pair: (mean x, mean y, conic a, b, c, opacity, r, g, b, z).
V_COLS = 10
# A pixel is evaluated when its exponent is above ln(1/255 / opacity) minus this: the exact
# alpha >= 1/255 test then decides, so rounding near the cutoff cannot drop a pixel.
POWER_SLACK = 1e-6


@njit(cache=True, fastmath=False, inline="always")
def _rows(g: np.ndarray, gid: int, y0: int, ny: int) -> tuple[int, int]:
    """Tile-local pixel rows [py0, py1) of the Gaussian's 1/255 bounding box."""
    my = g[gid, G_MY] - y0
    hy = g[gid, G_HY]
    return max(0, math.ceil(my - hy)), min(ny, math.floor(my + hy) + 1)


@njit(cache=True, fastmath=False, inline="always")
def _run(
    ca: float, cb: float, cc: float, lncut: float, mx: float, dy: float, nx: int
) -> tuple[int, int, float, float]:
    """On the pixel row at offset dy from the mean: the tile-local pixels [px0, px1) with
    power >= lncut - POWER_SLACK, exp(power) at px0 and the ratio r = exp(power(px0 + 1) - power(px0)).
    power(dx) = -0.5 (a dx^2 + c dy^2) - b dx dy with dx = px - mx."""
    bq = cb * dy
    disc = bq * bq - ca * (cc * dy * dy + 2.0 * (lncut - POWER_SLACK))
    if disc < 0.0:
        return 0, 0, 0.0, 0.0
    root = math.sqrt(disc)
    px0 = max(0, math.ceil(mx + (-bq - root) / ca))
    px1 = min(nx, math.floor(mx + (-bq + root) / ca) + 1)
    if px0 >= px1:
        return 0, 0, 0.0, 0.0
    dx = px0 - mx
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    step = -0.5 * ca * (2.0 * dx + 1.0) - bq
    return px0, px1, math.exp(power), math.exp(step)


class _Splat(NamedTuple):
    """One Gaussian's row of the table, its mean relative to the tile's origin."""

    mx: float
    my: float
    ca: float  # conic a, b, c
    cb: float
    cc: float
    op: float  # opacity
    lncut: float  # ln(1/255 / opacity)
    expa: float  # exp(-a)
    cr: float  # colour r, g, b
    cg: float
    cbl: float
    z: float  # depth


@njit(cache=True, fastmath=False, inline="always")
def _splat(g: np.ndarray, gid: int, x0: int, y0: int) -> _Splat:
    return _Splat(g[gid, G_MX] - x0, g[gid, G_MY] - y0, g[gid, G_A], g[gid, G_B], g[gid, G_C], g[gid, G_OP],
                  g[gid, G_LNCUT], g[gid, G_EXPA], g[gid, G_R], g[gid, G_G], g[gid, G_BL], g[gid, G_Z])


@njit(cache=True, fastmath=False, inline="always")
def _tile_box(t: int, tiles_x: int, tile_size: int, width: int, height: int) -> tuple[int, int, int, int]:
    """(x0, y0, nx, ny): tile t's pixel origin and size (edge tiles are cut at the image border)."""
    x0 = (t % tiles_x) * tile_size
    y0 = (t // tiles_x) * tile_size
    return x0, y0, min(tile_size, width - x0), min(tile_size, height - y0)


@njit(cache=True, fastmath=False, inline="always")
def _blend(s: _Splat, j: int, py0: int, py1: int, nx: int, trans: np.ndarray, acc: np.ndarray, used: np.ndarray,
           done: np.ndarray) -> int:
    """Composites list entry j (Gaussian ``s``) over the tile's pixels; returns how many pixels it terminated."""
    n_done = 0
    for py in range(py0, py1):
        px0, px1, e_next, r = _run(s.ca, s.cb, s.cc, s.lncut, s.mx, py - s.my, nx)
        for px in range(px0, px1):
            e = e_next
            e_next = e * r
            r *= s.expa
            p = py * nx + px
            if done[p]:
                continue
            alpha = min(MAX_ALPHA, s.op * e)
            if alpha < MIN_ALPHA:
                continue
            t_next = trans[p] * (1.0 - alpha)
            if t_next < MIN_TRANSMITTANCE:
                done[p] = True
                n_done += 1
                continue
            w = alpha * trans[p]
            acc[0, p] += w * s.cr
            acc[1, p] += w * s.cg
            acc[2, p] += w * s.cbl
            acc[3, p] += w * s.z
            acc[4, p] += w
            trans[p] = t_next
            used[p] = j + 1
    return n_done


@njit(nogil=True, cache=True, fastmath=False)
def composite_forward(tiles: np.ndarray, plan: tuple[Any, ...], out: np.ndarray, t_end: np.ndarray,
                      n_used: np.ndarray) -> None:
    """Front-to-back compositing of ``tiles`` ([T] int64 tile ids; background not added).

    plan: (g [N, G_COLS] float64, pair_gid [M] int64 grouped by tile and front to back within one,
    tile_start [n_tiles] int64, tile_count [n_tiles] int64, tiles_x, tile_size, width, height).
    Written: out [5, H, W] float64 (r, g, b, depth, sum of weights), t_end [H, W] float64
    (transmittance after the last Gaussian), n_used [H, W] int32 (list position + 1 of the last
    contributing Gaussian).
    """
    g, pair_gid, tile_start, tile_count, tiles_x, tile_size, width, height = plan
    for i in range(tiles.shape[0]):
        t = tiles[i]
        x0, y0, nx, ny = _tile_box(t, tiles_x, tile_size, width, height)
        npx = nx * ny
        trans = np.ones(npx)
        acc = np.zeros((5, npx))
        used = np.zeros(npx, dtype=np.int32)
        done = np.zeros(npx, dtype=np.bool_)
        n_done = 0
        start = tile_start[t]
        for j in range(tile_count[t]):
            gid = pair_gid[start + j]
            py0, py1 = _rows(g, gid, y0, ny)
            n_done += _blend(_splat(g, gid, x0, y0), j, py0, py1, nx, trans, acc, used, done)
            if n_done == npx:
                break
        for py in range(ny):
            for px in range(nx):
                p = py * nx + px
                for k in range(5):
                    out[k, y0 + py, x0 + px] = acc[k, p]
                t_end[y0 + py, x0 + px] = trans[p]
                n_used[y0 + py, x0 + px] = used[p]


@njit(cache=True, fastmath=False, inline="always")
def _unblend_vjp(s: _Splat, j: int, py0: int, py1: int, nx: int, trans: np.ndarray, acc: np.ndarray,
                 used: np.ndarray, gc: np.ndarray, v_pair: np.ndarray, q: int) -> None:
    """List entry j (Gaussian ``s``) taken back out of the tile's pixels that used it: T is divided
    back, the colour behind accumulated; writes dL/d(pair inputs) into v_pair[q] [V_COLS]."""
    v_mx = 0.0
    v_my = 0.0
    v_a = 0.0
    v_b = 0.0
    v_c = 0.0
    v_op = 0.0
    v_r = 0.0
    v_g = 0.0
    v_bl = 0.0
    v_z = 0.0
    for py in range(py0, py1):
        dy = py - s.my
        px0, px1, e_next, r = _run(s.ca, s.cb, s.cc, s.lncut, s.mx, dy, nx)
        for px in range(px0, px1):
            gauss = e_next
            e_next = gauss * r
            r *= s.expa
            p = py * nx + px
            if j >= used[p]:
                continue
            dx = px - s.mx
            raw = s.op * gauss
            alpha = min(MAX_ALPHA, raw)
            if alpha < MIN_ALPHA:
                continue
            one_minus = 1.0 - alpha
            t_i = trans[p] / one_minus
            w = alpha * t_i
            v = s.cr * gc[0, p] + s.cg * gc[1, p] + s.cbl * gc[2, p] + s.z * gc[3, p]
            v_r += w * gc[0, p]
            v_g += w * gc[1, p]
            v_bl += w * gc[2, p]
            v_z += w * gc[3, p]
            v_alpha = t_i * v - acc[p] / one_minus
            acc[p] += w * v
            trans[p] = t_i
            if raw <= MAX_ALPHA:
                v_op += v_alpha * gauss
                v_power = v_alpha * alpha
                v_mx += v_power * (s.ca * dx + s.cb * dy)
                v_my += v_power * (s.cb * dx + s.cc * dy)
                v_a -= 0.5 * v_power * dx * dx
                v_b -= v_power * dx * dy
                v_c -= 0.5 * v_power * dy * dy
    v_pair[q, 0] = v_mx
    v_pair[q, 1] = v_my
    v_pair[q, 2] = v_a
    v_pair[q, 3] = v_b
    v_pair[q, 4] = v_c
    v_pair[q, 5] = v_op
    v_pair[q, 6] = v_r
    v_pair[q, 7] = v_g
    v_pair[q, 8] = v_bl
    v_pair[q, 9] = v_z


@njit(nogil=True, cache=True, fastmath=False)
def composite_backward(tiles: np.ndarray, plan: tuple[Any, ...], t_end: np.ndarray, n_used: np.ndarray,
                       grads: np.ndarray, behind: np.ndarray, v_pair: np.ndarray) -> None:
    """Back-to-front walk of each pixel's list (3DGS): T is divided back out Gaussian by
    Gaussian from T_end, the colour behind is accumulated. Writes dL/d(pair inputs) per pair.

    tiles, plan: as composite_forward's; t_end [H, W] float64 and n_used [H, W] int32 from the
    forward pass; grads [5, H, W] float64: dL/d (r, g, b, depth, alpha) images; behind [H, W]
    float64: dL/dT_end = bg . dL/dC - dL/dA; v_pair [M, V_COLS] float64 (written).
    """
    g, pair_gid, tile_start, tile_count, tiles_x, tile_size, width, height = plan
    for i in range(tiles.shape[0]):
        t = tiles[i]
        x0, y0, nx, ny = _tile_box(t, tiles_x, tile_size, width, height)
        npx = nx * ny
        start = tile_start[t]
        trans = np.empty(npx)
        acc = np.empty(npx)  # sum over Gaussians behind of w v, plus T_end behind
        used = np.empty(npx, dtype=np.int32)
        gc = np.empty((4, npx))
        last = 0
        for py in range(ny):
            for px in range(nx):
                p = py * nx + px
                trans[p] = t_end[y0 + py, x0 + px]
                acc[p] = trans[p] * behind[y0 + py, x0 + px]
                used[p] = n_used[y0 + py, x0 + px]
                last = max(last, used[p])
                for k in range(4):
                    gc[k, p] = grads[k, y0 + py, x0 + px]
        for j in range(tile_count[t]):
            for k in range(V_COLS):
                v_pair[start + j, k] = 0.0
        for j in range(last - 1, -1, -1):
            gid = pair_gid[start + j]
            py0, py1 = _rows(g, gid, y0, ny)
            _unblend_vjp(_splat(g, gid, x0, y0), j, py0, py1, nx, trans, acc, used, gc, v_pair, start + j)


@njit(cache=True, fastmath=False)
def reduce_pairs(pair_gid: np.ndarray, v_pair: np.ndarray, n: int) -> np.ndarray:
    """Sum per-pair gradients into per-Gaussian rows: [M, V_COLS] -> [N, V_COLS] (in pair order)."""
    out = np.zeros((n, v_pair.shape[1]))
    for q in range(pair_gid.shape[0]):
        gid = pair_gid[q]
        for k in range(v_pair.shape[1]):
            out[gid, k] += v_pair[q, k]
    return out


# Columns of bin_pairs' per-Gaussian rows.
B_MX, B_MY, B_XX, B_XY, B_YY, B_R, B_R2, B_ROW_LO, B_ROW_HI = range(9)


@njit(nogil=True, cache=True, fastmath=False, inline="always")
def _row_columns(gi: np.ndarray, ty: int, width: int, tile_size: int) -> tuple[int, int]:
    """Tile columns [tx0, tx1) the Gaussian's cutoff ellipse touches in tile row ty (the
    formulas of tiles._bin_pairs_torch, operation for operation). gi: one row of bin_pairs' ``gauss``."""
    gmy = gi[B_MY]
    band_lo = max(float(ty * tile_size), gi[B_ROW_LO]) - gmy
    band_hi = min(float(ty * tile_size + tile_size - 1), gi[B_ROW_HI]) - gmy
    gxx = gi[B_XX]
    gxy = gi[B_XY]
    gyy = gi[B_YY]
    det = gxx * gyy - gxy * gxy
    slope = gxy / gyy
    dy_tan = gi[B_R] * gxy / math.sqrt(gxx)
    dy_l = min(max(-dy_tan, band_lo), band_hi)
    dy_r = min(max(dy_tan, band_lo), band_hi)
    half_l = math.sqrt(max(det * (gi[B_R2] * gyy - dy_l * dy_l), 0.0)) / gyy
    half_r = math.sqrt(max(det * (gi[B_R2] * gyy - dy_r * dy_r), 0.0)) / gyy
    x_lo = gi[B_MX] + slope * dy_l - half_l
    x_hi = gi[B_MX] + slope * dy_r + half_r
    c_lo = max(math.ceil(x_lo), 0)
    c_hi = min(math.floor(x_hi), width - 1)
    if c_lo > c_hi:
        return 0, 0
    return c_lo // tile_size, c_hi // tile_size + 1


@njit(nogil=True, cache=True, fastmath=False)
def bin_pairs(
    idx: np.ndarray,  # [G] int64 Gaussian ids, front to back
    gauss: np.ndarray,  # [G, 9] float64 rows (mean x, y, cov xx, xy, yy, cutoff r, r^2, first row, last row)
    n: int,
    width: int,
    tile_size: int,
    tiles_x: int,
    n_tiles: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(tile, Gaussian) pairs sorted by tile, front to back within a tile (a counting sort:
    one pass counts, a second one places). ``gauss`` holds the Gaussians of ``idx`` in that order.
    Returns pair_tile [M] int64, pair_gid [M] int64, tile_count [n_tiles] int64, hit [N] bool."""
    tile_count = np.zeros(n_tiles, dtype=np.int64)
    for i in range(idx.shape[0]):
        gi = gauss[i]
        for ty in range(int(gi[B_ROW_LO]) // tile_size, int(gi[B_ROW_HI]) // tile_size + 1):
            tx0, tx1 = _row_columns(gi, ty, width, tile_size)
            for tx in range(tx0, tx1):
                tile_count[ty * tiles_x + tx] += 1
    cursor = np.empty(n_tiles, dtype=np.int64)
    total = 0
    for t in range(n_tiles):
        cursor[t] = total
        total += tile_count[t]
    pair_tile = np.empty(total, dtype=np.int64)
    pair_gid = np.empty(total, dtype=np.int64)
    hit = np.zeros(n, dtype=np.bool_)
    for i in range(idx.shape[0]):
        gi = gauss[i]
        gid = idx[i]
        for ty in range(int(gi[B_ROW_LO]) // tile_size, int(gi[B_ROW_HI]) // tile_size + 1):
            tx0, tx1 = _row_columns(gi, ty, width, tile_size)
            for tx in range(tx0, tx1):
                t = ty * tiles_x + tx
                q = cursor[t]
                pair_tile[q] = t
                pair_gid[q] = gid
                cursor[t] = q + 1
                hit[gid] = True
    return pair_tile, pair_gid, tile_count, hit
