"""numba kernels of the per-frame tracking hot spots (optional: plain numpy twins are the reference).

- ``match_by_projection_kernel``: twin of ``features._match_by_projection``. A grid of keypoint
  cells replaces the k-d tree; each map point examines its ``max_candidates`` nearest keypoints
  inside its own radius, scores their Hamming distances with a 64-bit popcount, applies the
  ratio test and resolves keypoints claimed by several points, without building the
  intermediate pair arrays of the numpy version (7 ms -> ~1 ms a frame at 640x480). The cells
  are visited in rings around the point and the scan stops once no further ring can hold a
  nearer keypoint (28 % less on fr1/rpy's wide first pass and tight second pass together).
- ``optimize_pose_kernel``: twin of ``bundle_adjustment._optimize_pose``. The same Gauss-Newton
  with Huber weights and outlier rounds, accumulating the 6x6 normal equations point by point
  (no [N, 3, 6] Jacobian arrays).

The frame path calls them through three per-frame kernels, each one call per stage on the flat
arrays of the sparse map's store (read in place, no per-frame copies of the map):

- ``track_pass_kernel``: a projection pass over the local map (project, match, optimise the pose);
  twin of ``LocalMapMatcher._match_and_optimise_reference``.
- ``count_seen_kernel``: the visible / found statistics of the local map's points.
- ``unroll_kernel``: the rolling-shutter correction of the keypoints; twin of
  ``features._unroll_rolling_shutter``.

Disabled with ``MEMGS_DISABLE_NUMBA=1`` (or when numba is missing); ``numba_available`` says which
path runs. Compiled on first use and cached on disk (``cache=True``). This module holds the
kernels' bodies, which call each other and so stay in one file (numba's disk cache does not see a
change in another file's kernel); their Python entry points, which fix the array layouts, and
``warm_up`` are in ``kernel_calls``.
"""
from __future__ import annotations

import numpy as np

from memgs_ros.core.runtime.cpu import numba_available  # noqa: F401 - re-exported

__all__ = ["numba_available"]  # the kernels' entry points are ``kernel_calls``'s


# Search windows of up to this many grid cells are read whole rather than ring by ring: the
# tight second pass (4 px at octave 0) then gathers its ~8 candidates without the rings'
# bookkeeping or a sorted insertion per candidate (that pass 0.73 -> 0.56 ms on fr1/rpy).
_GATHER_CELLS = 16


def _popcount64(x):
    """Bits set in a uint64 (SWAR)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


def _hamming256(a, i, b, j):
    """Hamming distance of packed 256-bit descriptors a[i] and b[j] ([., 4] uint64 each)."""
    return (_popcount64(a[i, 0] ^ b[j, 0]) + _popcount64(a[i, 1] ^ b[j, 1])
            + _popcount64(a[i, 2] ^ b[j, 2]) + _popcount64(a[i, 3] ^ b[j, 3]))


def _bucket(kp_uv, cell_px, gx, gy):
    """Keypoints [M, 2] bucketed by grid cell (counting sort): (start [gx * gy + 1] of each cell's
    run, order [M] keypoint of each bucket slot, su / sv [M] their positions in bucket order, which
    the scan reads contiguously). Coordinates outside the grid are clamped into its border cells,
    so every keypoint sits in exactly one cell."""
    M = kp_uv.shape[0]
    cell_of = np.empty(M, np.int64)
    start = np.zeros(gx * gy + 1, np.int64)
    for j in range(M):
        cx = min(max(int(np.floor(kp_uv[j, 0] / cell_px)), 0), gx - 1)
        cy = min(max(int(np.floor(kp_uv[j, 1] / cell_px)), 0), gy - 1)
        cell_of[j] = cy * gx + cx
        start[cell_of[j] + 1] += 1
    for c in range(gx * gy):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(M, np.int64)
    for j in range(M):
        order[fill[cell_of[j]]] = j
        fill[cell_of[j]] += 1
    su = np.empty(M, np.float64)
    sv = np.empty(M, np.float64)
    for s in range(M):
        su[s] = kp_uv[order[s], 0]
        sv[s] = kp_uv[order[s], 1]
    return start, order, su, sv


def _nearest(u, v, r, start, su, sv, cell_px, gx, gy, K, cand_d2, cand_s):
    """The (at most) ``K`` bucketed keypoints nearest to (u, v) within radius ``r`` by (distance,
    bucket slot), into cand_d2 / cand_s (at least as long as the keypoints, plus one); returns how
    many. Their order there is (distance, slot) where the window is wide, any order otherwise.

    A window of up to ``_GATHER_CELLS`` cells is gathered whole (``_gather``). A wider one is
    scanned in rings around the point's own cell, and the scan stops once it holds ``K`` keypoints
    nearer than anything a further ring could hold: with a wide radius (15 px at octave 0, 54 px at
    octave 7) most of the window lies beyond the nearest candidates. (distance, slot) is the order
    a row-major scan of the whole window meets them, so ties resolve as the reference's stable sort.
    """
    r2 = r * r
    n = 0
    x0 = min(max(int(np.floor((u - r) / cell_px)), 0), gx - 1)
    x1 = min(max(int(np.floor((u + r) / cell_px)), 0), gx - 1)
    y0 = min(max(int(np.floor((v - r) / cell_px)), 0), gy - 1)
    y1 = min(max(int(np.floor((v + r) / cell_px)), 0), gy - 1)
    if (x1 - x0 + 1) * (y1 - y0 + 1) <= _GATHER_CELLS:
        return _gather(u, v, r2, start, su, sv, x0, x1, y0, y1, gx, K, cand_d2, cand_s)
    pcx = min(max(int(np.floor(u / cell_px)), x0), x1)
    pcy = min(max(int(np.floor(v / cell_px)), y0), y1)
    rmax = max(pcx - x0, x1 - pcx, pcy - y0, y1 - pcy)
    for R in range(rmax + 1):
        for cy in range(max(pcy - R, y0), min(pcy + R, y1) + 1):
            if cy == pcy - R or cy == pcy + R:  # a ring's top or bottom row: all of it
                cx_first, cx_step, cx_count = pcx - R, 1, 2 * R + 1
            else:  # a row in between: its two ends
                cx_first, cx_step, cx_count = pcx - R, 2 * R, 2
            for t in range(cx_count):
                cx = cx_first + t * cx_step
                if cx < x0 or cx > x1:
                    continue
                c = cy * gx + cx
                for s in range(start[c], start[c + 1]):
                    du = su[s] - u
                    dv = sv[s] - v
                    d2 = du * du + dv * dv
                    if d2 > r2:
                        continue
                    # Kept sorted by (distance, slot), at most K: insertion from the end.
                    if n < K:
                        q = n
                        n += 1
                    elif d2 < cand_d2[K - 1] or (d2 == cand_d2[K - 1] and s < cand_s[K - 1]):
                        q = K - 1
                    else:
                        continue
                    while q > 0 and (cand_d2[q - 1] > d2 or (cand_d2[q - 1] == d2 and cand_s[q - 1] > s)):
                        cand_d2[q] = cand_d2[q - 1]
                        cand_s[q] = cand_s[q - 1]
                        q -= 1
                    cand_d2[q] = d2
                    cand_s[q] = s
        # Every cell of a further ring lies beyond this block's open sides.
        dmin = 1e300
        if pcx - R > x0:
            dmin = min(dmin, u - (pcx - R) * cell_px)
        if pcx + R < x1:
            dmin = min(dmin, (pcx + R + 1) * cell_px - u)
        if pcy - R > y0:
            dmin = min(dmin, v - (pcy - R) * cell_px)
        if pcy + R < y1:
            dmin = min(dmin, (pcy + R + 1) * cell_px - v)
        if dmin >= 1e300 or dmin > r or (n == K and dmin * dmin > cand_d2[K - 1]):
            break
    return n


def _gather(u, v, r2, start, su, sv, x0, x1, y0, y1, gx, K, cand_d2, cand_s):
    """``_nearest`` over the window of cells x0..x1, y0..y1 read whole: every keypoint within
    sqrt(r2) into cand_d2 / cand_s (written for each keypoint read, kept by the count: no branch
    to mispredict), then, only when more than ``K``, the K nearest by (distance, slot), in order."""
    n = 0
    for cy in range(y0, y1 + 1):  # a window row's cells are one run of bucket slots
        for s in range(start[cy * gx + x0], start[cy * gx + x1 + 1]):
            du = su[s] - u
            dv = sv[s] - v
            d2 = du * du + dv * dv
            cand_d2[n] = d2
            cand_s[n] = s
            n += d2 <= r2
    if n <= K:
        return n
    # The first K sorted, then each later one inserted when nearer than the K-th: the slots came
    # ascending, so stable insertions by distance order by (distance, slot).
    for a in range(1, n):
        d2 = cand_d2[a]
        if a >= K and not d2 < cand_d2[K - 1]:
            continue
        s = cand_s[a]
        q = min(a, K - 1)
        while q > 0 and cand_d2[q - 1] > d2:
            cand_d2[q] = cand_d2[q - 1]
            cand_s[q] = cand_s[q - 1]
            q -= 1
        cand_d2[q] = d2
        cand_s[q] = s
    return K


def _best_two(pd, i, kd, order, cand_d2, cand_s, n, available):
    """(keypoint, best, second best Hamming) of point ``i`` among its ``n`` candidates in any
    order; a tie on the best goes to the nearest, then the lower slot (the reference sorts by
    distance stably within a point); keypoint -1 for none."""
    b1 = np.int64(1 << 30)
    b2 = np.int64(1 << 30)
    bj = -1
    bd = np.inf
    bs = -1
    for q in range(n):
        s = cand_s[q]
        j = order[s]
        if not available[j]:
            continue
        h = _hamming256(pd, i, kd, j)
        d2 = cand_d2[q]
        if h < b1 or (h == b1 and (d2 < bd or (d2 == bd and s < bs))):
            b2 = b1
            b1 = h
            bj = j
            bd = d2
            bs = s
        elif h < b2:
            b2 = h
    return bj, b1, b2


def _one_per_keypoint(best_k, best_d, M):
    """One point per keypoint (the lowest distance, then the lowest point index): (point [K],
    keypoint [K], Hamming [K]) sorted by keypoint."""
    owner = np.full(M, -1, np.int64)
    for i in range(best_k.shape[0]):
        j = best_k[i]
        if j >= 0 and (owner[j] < 0 or best_d[i] < best_d[owner[j]]):
            owner[j] = i
    n_out = 0
    for j in range(M):
        if owner[j] >= 0:
            n_out += 1
    out_p = np.empty(n_out, np.int64)
    out_k = np.empty(n_out, np.int64)
    out_d = np.empty(n_out, np.int64)
    q = 0
    for j in range(M):
        if owner[j] >= 0:
            out_p[q] = owner[j]
            out_k[q] = j
            out_d[q] = best_d[owner[j]]
            q += 1
    return out_p, out_k, out_d


def _match(proj_uv, radius, point_desc, kp_uv, kp_desc, available, max_distance, ratio,
           max_candidates, cell_px, width, height):
    """Body of ``match_by_projection_kernel`` (see there): each point's nearest keypoints
    (``_nearest``), the ratio test on their Hamming distances (``_best_two``), then one point per
    keypoint."""
    P = proj_uv.shape[0]
    gx = max(1, int(np.ceil(width / cell_px)))
    gy = max(1, int(np.ceil(height / cell_px)))
    start, order, su, sv = _bucket(kp_uv, cell_px, gx, gy)
    pd = point_desc.view(np.uint64)  # [P, 4]
    kd = kp_desc.view(np.uint64)  # [M, 4]
    cand_d2 = np.empty(kp_uv.shape[0] + 1, np.float64)  # _gather writes each keypoint it reads
    cand_s = np.empty(kp_uv.shape[0] + 1, np.int64)
    best_k = np.full(P, -1, np.int64)
    best_d = np.zeros(P, np.int64)
    for i in range(P):
        n = _nearest(proj_uv[i, 0], proj_uv[i, 1], radius[i], start, su, sv, cell_px, gx, gy, max_candidates,
                     cand_d2, cand_s)
        bj, b1, b2 = _best_two(pd, i, kd, order, cand_d2, cand_s, n, available)
        if bj >= 0 and b1 <= max_distance and b1 <= ratio * (b2 if b2 < (1 << 30) else 1e9):
            best_k[i] = bj
            best_d[i] = b1
    return _one_per_keypoint(best_k, best_d, kp_uv.shape[0])


def _left_update(T, xi):
    """T [4, 4] <- Exp(w) T with t += v (exact Rodrigues)."""
    w0, w1, w2 = xi[0], xi[1], xi[2]
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    th = np.sqrt(th2)
    if th < 1e-8:
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
    else:
        a = np.sin(th) / th
        b = (1.0 - np.cos(th)) / th2
    R = np.empty((3, 3))
    R[0, 0] = 1.0 - b * (w1 * w1 + w2 * w2)
    R[1, 1] = 1.0 - b * (w0 * w0 + w2 * w2)
    R[2, 2] = 1.0 - b * (w0 * w0 + w1 * w1)
    R[0, 1] = -a * w2 + b * w0 * w1
    R[1, 0] = a * w2 + b * w0 * w1
    R[0, 2] = a * w1 + b * w0 * w2
    R[2, 0] = -a * w1 + b * w0 * w2
    R[1, 2] = -a * w0 + b * w1 * w2
    R[2, 1] = a * w0 + b * w1 * w2
    out = np.eye(4)
    for r in range(3):
        for c in range(3):
            out[r, c] = R[r, 0] * T[0, c] + R[r, 1] * T[1, c] + R[r, 2] * T[2, c]
        out[r, 3] = R[r, 0] * T[0, 3] + R[r, 1] * T[1, 3] + R[r, 2] * T[2, 3] + xi[3 + r]
    return out


def _camera_point(T, p, i):
    """Point ``p[i]`` [3] in the camera T [4, 4] maps it into: (x, y, z)."""
    x = T[0, 0] * p[i, 0] + T[0, 1] * p[i, 1] + T[0, 2] * p[i, 2] + T[0, 3]
    y = T[1, 0] * p[i, 0] + T[1, 1] * p[i, 1] + T[1, 2] * p[i, 2] + T[1, 3]
    z = T[2, 0] * p[i, 0] + T[2, 1] * p[i, 1] + T[2, 2] * p[i, 2] + T[2, 3]
    return x, y, z


def _residual(x, y, z, obs, has_depth, i, fx, fy, cx, cy, bf):
    """Predicted minus observed (u, v, u - bf/z) of observation ``i`` at camera point (x, y, z); the
    third is 0 without depth."""
    iz = 1.0 / z
    u = fx * x * iz + cx
    v = fy * y * iz + cy
    r2 = (u - bf * iz) - obs[i, 2] if has_depth[i] else 0.0
    return u - obs[i, 0], v - obs[i, 1], r2


def _add_row(H, g, wt, rk, j0, j1, j2, j3, j4, j5):
    """One weighted row (j0..j5, residual ``rk``) of the normal equations into the upper triangle of
    H [6, 6] and into g [6], unrolled: the generic loop's products in its order, bit for bit."""
    w0 = wt * j0
    w1 = wt * j1
    w2 = wt * j2
    w3 = wt * j3
    w4 = wt * j4
    w5 = wt * j5
    g[0] += w0 * rk
    g[1] += w1 * rk
    g[2] += w2 * rk
    g[3] += w3 * rk
    g[4] += w4 * rk
    g[5] += w5 * rk
    H[0, 0] += w0 * j0
    H[0, 1] += w0 * j1
    H[0, 2] += w0 * j2
    H[0, 3] += w0 * j3
    H[0, 4] += w0 * j4
    H[0, 5] += w0 * j5
    H[1, 1] += w1 * j1
    H[1, 2] += w1 * j2
    H[1, 3] += w1 * j3
    H[1, 4] += w1 * j4
    H[1, 5] += w1 * j5
    H[2, 2] += w2 * j2
    H[2, 3] += w2 * j3
    H[2, 4] += w2 * j4
    H[2, 5] += w2 * j5
    H[3, 3] += w3 * j3
    H[3, 4] += w3 * j4
    H[3, 5] += w3 * j5
    H[4, 4] += w4 * j4
    H[4, 5] += w4 * j5
    H[5, 5] += w5 * j5


def _accumulate(H, g, x, y, z, r0, r1, r2, depth, wt, fx, fy, bf):
    """Add one observation's weighted rows of [-Jp [p_c]_x, Jp] (u, v and, with ``depth``,
    u - bf/z) to the upper triangle of H [6, 6] and to g [6]."""
    iz = 1.0 / z
    # Nonzero entries of Jp = d(u, v, u - bf/z) / d p_c; a u-like row is (a02 y, a00 z - a02 x,
    # -a00 y, a00, 0, a02) with a02 its own (u's, or the virtual right image's a22).
    a00 = fx * iz
    a02 = -fx * x * iz * iz
    a11 = fy * iz
    a12 = -fy * y * iz * iz
    _add_row(H, g, wt, r0, a02 * y, a00 * z - a02 * x, -a00 * y, a00, 0.0, a02)
    _add_row(H, g, wt, r1, -a11 * z + a12 * y, -a12 * x, a11 * x, 0.0, a11, a12)
    if depth:
        a22 = a02 + bf * iz * iz
        _add_row(H, g, wt, r2, a22 * y, a00 * z - a22 * x, -a00 * y, a00, 0.0, a22)


def _normal_equations(T, p_w, obs, has_depth, w2, use, robust, fx, fy, cx, cy, bf, d_mono, d_stereo):
    """Gauss-Newton's H [6, 6] (symmetric, 1e-9 on the diagonal) and g [6] at T over the used
    observations, Huber-weighted when ``robust``."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    for i in range(p_w.shape[0]):
        if not use[i]:
            continue
        x, y, z = _camera_point(T, p_w, i)
        z = max(z, 1e-6)
        r0, r1, r2 = _residual(x, y, z, obs, has_depth, i, fx, fy, cx, cy, bf)
        chi2 = w2[i] * (r0 * r0 + r1 * r1 + r2 * r2)
        wt = w2[i]
        if robust:
            delta = d_stereo if has_depth[i] else d_mono
            e = np.sqrt(chi2)
            if e > delta:
                wt *= delta / max(e, 1e-12)
        _accumulate(H, g, x, y, z, r0, r1, r2, has_depth[i], wt, fx, fy, bf)
    for a in range(6):
        H[a, a] += 1e-9
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g


def _classify(T, p_w, obs, has_depth, w2, inlier, fx, fy, cx, cy, bf, th_mono, th_stereo):
    """Mark each observation an inlier at T (in front, chi-square under its bound), in place;
    returns how many changed."""
    n_changed = 0
    for i in range(p_w.shape[0]):
        x, y, z = _camera_point(T, p_w, i)
        front = z > 1e-6
        if not front:
            z = 1.0
        r0, r1, r2 = _residual(x, y, z, obs, has_depth, i, fx, fy, cx, cy, bf)
        chi2 = w2[i] * (r0 * r0 + r1 * r1 + r2 * r2)
        ok = front and chi2 < (th_stereo if has_depth[i] else th_mono)
        n_changed += ok != inlier[i]
        inlier[i] = ok
    return n_changed


def _optimize(T0, p_w, obs, has_depth, w2, fx, fy, cx, cy, bf, th_mono, th_stereo, rounds, iterations):
    """Body of ``optimize_pose_kernel``; step for step ``bundle_adjustment._optimize_pose``."""
    N = p_w.shape[0]
    T = T0.copy()
    inlier = np.ones(N, np.bool_)
    d_mono = np.sqrt(th_mono)
    d_stereo = np.sqrt(th_stereo)
    for rnd in range(rounds):
        use = inlier.copy()
        n_use = 0
        for i in range(N):
            n_use += use[i]
        if n_use < 4:
            break
        robust = rounds == 1 or rnd < rounds - 1
        for _ in range(iterations):
            H, g = _normal_equations(T, p_w, obs, has_depth, w2, use, robust, fx, fy, cx, cy, bf, d_mono,
                                     d_stereo)
            dx = -np.linalg.solve(H, g)
            if not np.all(np.isfinite(dx)):
                break
            T = _left_update(T, dx)
            if np.sqrt(np.sum(dx * dx)) < 1e-5:
                break
        n_changed = _classify(T, p_w, obs, has_depth, w2, inlier, fx, fy, cx, cy, bf, th_mono, th_stereo)
        if n_changed == 0 and rnd < rounds - 1:
            break  # the same set again: more rounds would repeat this one
    return T, inlier


def _project(pos, pid, T, view):
    """Pixel (u, v) of store point ``pid`` at pose T and whether it is in view: in front of the
    camera by more than view[6] and inside the view[4] x view[5] image; view = (fx, fy, cx, cy,
    width, height, min_z). Twin of ``LocalMapMatcher.project`` for one point."""
    x, y, z = _camera_point(T, pos, pid)
    front = z > view[6]
    zs = z if front else 1.0
    u = view[0] * x / zs + view[2]
    v = view[1] * y / zs + view[3]
    return u, v, front and u >= 0.0 and u < view[4] and v >= 0.0 and v < view[5]


def _in_view(pos, pids, T, view):
    """Indices q [V] (ascending) of the points pids[q] in view at T, and their pixels [V, 2]."""
    P = pids.shape[0]
    idx = np.empty(P, np.int64)
    uv = np.empty((P, 2))
    n = 0
    for q in range(P):
        u, v, ok = _project(pos, pids[q], T, view)
        if ok:
            idx[n] = q
            uv[n, 0] = u
            uv[n, 1] = v
            n += 1
    return idx[:n], uv[:n]


def _track_pass(pos, desc, octave, pids, T0, view, radius_px, inv_sigma_levels, kp_uv, kp_desc, kp_obs,
                kp_has_depth, kp_w2, max_distance, ratio, max_candidates, cell_px, bf, th_mono, th_stereo,
                rounds, iterations):
    """Body of ``track_pass_kernel`` (see there)."""
    idx, uv = _in_view(pos, pids, T0, view)
    V = idx.shape[0]
    M = kp_uv.shape[0]
    if V == 0 or M == 0:
        empty = np.zeros(0, np.int64)
        return T0.copy(), empty, empty.copy(), np.zeros(0, np.bool_)
    last = inv_sigma_levels.shape[0] - 1
    radius = np.empty(V)
    pdesc = np.empty((V, desc.shape[1]), np.uint8)
    width = kp_uv[0, 0]
    height = kp_uv[0, 1]
    for j in range(M):  # the grid covers the keypoints and the projections
        width = max(width, kp_uv[j, 0])
        height = max(height, kp_uv[j, 1])
    for k in range(V):
        pid = pids[idx[k]]
        radius[k] = radius_px / inv_sigma_levels[min(max(octave[pid], 0), last)]
        pdesc[k] = desc[pid]
        width = max(width, uv[k, 0])
        height = max(height, uv[k, 1])
    gw = int(np.ceil(max(width + 1.0, 1.0)))
    gh = int(np.ceil(max(height + 1.0, 1.0)))
    mp, mk, _ = _match(uv, radius, pdesc, kp_uv, kp_desc, np.ones(M, np.bool_), max_distance, ratio,
                       min(max_candidates, M), cell_px, gw, gh)
    pi = idx[mp]
    K = pi.shape[0]
    if K < 4:
        return T0.copy(), pi, mk, np.zeros(K, np.bool_)
    p_w = np.empty((K, 3))
    obs = np.empty((K, 3))
    has_depth = np.empty(K, np.bool_)
    w2 = np.empty(K)
    for k in range(K):
        p_w[k] = pos[pids[pi[k]]]
        obs[k] = kp_obs[mk[k]]
        has_depth[k] = kp_has_depth[mk[k]]
        w2[k] = kp_w2[mk[k]]
    T, inlier = _optimize(T0, p_w, obs, has_depth, w2, view[0], view[1], view[2], view[3], bf, th_mono,
                          th_stereo, rounds, iterations)
    return T, pi, mk, inlier


def _count_seen(pos, pids, T, view, found, n_visible, n_found):
    """Add one to n_visible of the points pids in view at T and to n_found of ``found``, in place."""
    for q in range(pids.shape[0]):
        if _project(pos, pids[q], T, view)[2]:
            n_visible[pids[q]] += 1
    for k in range(found.shape[0]):
        n_found[found[k]] += 1


def _unroll(uv_raw, uv, K, omega, readout_s, height):
    """Body of ``unroll_kernel``; element for element ``features._unroll_rolling_shutter``."""
    M = uv.shape[0]
    out = np.empty((M, 2))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for m in range(M):
        s = (np.float64(uv_raw[m, 1]) - 0.5 * (height - 1)) / height * readout_s
        r0, r1, r2 = s * omega[0], s * omega[1], s * omega[2]
        theta2 = r0 * r0 + r1 * r1 + r2 * r2
        a = 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0
        b = 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0
        x0 = (uv[m, 0] - cx) / fx
        x1 = (uv[m, 1] - cy) / fy
        c0, c1, c2 = r1 - r2 * x1, r2 * x0 - r0, r0 * x1 - r1 * x0
        y0 = x0 + a * c0 + b * (r1 * c2 - r2 * c1)
        y1 = x1 + a * c1 + b * (r2 * c0 - r0 * c2)
        y2 = 1.0 + a * c2 + b * (r0 * c1 - r1 * c0)
        out[m, 0] = fx * y0 / y2 + cx
        out[m, 1] = fy * y1 / y2 + cy
    return out


def _words(desc, centres, branching, depth):
    """Vocabulary words [M] of packed descriptors desc [M, 4] uint64: descend the tree of centres
    [sum of branching ** (l + 1) over levels, 4] uint64 (level after level; node i's children are
    nodes i * branching + j of the next level), at each level to the child at the least Hamming
    distance, the first of equals (as argmax of the +-1 dot products picks)."""
    m = desc.shape[0]
    out = np.empty(m, np.int64)
    for i in range(m):
        node = 0
        offset = 0
        width = branching  # nodes of the level
        for lvl in range(depth):
            first = node * branching if lvl else 0
            best = 257
            pick = first
            for j in range(first, first + branching):
                d = _hamming256(desc, i, centres, offset + j)
                if d < best:
                    best = d
                    pick = j
            node = pick
            offset += width
            width *= branching
        out[i] = node
    return out


if numba_available():
    import numba

    # Module-level functions so that cache=True can key them (closures recompile every process).
    _jit = numba.njit(cache=True, nogil=True)
    # The helpers of the kernels are inlined into them (numba IR): called per candidate or per
    # observation, an out-of-line call made the matcher 2.5 times slower.
    _inl = numba.njit(cache=True, nogil=True, inline="always")
    _popcount64 = _inl(_popcount64)
    _hamming256 = _inl(_hamming256)
    _bucket = _jit(_bucket)
    _nearest = _jit(_nearest)
    _gather = _jit(_gather)
    _best_two = _jit(_best_two)
    _one_per_keypoint = _jit(_one_per_keypoint)
    _match = _jit(_match)
    _left_update = _jit(_left_update)
    _camera_point = _inl(_camera_point)
    _residual = _inl(_residual)
    _add_row = _inl(_add_row)
    _accumulate = _inl(_accumulate)
    _normal_equations = _jit(_normal_equations)
    _classify = _jit(_classify)
    _optimize = _jit(_optimize)
    _project = _inl(_project)
    _in_view = _jit(_in_view)
    _track_pass = _jit(_track_pass)
    _count_seen = _jit(_count_seen)
    _unroll = _jit(_unroll)
    _words = _jit(_words)
