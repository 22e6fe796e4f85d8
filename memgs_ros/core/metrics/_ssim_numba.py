"""Compiled SSIM kernels (numba); imported only by :mod:`memgs_ros.core.metrics.ssim` when numba is available.

Same definition as :func:`memgs_ros.core.metrics.ssim._ssim_map` (Gaussian window, zero 'same' padding),
computed plane by plane (one plane = one channel of one image) and row by row:

- forward: each input row gives its five statistic rows (x1, x2, x1^2, x2^2, x1 x2), filtered
  horizontally into a ring of K rows; as soon as the K rows around output row y are there, the
  vertical pass gives the five local statistics of row y, and the SSIM of that row follows, with
  the per-pixel factors of the backward pass (dS/dmu1, dS/dE[x1^2] = dS/dE[x2^2], dS/dE[x1 x2]
  and dS/dmu2 as needed) when gradients are wanted. The working set is the ring (K x 5 rows),
  so it stays in cache; nothing of image size is written but the map and those factors.
- backward: the cotangent times each factor, filtered the same way (the window is symmetric,
  so the filter is its own adjoint), gives the image gradient row by row:
  v_img1 = G*(v dS/dmu1) + 2 img1 G*(v dS/dE[x1^2]) + img2 G*(v dS/dE[x1 x2]).

Arithmetic is in the images' dtype (float32 or float64; constants are passed in that dtype, as
Python float literals would promote float32 work to float64). In float32 the map is within
~2e-6 of a float64 evaluation at 320x240 and the gradient within ~5e-7 of its largest entry,
as close as the torch path. One division per pixel. The window must be symmetric (the horizontal
pass adds mirrored taps before multiplying); :func:`memgs_ros.core.metrics.ssim.gaussian_window_1d` is, exactly.

Kernels release the GIL and run on the calling thread (no numba threading layer, see
:mod:`memgs_ros.core.raster.composite_numba` for why).
"""
from __future__ import annotations

import numpy as np
from numba import njit

N_STATS = 5  # x1, x2, x1^2, x2^2, x1 x2
# Factor planes of the forward pass, in this order: dS/dE[x1^2] (= dS/dE[x2^2]), dS/dE[x1 x2],
# then dS/dmu1 when image 1 needs a gradient, then dS/dmu2 when image 2 does.
F_SQ, F_12 = 0, 1


@njit(nogil=True, cache=True, inline="always")
def _hfilter(src: np.ndarray,  # [W + 2 pad] row with pad zeros on each side
             g: np.ndarray,  # [K] symmetric window
             pad: int,
             dst: np.ndarray,  # [W]
             ) -> None:
    """dst[x] = sum_k g[k] src[x + k], taps k and K-1-k added before multiplying.

    The shifted rows are taken as slices: indexing ``src[x + k]`` directly kept LLVM from
    vectorising the loop (5x slower, measured).
    """
    W = dst.shape[0]
    gc = g[pad]
    mid = src[pad:pad + W]
    for x in range(W):
        dst[x] = gc * mid[x]
    for k in range(pad):
        gk = g[k]
        lo = src[k:k + W]
        hi = src[2 * pad - k:2 * pad - k + W]
        for x in range(W):
            dst[x] += gk * (lo[x] + hi[x])


@njit(nogil=True, cache=True, inline="always")
def _vfilter(ring: np.ndarray,  # [K, n_max, W] horizontally filtered rows, row r in slot r % K
             y: int, H: int, n: int,
             g: np.ndarray,  # [K] symmetric window
             dst: np.ndarray,  # [n_max, W]; planes [0, n) are written
             ) -> None:
    """dst[j, x] = sum_k g[k] row(y + k - pad)[j, x] over rows inside [0, H) (zero padding);
    rows y - d and y + d are added before multiplying when both exist."""
    K = g.shape[0]
    pad = K // 2
    W = dst.shape[1]
    gc = g[pad]
    for j in range(n):
        src = ring[y % K, j]
        d = dst[j]
        for x in range(W):
            d[x] = gc * src[x]
    for k in range(pad):
        gk = g[k]
        y_lo = y - pad + k
        y_hi = y + pad - k
        if y_lo >= 0 and y_hi < H:
            for j in range(n):
                lo = ring[y_lo % K, j]
                hi = ring[y_hi % K, j]
                d = dst[j]
                for x in range(W):
                    d[x] += gk * (lo[x] + hi[x])
        elif y_lo >= 0 or y_hi < H:
            yy = y_lo if y_lo >= 0 else y_hi
            for j in range(n):
                src = ring[yy % K, j]
                d = dst[j]
                for x in range(W):
                    d[x] += gk * src[x]


@njit(nogil=True, cache=True, inline="always")
def _ssim_row_value(st: np.ndarray,  # [N_STATS, W] local statistics of one row
                    c1: float, c2: float, one: float, two: float,
                    s_row: np.ndarray,  # [W]
                    ) -> None:
    """SSIM of one row from its local statistics (no backward factors)."""
    mu1, mu2, e11, e22, e12 = st[0], st[1], st[2], st[3], st[4]
    for x in range(s_row.shape[0]):
        mu12 = mu1[x] * mu2[x]
        mu11 = mu1[x] * mu1[x]
        mu22 = mu2[x] * mu2[x]
        num_l = two * mu12 + c1  # A
        num_cs = two * (e12[x] - mu12) + c2  # B
        den_l = mu11 + mu22 + c1  # C
        den_cs = (e11[x] - mu11) + (e22[x] - mu22) + c2  # D
        s_row[x] = num_l * num_cs * (one / (den_l * den_cs))  # as in _ssim_row, bit for bit


@njit(nogil=True, cache=True, inline="always")
def _ssim_row(st: np.ndarray,  # [N_STATS, W] local statistics of one row
              c1: float, c2: float, one: float, two: float,
              s_row: np.ndarray,  # [W] SSIM
              f_sq: np.ndarray,  # [W] dS/dE[x1^2] (= dS/dE[x2^2])
              f_12: np.ndarray,  # [W] dS/dE[x1 x2]
              f_a: np.ndarray, need_a: bool,  # [W] dS/dmu1, written when need_a
              f_b: np.ndarray, need_b: bool,  # [W] dS/dmu2, written when need_b
              ) -> None:
    """SSIM of one row and the factors of the backward pass (see ssim._SsimMapFunction).

    With S = A B / (C D): dS/dmu1 = 2 (mu2 (B - A) / (C D) - mu1 S (1/C - 1/D)),
    dS/dE[x1^2] = -S / D, dS/dE[x1 x2] = 2 A / (C D); symmetrically for image 2. One division
    per pixel: 1/C and 1/D are taken as D/(C D) and C/(C D).
    """
    mu1, mu2, e11, e22, e12 = st[0], st[1], st[2], st[3], st[4]
    for x in range(s_row.shape[0]):
        m1 = mu1[x]
        m2 = mu2[x]
        mu12 = m1 * m2
        mu11 = m1 * m1
        mu22 = m2 * m2
        num_l = two * mu12 + c1  # A
        num_cs = two * (e12[x] - mu12) + c2  # B
        den_l = mu11 + mu22 + c1  # C
        den_cs = (e11[x] - mu11) + (e22[x] - mu22) + c2  # D
        inv_cd = one / (den_l * den_cs)  # the one division; 1/C = D inv_cd, 1/D = C inv_cd
        s = num_l * num_cs * inv_cd
        s_row[x] = s
        f_sq[x] = -s * den_l * inv_cd
        f_12[x] = two * num_l * inv_cd
        t = (num_cs - num_l) * inv_cd
        q = s * (den_cs - den_l) * inv_cd
        if need_a:
            f_a[x] = two * (m2 * t - m1 * q)
        if need_b:
            f_b[x] = two * (m1 * t - m2 * q)


@njit(nogil=True, cache=True)
def ssim_forward(a: np.ndarray,  # [P, H, W] image 1, P = batch x channels
                 b: np.ndarray,  # [P, H, W] image 2, same dtype
                 g: np.ndarray,  # [K] symmetric window, same dtype
                 consts: np.ndarray,  # [2] (c1, c2) in the images' dtype
                 s_out: np.ndarray,  # [P, H, W] SSIM map (written)
                 fac: np.ndarray,  # [P, F, H, W] backward factors, F = 2 + need_a + need_b (unused otherwise)
                 need_a: bool, need_b: bool,
                 ) -> None:
    """SSIM map of every plane; with need_a or need_b also the factor planes (module docstring)."""
    P, H, W = a.shape
    K = g.shape[0]
    pad = K // 2
    want = need_a or need_b
    c1, c2 = consts[0], consts[1]
    one = np.ones(1, dtype=a.dtype)[0]  # 1 and 2 in the images' dtype: float literals would promote to float64
    two = one + one
    i_a = 2
    i_b = 3 if need_a else 2
    rows = np.zeros((N_STATS, W + 2 * pad), dtype=a.dtype)  # zero-padded statistic rows
    ring = np.empty((K, N_STATS, W), dtype=a.dtype)
    st = np.empty((N_STATS, W), dtype=a.dtype)
    for p in range(P):
        for r in range(H + pad):
            if r < H:
                a_row, b_row = a[p, r], b[p, r]
                r0, r1, r2 = rows[0, pad:pad + W], rows[1, pad:pad + W], rows[2, pad:pad + W]
                r3, r4 = rows[3, pad:pad + W], rows[4, pad:pad + W]
                for x in range(W):
                    u = a_row[x]
                    v = b_row[x]
                    r0[x] = u
                    r1[x] = v
                    r2[x] = u * u
                    r3[x] = v * v
                    r4[x] = u * v
                slot = r % K
                for j in range(N_STATS):
                    _hfilter(rows[j], g, pad, ring[slot, j])
            y = r - pad
            if y < 0:
                continue
            _vfilter(ring, y, H, N_STATS, g, st)
            s_row = s_out[p, y]
            if want:
                _ssim_row(st, c1, c2, one, two, s_row, fac[p, F_SQ, y], fac[p, F_12, y],
                          fac[p, i_a, y] if need_a else s_row, need_a,
                          fac[p, i_b, y] if need_b else s_row, need_b)
            else:
                _ssim_row_value(st, c1, c2, one, two, s_row)


@njit(nogil=True, cache=True)
def ssim_backward(a: np.ndarray,  # [P, H, W] image 1
                  b: np.ndarray,  # [P, H, W] image 2
                  g: np.ndarray,  # [K] symmetric window
                  fac: np.ndarray,  # [P, F, H, W] factors from ssim_forward
                  v_s: np.ndarray,  # [P, H, W] dL/dS
                  need_a: bool, need_b: bool,
                  v_a: np.ndarray,  # [P, H, W] dL/dimg1 (written when need_a)
                  v_b: np.ndarray,  # [P, H, W] dL/dimg2 (written when need_b)
                  ) -> None:
    """Image gradients from the cotangent of the SSIM map (module docstring)."""
    P, H, W = a.shape
    K = g.shape[0]
    pad = K // 2
    n = fac.shape[1]
    i_a = 2
    i_b = 3 if need_a else 2
    rows = np.zeros((n, W + 2 * pad), dtype=a.dtype)
    ring = np.empty((K, n, W), dtype=a.dtype)
    st = np.empty((n, W), dtype=a.dtype)
    for p in range(P):
        for r in range(H + pad):
            if r < H:
                slot = r % K
                v_row = v_s[p, r]
                for j in range(n):
                    f_row = fac[p, j, r]
                    row = rows[j, pad:pad + W]
                    for x in range(W):
                        row[x] = v_row[x] * f_row[x]
                    _hfilter(rows[j], g, pad, ring[slot, j])
            y = r - pad
            if y < 0:
                continue
            _vfilter(ring, y, H, n, g, st)
            a_row, b_row, f_sq, f_12 = a[p, y], b[p, y], st[F_SQ], st[F_12]
            if need_a:
                f_mu, out = st[i_a], v_a[p, y]
                for x in range(W):
                    out[x] = f_mu[x] + (a_row[x] + a_row[x]) * f_sq[x] + b_row[x] * f_12[x]
            if need_b:
                f_mu, out = st[i_b], v_b[p, y]
                for x in range(W):
                    out[x] = f_mu[x] + (b_row[x] + b_row[x]) * f_sq[x] + a_row[x] * f_12[x]
