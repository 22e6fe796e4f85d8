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

Disabled with ``MEMGS_DISABLE_NUMBA=1`` (or when numba is missing); ``numba_available`` says which
path runs. Compiled on first use and cached on disk (``cache=True``).
"""
from __future__ import annotations

import numpy as np

from memgs_ros.core.runtime.cpu import numba_available  # noqa: F401 - re-exported
from memgs_ros.core.tracking import orb

__all__ = ["match_by_projection_kernel", "numba_available", "optimize_pose_kernel", "warm_up"]


def _popcount64(x):
    """Bits set in a uint64 (SWAR)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


def _match(proj_uv, radius, point_desc, kp_uv, kp_desc, available, max_distance, ratio,
           max_candidates, cell_px, width, height):
    """Body of ``match_by_projection_kernel`` (see there).

    Each point scans the cells of its search window in rings around its own cell and stops once
    it holds ``max_candidates`` keypoints nearer than anything a further ring could hold: with a
    wide radius (15 px at octave 0, 54 px at octave 7) most of the window lies beyond the nearest
    candidates. Candidates rank by (distance, bucket position), the order a row-major scan of
    the whole window meets them, so ties resolve as the reference's stable sort.
    """
    P = proj_uv.shape[0]
    M = kp_uv.shape[0]
    # Keypoints bucketed by cell (counting sort); coordinates outside the image are clamped
    # into the border cells, so every keypoint sits in exactly one cell.
    gx = max(1, int(np.ceil(width / cell_px)))
    gy = max(1, int(np.ceil(height / cell_px)))
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
    # Keypoint positions in bucket order: the scan reads them contiguously.
    su = np.empty(M, np.float64)
    sv = np.empty(M, np.float64)
    for s in range(M):
        su[s] = kp_uv[order[s], 0]
        sv[s] = kp_uv[order[s], 1]
    pd = point_desc.view(np.uint64)  # [P, 4]
    kd = kp_desc.view(np.uint64)  # [M, 4]
    K = max_candidates
    cand_d2 = np.empty(K, np.float64)
    cand_s = np.empty(K, np.int64)
    best_k = np.full(P, -1, np.int64)
    best_d = np.zeros(P, np.int64)
    for i in range(P):
        u, v, r = proj_uv[i, 0], proj_uv[i, 1], radius[i]
        r2 = r * r
        n = 0
        x0 = min(max(int(np.floor((u - r) / cell_px)), 0), gx - 1)
        x1 = min(max(int(np.floor((u + r) / cell_px)), 0), gx - 1)
        y0 = min(max(int(np.floor((v - r) / cell_px)), 0), gy - 1)
        y1 = min(max(int(np.floor((v + r) / cell_px)), 0), gy - 1)
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
                        # The K nearest by (distance, bucket position): the row-major scan's order.
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
        # Best and second best Hamming among the candidates, nearest first on ties (the
        # reference sorts by distance stably within a point).
        b1 = np.int64(1 << 30)
        b2 = np.int64(1 << 30)
        bj = -1
        for q in range(n):
            j = order[cand_s[q]]
            if not available[j]:
                continue
            h = (_popcount64(pd[i, 0] ^ kd[j, 0]) + _popcount64(pd[i, 1] ^ kd[j, 1])
                 + _popcount64(pd[i, 2] ^ kd[j, 2]) + _popcount64(pd[i, 3] ^ kd[j, 3]))
            if h < b1:
                b2 = b1
                b1 = h
                bj = j
            elif h < b2:
                b2 = h
        if bj >= 0 and b1 <= max_distance and b1 <= ratio * (b2 if b2 < (1 << 30) else 1e9):
            best_k[i] = bj
            best_d[i] = b1
    # One point per keypoint: the lowest distance, then the lowest point index.
    owner = np.full(M, -1, np.int64)
    for i in range(P):
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


def _optimize(T0, p_w, obs, has_depth, w2, fx, fy, cx, cy, bf, th_mono, th_stereo, rounds, iterations):
    """Body of ``optimize_pose_kernel``; step for step ``bundle_adjustment._optimize_pose``."""
    N = p_w.shape[0]
    T = T0.copy()
    inlier = np.ones(N, np.bool_)
    d_mono = np.sqrt(th_mono)
    d_stereo = np.sqrt(th_stereo)
    J = np.zeros((3, 6))
    for rnd in range(rounds):
        use = inlier.copy()
        n_use = 0
        for i in range(N):
            n_use += use[i]
        if n_use < 4:
            break
        robust = rounds == 1 or rnd < rounds - 1
        for _ in range(iterations):
            H = np.zeros((6, 6))
            g = np.zeros(6)
            for i in range(N):
                if not use[i]:
                    continue
                x = T[0, 0] * p_w[i, 0] + T[0, 1] * p_w[i, 1] + T[0, 2] * p_w[i, 2] + T[0, 3]
                y = T[1, 0] * p_w[i, 0] + T[1, 1] * p_w[i, 1] + T[1, 2] * p_w[i, 2] + T[1, 3]
                z = T[2, 0] * p_w[i, 0] + T[2, 1] * p_w[i, 1] + T[2, 2] * p_w[i, 2] + T[2, 3]
                z = max(z, 1e-6)
                iz = 1.0 / z
                u = fx * x * iz + cx
                v = fy * y * iz + cy
                r0 = u - obs[i, 0]
                r1 = v - obs[i, 1]
                r2 = (u - bf * iz) - obs[i, 2] if has_depth[i] else 0.0
                chi2 = w2[i] * (r0 * r0 + r1 * r1 + r2 * r2)
                wt = w2[i]
                if robust:
                    delta = d_stereo if has_depth[i] else d_mono
                    e = np.sqrt(chi2)
                    if e > delta:
                        wt *= delta / max(e, 1e-12)
                # Nonzero entries of Jp = d(u, v, u - bf/z) / d p_c.
                a00 = fx * iz
                a02 = -fx * x * iz * iz
                a11 = fy * iz
                a12 = -fy * y * iz * iz
                a22 = a02 + bf * iz * iz
                # Rows of [-Jp [p_c]_x, Jp] for u, v and (where depth was measured) u - bf/z.
                J[0, 0] = a02 * y
                J[0, 1] = a00 * z - a02 * x
                J[0, 2] = -a00 * y
                J[0, 3] = a00
                J[0, 4] = 0.0
                J[0, 5] = a02
                J[1, 0] = -a11 * z + a12 * y
                J[1, 1] = -a12 * x
                J[1, 2] = a11 * x
                J[1, 3] = 0.0
                J[1, 4] = a11
                J[1, 5] = a12
                rows = 2
                if has_depth[i]:
                    J[2, 0] = a22 * y
                    J[2, 1] = a00 * z - a22 * x
                    J[2, 2] = -a00 * y
                    J[2, 3] = a00
                    J[2, 4] = 0.0
                    J[2, 5] = a22
                    rows = 3
                for k in range(rows):
                    rk = r0 if k == 0 else (r1 if k == 1 else r2)
                    for a in range(6):
                        ja = wt * J[k, a]
                        g[a] += ja * rk
                        for b in range(a, 6):
                            H[a, b] += ja * J[k, b]
            for a in range(6):
                H[a, a] += 1e-9
                for b in range(a):
                    H[a, b] = H[b, a]
            dx = -np.linalg.solve(H, g)
            if not np.all(np.isfinite(dx)):
                break
            T = _left_update(T, dx)
            if np.sqrt(np.sum(dx * dx)) < 1e-5:
                break
        n_changed = 0
        for i in range(N):
            x = T[0, 0] * p_w[i, 0] + T[0, 1] * p_w[i, 1] + T[0, 2] * p_w[i, 2] + T[0, 3]
            y = T[1, 0] * p_w[i, 0] + T[1, 1] * p_w[i, 1] + T[1, 2] * p_w[i, 2] + T[1, 3]
            z = T[2, 0] * p_w[i, 0] + T[2, 1] * p_w[i, 1] + T[2, 2] * p_w[i, 2] + T[2, 3]
            front = z > 1e-6
            if not front:
                z = 1.0
            iz = 1.0 / z
            u = fx * x * iz + cx
            v = fy * y * iz + cy
            r0 = u - obs[i, 0]
            r1 = v - obs[i, 1]
            r2 = (u - bf * iz) - obs[i, 2] if has_depth[i] else 0.0
            chi2 = w2[i] * (r0 * r0 + r1 * r1 + r2 * r2)
            ok = front and chi2 < (th_stereo if has_depth[i] else th_mono)
            n_changed += ok != inlier[i]
            inlier[i] = ok
        if n_changed == 0 and rnd < rounds - 1:
            break  # the same set again: more rounds would repeat this one
    return T, inlier


def _solve6(H, g):
    """-H^-1 g for a symmetric 6x6 H by Cholesky (NaN when H is not positive definite)."""
    L = np.zeros((6, 6))
    for i in range(6):
        for j in range(i + 1):
            acc = H[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if acc <= 0.0:
                    return np.full(6, np.nan)
                L[i, i] = np.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    y = np.empty(6)
    for i in range(6):
        acc = -g[i]
        for k in range(i):
            acc -= L[i, k] * y[k]
        y[i] = acc / L[i, i]
    x = np.empty(6)
    for i in range(5, -1, -1):
        acc = y[i]
        for k in range(i + 1, 6):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return x




if numba_available():
    import numba

    # Module-level functions so that cache=True can key them (closures recompile every process).
    _jit = numba.njit(cache=True, nogil=True)
    _popcount64 = _jit(_popcount64)
    _solve6 = _jit(_solve6)
    _left_update = _jit(_left_update)
    _match = _jit(_match)
    _optimize = _jit(_optimize)


def _arg(a: np.ndarray, dtype: type) -> np.ndarray:
    """The one array layout the kernels are compiled for: C-contiguous, writable, ``dtype``. numba
    compiles a signature per layout, and a read-only array (a view a caller kept read-only) made a
    live run's first frame compile a second one for 1.7 s."""
    out: np.ndarray = np.ascontiguousarray(a, dtype)
    return out if out.flags.writeable else out.copy()


def match_by_projection_kernel(proj_uv: np.ndarray, radius: np.ndarray, point_desc: np.ndarray,
                               kp_uv: np.ndarray, kp_desc: np.ndarray, available: np.ndarray,
                               max_distance: int, ratio: float, max_candidates: int, cell_px: float,
                               width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compiled ``_match_by_projection``. proj_uv: [P, 2] float64; radius: [P] float64;
    point_desc: [P, 32] uint8; kp_uv: [M, 2] float64; kp_desc: [M, 32] uint8; available: [M] bool;
    cell_px: grid cell size; width/height: the image the keypoints lie in (cells outside are clamped).
    Returns (point_index [K], keypoint_index [K], hamming [K]) int64, sorted by keypoint index."""
    return _match(_arg(proj_uv, np.float64), _arg(radius, np.float64), _arg(point_desc, np.uint8),
                  _arg(kp_uv, np.float64), _arg(kp_desc, np.uint8), _arg(available, np.bool_),
                  int(max_distance), float(ratio), int(max_candidates), float(cell_px), int(width), int(height))


def optimize_pose_kernel(T_cw: np.ndarray, p_w: np.ndarray, obs_uvr: np.ndarray, has_depth: np.ndarray,
                         w2: np.ndarray, K: np.ndarray, bf: float, th_mono: float, th_stereo: float,
                         rounds: int, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Compiled core of ``_optimize_pose``. T_cw: [4, 4]; p_w: [N, 3]; obs_uvr: [N, 3] (u, v, u - bf/z);
    has_depth: [N] bool; w2: [N] squared 1/sigma. Returns (T_cw [4, 4] not re-orthonormalised, inlier [N])."""
    return _optimize(_arg(T_cw, np.float64), _arg(p_w, np.float64), _arg(obs_uvr, np.float64),
                     _arg(has_depth, np.bool_), _arg(w2, np.float64), float(K[0, 0]), float(K[1, 1]),
                     float(K[0, 2]), float(K[1, 2]), float(bf), float(th_mono), float(th_stereo),
                     int(rounds), int(iterations))


def warm_up() -> None:
    """Compile (or load from the disk cache) both kernels, and ORB's (``orb.warm_up``), on tiny
    inputs, so that the first tracked frame does not pay for it (~10 s of compilation on first use,
    ~0.2 s from the cache)."""
    if not numba_available():
        return
    orb.warm_up()
    uv = np.array([[10.0, 10.0], [20.0, 20.0]])
    desc = np.zeros((2, 32), np.uint8)
    match_by_projection_kernel(uv, np.full(2, 5.0), desc, uv, desc, np.ones(2, bool), 80, 0.85, 2, 16.0, 32, 32)
    p_w = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0], [1.0, 1.0, 3.0]])
    obs = np.column_stack([p_w[:, :2] / p_w[:, 2:] * 500.0 + 320.0, np.zeros(4)])
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 320.0], [0.0, 0.0, 1.0]])
    optimize_pose_kernel(np.eye(4), p_w, obs, np.zeros(4, bool), np.ones(4), K, 40.0, 5.991, 7.815, 1, 1)
