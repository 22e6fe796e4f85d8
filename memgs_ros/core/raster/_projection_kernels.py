"""Compiled projection + SH kernels (numba); imported only by :mod:`.projection_numba`.

Per Gaussian, computed in float64 whatever the array dtype (float32 or float64; outputs and gradients are
written in the arrays' dtype), the same formulas as :func:`memgs_ros.core.raster.projection.project_gaussians`
(near culling with z = 1 for culled rows, Jacobian x/z and y/z clamps, 0.3 px^2 dilation,
normalised quaternions, sigmoid opacity, SH colours of the active degree with +0.5 and a clamp
at 0) and, in the backward kernel, their analytic vector-Jacobian products, with the same
subgradient choices as torch (clamps pass the gradient at their bounds; culled rows give no
gradient through 1/z). Each call handles the Gaussian rows [lo, hi) and releases the GIL, so
callers run disjoint row ranges on several Python threads; the pose gradient of a range is
written to its own accumulator row.

Both kernels are built from the same per-stage helpers (``_view``: camera point and J W rows;
``_cov2d``: quaternion and scales -> 2D covariance; ``_sh_raw``: colour), and the backward one
from one vjp helper per stage, as gsplat splits its kernels; numba inlines them (no speed cost).

Camera array ``cam``: (fx, fy, cx, cy, x/z lower limit, x/z upper limit, y/z lower limit,
y/z upper limit, near). Pose array ``pose``: (R row-major, t) of T_cw, [12].
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from memgs_ros.core.raster.projection import COV2D_DILATION
from memgs_ros.core.raster.sh import SH_C0, SH_C1, SH_C2, SH_C3

C20, C21, C22, C23, C24 = SH_C2
C30, C31, C32, C33, C34, C35, C36 = SH_C3
# Pose accumulator columns: dL/dR (9, row-major), dL/dt (3), sum of dL/d(Gaussian - camera centre) (3).
ACC_COLS = 15


@njit(cache=True, fastmath=False, inline="always")
def _sh_basis(x: float, y: float, z: float, degree: int, b: np.ndarray) -> None:
    """Real SH basis 0..(degree + 1)^2 - 1 at the unit direction (x, y, z), into b[:]."""
    b[0] = SH_C0
    if degree >= 1:
        b[1] = -SH_C1 * y
        b[2] = SH_C1 * z
        b[3] = -SH_C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b[4] = C20 * (x * y)
        b[5] = C21 * (y * z)
        b[6] = C22 * (2.0 * zz - xx - yy)
        b[7] = C23 * (x * z)
        b[8] = C24 * (xx - yy)
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        b[9] = C30 * y * (3.0 * xx - yy)
        b[10] = C31 * (x * y) * z
        b[11] = C32 * y * (4.0 * zz - xx - yy)
        b[12] = C33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        b[13] = C34 * x * (4.0 * zz - xx - yy)
        b[14] = C35 * z * (xx - yy)
        b[15] = C36 * x * (xx - 3.0 * yy)


@njit(cache=True, fastmath=False, inline="always")
def _sh_basis_vjp(x: float, y: float, z: float, degree: int, v: np.ndarray) -> tuple[float, float, float]:
    """d(sum_b v[b] Y_b) / d(x, y, z) for the bands 1..degree (v[b] for basis index b)."""
    gx = -SH_C1 * v[3]
    gy = -SH_C1 * v[1]
    gz = SH_C1 * v[2]
    if degree >= 2:
        gx += C20 * y * v[4] - 2.0 * C22 * x * v[6] + C23 * z * v[7] + 2.0 * C24 * x * v[8]
        gy += C20 * x * v[4] + C21 * z * v[5] - 2.0 * C22 * y * v[6] - 2.0 * C24 * y * v[8]
        gz += C21 * y * v[5] + 4.0 * C22 * z * v[6] + C23 * x * v[7]
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        gx += (
            C30 * 6.0 * xy * v[9]
            + C31 * yz * v[10]
            - C32 * 2.0 * xy * v[11]
            - C33 * 6.0 * xz * v[12]
            + C34 * (4.0 * zz - 3.0 * xx - yy) * v[13]
            + C35 * 2.0 * xz * v[14]
            + C36 * 3.0 * (xx - yy) * v[15]
        )
        gy += (
            C30 * 3.0 * (xx - yy) * v[9]
            + C31 * xz * v[10]
            + C32 * (4.0 * zz - xx - 3.0 * yy) * v[11]
            - C33 * 6.0 * yz * v[12]
            - C34 * 2.0 * xy * v[13]
            - C35 * 2.0 * yz * v[14]
            - C36 * 6.0 * xy * v[15]
        )
        gz += (
            C31 * xy * v[10]
            + C32 * 8.0 * yz * v[11]
            + C33 * (6.0 * zz - 3.0 * xx - 3.0 * yy) * v[12]
            + C34 * 8.0 * xz * v[13]
            + C35 * (xx - yy) * v[14]
        )
    return gx, gy, gz


class _View(NamedTuple):
    """A Gaussian's centre in the camera and the rows of J W (the projection Jacobian times R)."""

    x: float
    y: float
    z: float
    front: bool  # z > near
    inv_z: float  # 1 / z, or 1 for culled rows (no inf/NaN in their gradients)
    txr: float  # x / z before the clamp
    tyr: float
    tx: float  # x / z clamped to the camera's limits
    ty: float
    ax: float  # fx / z
    ay: float  # fy / z
    J: tuple[float, float, float, float, float, float]  # J W rows: ax (R0 - tx R2), ay (R1 - ty R2)


class _Cov(NamedTuple):
    """The 2D covariance of one Gaussian and its intermediates: A = J W M diag(s), Sigma = A A^T + dilation."""

    qnorm: float  # |q| of the stored quaternion
    qn: float  # max(|q|, 1e-12)
    q0: tuple[float, float, float, float]  # stored quaternion (wxyz)
    q: tuple[float, float, float, float]  # q0 / qn
    M: tuple[float, ...]  # R(q), row-major [9]
    s: tuple[float, float, float]  # exp(log scales)
    B: tuple[float, ...]  # J W M, row-major [2, 3]
    A: tuple[float, ...]  # B diag(s) [2, 3]
    sxx: float
    sxy: float
    syy: float
    inv_det: float  # 1 / det(Sigma)


@njit(cache=True, fastmath=False, inline="always")
def _pose(pose: np.ndarray) -> tuple[tuple[float, ...], tuple[float, float, float], tuple[float, float, float]]:
    """(R row-major [9], t [3], camera centre -R^T t [3]) of the pose array."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (pose[0], pose[1], pose[2], pose[3], pose[4], pose[5], pose[6],
                                                   pose[7], pose[8])
    t0, t1, t2 = pose[9], pose[10], pose[11]
    cc = (-(r00 * t0 + r10 * t1 + r20 * t2), -(r01 * t0 + r11 * t1 + r21 * t2), -(r02 * t0 + r12 * t1 + r22 * t2))
    return (r00, r01, r02, r10, r11, r12, r20, r21, r22), (t0, t1, t2), cc


@njit(cache=True, fastmath=False, inline="always")
def _view(R: tuple[float, ...], t: tuple[float, float, float], cam: np.ndarray, mx: float, my: float,
          mz: float) -> _View:
    """p_c = R m + t, the near test and the clamped Jacobian rows (as project_gaussians)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    fx, fy = cam[0], cam[1]
    lxn, lxp, lyn, lyp, near = cam[4], cam[5], cam[6], cam[7], cam[8]
    x = r00 * mx + r01 * my + r02 * mz + t[0]
    y = r10 * mx + r11 * my + r12 * mz + t[1]
    z = r20 * mx + r21 * my + r22 * mz + t[2]
    front = z > near
    inv_z = 1.0 / z if front else 1.0
    txr, tyr = x * inv_z, y * inv_z
    tx = min(max(txr, -lxn), lxp)
    ty = min(max(tyr, -lyn), lyp)
    ax, bx = fx * inv_z, fx * tx * inv_z
    ay, by = fy * inv_z, fy * ty * inv_z
    J = (ax * r00 - bx * r20, ax * r01 - bx * r21, ax * r02 - bx * r22,
         ay * r10 - by * r20, ay * r11 - by * r21, ay * r12 - by * r22)
    return _View(x, y, z, front, inv_z, txr, tyr, tx, ty, ax, ay, J)


@njit(cache=True, fastmath=False, inline="always")
def _cov2d(J: tuple[float, ...], quats: np.ndarray, log_scales: np.ndarray, i: int) -> _Cov:
    """Row i's quaternion and scales -> its dilated 2D covariance (and the intermediates the vjp needs)."""
    j00, j01, j02, j10, j11, j12 = J
    qw0, qx0, qy0, qz0 = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
    qnorm = math.sqrt(qw0 * qw0 + qx0 * qx0 + qy0 * qy0 + qz0 * qz0)
    qn = max(qnorm, 1e-12)
    qw, qx, qy, qz = qw0 / qn, qx0 / qn, qy0 / qn, qz0 / qn
    m00 = 1.0 - 2.0 * (qy * qy + qz * qz)
    m01 = 2.0 * (qx * qy - qw * qz)
    m02 = 2.0 * (qx * qz + qw * qy)
    m10 = 2.0 * (qx * qy + qw * qz)
    m11 = 1.0 - 2.0 * (qx * qx + qz * qz)
    m12 = 2.0 * (qy * qz - qw * qx)
    m20 = 2.0 * (qx * qz - qw * qy)
    m21 = 2.0 * (qy * qz + qw * qx)
    m22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    s0 = math.exp(float(log_scales[i, 0]))
    s1 = math.exp(float(log_scales[i, 1]))
    s2 = math.exp(float(log_scales[i, 2]))
    b00 = j00 * m00 + j01 * m10 + j02 * m20
    b01 = j00 * m01 + j01 * m11 + j02 * m21
    b02 = j00 * m02 + j01 * m12 + j02 * m22
    b10 = j10 * m00 + j11 * m10 + j12 * m20
    b11 = j10 * m01 + j11 * m11 + j12 * m21
    b12 = j10 * m02 + j11 * m12 + j12 * m22
    a00, a01, a02 = b00 * s0, b01 * s1, b02 * s2
    a10, a11, a12 = b10 * s0, b11 * s1, b12 * s2
    sxx = a00 * a00 + a01 * a01 + a02 * a02 + COV2D_DILATION
    sxy = a00 * a10 + a01 * a11 + a02 * a12
    syy = a10 * a10 + a11 * a11 + a12 * a12 + COV2D_DILATION
    return _Cov(qnorm, qn, (qw0, qx0, qy0, qz0), (qw, qx, qy, qz), (m00, m01, m02, m10, m11, m12, m20, m21, m22),
                (s0, s1, s2), (b00, b01, b02, b10, b11, b12), (a00, a01, a02, a10, a11, a12), sxx, sxy, syy,
                1.0 / (sxx * syy - sxy * sxy))


@njit(cache=True, fastmath=False, inline="always")
def _view_dir(mx: float, my: float, mz: float, cc: tuple[float, float, float]
              ) -> tuple[tuple[float, float, float], float, float, tuple[float, float, float]]:
    """(d = mean - camera centre, |d|, max(|d|, 1e-12), d / that): the SH viewing direction."""
    d0, d1, d2 = mx - cc[0], my - cc[1], mz - cc[2]
    dnorm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    dn = max(dnorm, 1e-12)
    return (d0, d1, d2), dnorm, dn, (d0 / dn, d1 / dn, d2 / dn)


@njit(cache=True, fastmath=False, inline="always")
def _sh_raw(b: np.ndarray, dc: np.ndarray, rest: np.ndarray, i: int, ch: int, n_basis: int) -> float:
    """Channel ch of row i's SH colour before the clamp at 0: sum_k b[k] rest[k - 1] + (C0 dc + 0.5)."""
    acc = 0.0
    for k in range(1, n_basis):
        acc += b[k] * float(rest[i, k - 1, ch])
    return acc + (SH_C0 * float(dc[i, ch]) + 0.5)


@njit(cache=True, fastmath=False, inline="always")
def _sigmoid(logit: float) -> float:
    return 1.0 / (1.0 + math.exp(-logit))


@njit(nogil=True, cache=True, fastmath=False)
def project_forward(lo: int, hi: int, args: tuple[Any, ...], outs: tuple[np.ndarray, ...]) -> None:
    """Projects rows [lo, hi).

    args: (means [N, 3], quats [N, 4] wxyz unnormalised, log_scales [N, 3], logits [N], dc [N, 3],
    rest [N, K, 3], pose [12], cam [9], degree); outs (written): (means2d [N, 2], cov2d [N, 3],
    conics [N, 3], depths [N], opac [N], colors [N, 3], in_front [N] bool).
    """
    means, quats, log_scales, logits, dc, rest, pose, cam, degree = args
    means2d, cov2d, conics, depths, opac, colors, in_front = outs
    R, t, cc = _pose(pose)
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    n_basis = (degree + 1) * (degree + 1)
    b = np.empty(16)
    for i in range(lo, hi):
        mx, my, mz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        v = _view(R, t, cam, mx, my, mz)
        means2d[i, 0] = fx * v.x * v.inv_z + cx
        means2d[i, 1] = fy * v.y * v.inv_z + cy
        c = _cov2d(v.J, quats, log_scales, i)
        cov2d[i, 0], cov2d[i, 1], cov2d[i, 2] = c.sxx, c.sxy, c.syy
        conics[i, 0], conics[i, 1], conics[i, 2] = c.syy * c.inv_det, -c.sxy * c.inv_det, c.sxx * c.inv_det
        depths[i] = v.z
        in_front[i] = v.front
        opac[i] = _sigmoid(float(logits[i]))
        if degree > 0:
            u = _view_dir(mx, my, mz, cc)[3]
            _sh_basis(u[0], u[1], u[2], degree, b)
        for ch in range(3):
            colors[i, ch] = max(_sh_raw(b, dc, rest, i, ch, n_basis), 0.0)


# ------------------------------------------------------------------ backward stages
@njit(cache=True, fastmath=False, inline="always")
def _conic_vjp(c: _Cov, v_cov2d: np.ndarray, v_conics: np.ndarray, i: int) -> tuple[float, float, float]:
    """dL/d(sxx, sxy, syy) from the cov2d and conic cotangents of row i."""
    ca, cb, cc = c.syy * c.inv_det, -c.sxy * c.inv_det, c.sxx * c.inv_det
    va, vb_, vc = float(v_conics[i, 0]), float(v_conics[i, 1]), float(v_conics[i, 2])
    # d(Sigma^-1) = -Sigma^-1 dSigma Sigma^-1 with conic (a, b, c) = ([0,0], [0,1], [1,1]) entries.
    v_sxx = float(v_cov2d[i, 0]) - (va * ca * ca + vb_ * ca * cb + vc * cb * cb)
    v_sxy = float(v_cov2d[i, 1]) - (2.0 * va * ca * cb + vb_ * (ca * cc + cb * cb) + 2.0 * vc * cb * cc)
    v_syy = float(v_cov2d[i, 2]) - (va * cb * cb + vb_ * cb * cc + vc * cc * cc)
    return v_sxx, v_sxy, v_syy


@njit(cache=True, fastmath=False, inline="always")
def _cov2d_vjp(c: _Cov, v_sxx: float, v_sxy: float, v_syy: float, v_log_scales: np.ndarray, i: int
               ) -> tuple[float, ...]:
    """Sigma = A A^T, A = B diag(s): writes dL/d(log scales) of row i, returns dL/dB [6]."""
    a00, a01, a02, a10, a11, a12 = c.A
    b00, b01, b02, b10, b11, b12 = c.B
    s0, s1, s2 = c.s
    va00 = 2.0 * v_sxx * a00 + v_sxy * a10
    va01 = 2.0 * v_sxx * a01 + v_sxy * a11
    va02 = 2.0 * v_sxx * a02 + v_sxy * a12
    va10 = 2.0 * v_syy * a10 + v_sxy * a00
    va11 = 2.0 * v_syy * a11 + v_sxy * a01
    va12 = 2.0 * v_syy * a12 + v_sxy * a02
    v_log_scales[i, 0] = (va00 * b00 + va10 * b10) * s0
    v_log_scales[i, 1] = (va01 * b01 + va11 * b11) * s1
    v_log_scales[i, 2] = (va02 * b02 + va12 * b12) * s2
    return va00 * s0, va01 * s1, va02 * s2, va10 * s0, va11 * s1, va12 * s2


@njit(cache=True, fastmath=False, inline="always")
def _jwm_vjp(vB: tuple[float, ...], J: tuple[float, ...], M: tuple[float, ...]
             ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """B = (J W) M: (dL/d(J W) [6], dL/dM [9])."""
    vb00, vb01, vb02, vb10, vb11, vb12 = vB
    j00, j01, j02, j10, j11, j12 = J
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = M
    vJ = (vb00 * m00 + vb01 * m01 + vb02 * m02, vb00 * m10 + vb01 * m11 + vb02 * m12,
          vb00 * m20 + vb01 * m21 + vb02 * m22, vb10 * m00 + vb11 * m01 + vb12 * m02,
          vb10 * m10 + vb11 * m11 + vb12 * m12, vb10 * m20 + vb11 * m21 + vb12 * m22)
    gM = (vb00 * j00 + vb10 * j10, vb01 * j00 + vb11 * j10, vb02 * j00 + vb12 * j10,
          vb00 * j01 + vb10 * j11, vb01 * j01 + vb11 * j11, vb02 * j01 + vb12 * j11,
          vb00 * j02 + vb10 * j12, vb01 * j02 + vb11 * j12, vb02 * j02 + vb12 * j12)
    return vJ, gM


@njit(cache=True, fastmath=False, inline="always")
def _quat_vjp(c: _Cov, gM: tuple[float, ...], v_quats: np.ndarray, i: int) -> None:
    """M = R(q0 / |q0|): writes dL/dq0 of row i (no gradient through the norm below 1e-12)."""
    gm00, gm01, gm02, gm10, gm11, gm12, gm20, gm21, gm22 = gM
    qw, qx, qy, qz = c.q
    qw0, qx0, qy0, qz0 = c.q0
    vqw = 2.0 * (-qz * gm01 + qy * gm02 + qz * gm10 - qx * gm12 - qy * gm20 + qx * gm21)
    vqx = 2.0 * (qy * gm01 + qz * gm02 + qy * gm10 - 2.0 * qx * gm11 - qw * gm12 + qz * gm20 + qw * gm21
                 - 2.0 * qx * gm22)
    vqy = 2.0 * (-2.0 * qy * gm00 + qx * gm01 + qw * gm02 + qx * gm10 + qz * gm12 - qw * gm20 + qz * gm21
                 - 2.0 * qy * gm22)
    vqz = 2.0 * (-2.0 * qz * gm00 - qw * gm01 + qx * gm02 + qw * gm10 - 2.0 * qz * gm11 + qy * gm12 + qx * gm20
                 + qy * gm21)
    inv_qn = 1.0 / c.qn
    proj_q = 0.0
    if c.qnorm >= 1e-12:
        proj_q = (vqw * qw0 + vqx * qx0 + vqy * qy0 + vqz * qz0) * inv_qn * inv_qn * inv_qn
    v_quats[i, 0] = vqw * inv_qn - proj_q * qw0
    v_quats[i, 1] = vqx * inv_qn - proj_q * qx0
    v_quats[i, 2] = vqy * inv_qn - proj_q * qy0
    v_quats[i, 3] = vqz * inv_qn - proj_q * qz0


@njit(cache=True, fastmath=False, inline="always")
def _add_scaled3(g: np.ndarray, k: int, s: float, a: float, b: float, c: float) -> None:
    """g[k:k + 3] += s (a, b, c): one row of an outer product into the pose accumulator."""
    g[k] += s * a
    g[k + 1] += s * b
    g[k + 2] += s * c


@njit(cache=True, fastmath=False, inline="always")
def _jw_vjp(v: _View, vJ: tuple[float, ...], R: tuple[float, ...], cam: np.ndarray, g: np.ndarray
            ) -> tuple[float, float, float]:
    """J W rows ax (R0 - tx R2), ay (R1 - ty R2): adds dL/dR to g[0:9], returns dL/d(x, y, 1/z)
    (the clamps pass the gradient at their bounds)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    vj00, vj01, vj02, vj10, vj11, vj12 = vJ
    fx, fy = cam[0], cam[1]
    lxn, lxp, lyn, lyp = cam[4], cam[5], cam[6], cam[7]
    ax, ay, tx, ty = v.ax, v.ay, v.tx, v.ty
    e0, e1, e2 = r00 - tx * r20, r01 - tx * r21, r02 - tx * r22
    f0, f1, f2 = r10 - ty * r20, r11 - ty * r21, r12 - ty * r22
    _add_scaled3(g, 0, ax, vj00, vj01, vj02)
    _add_scaled3(g, 3, ay, vj10, vj11, vj12)
    g[6] -= vj00 * ax * tx + vj10 * ay * ty
    g[7] -= vj01 * ax * tx + vj11 * ay * ty
    g[8] -= vj02 * ax * tx + vj12 * ay * ty
    v_inv_z = fx * (vj00 * e0 + vj01 * e1 + vj02 * e2) + fy * (vj10 * f0 + vj11 * f1 + vj12 * f2)
    v_tx = -ax * (vj00 * r20 + vj01 * r21 + vj02 * r22)
    v_ty = -ay * (vj10 * r20 + vj11 * r21 + vj12 * r22)
    vx = 0.0
    vy = 0.0
    if -lxn <= v.txr <= lxp:
        vx += v_tx * v.inv_z
        v_inv_z += v_tx * v.x
    if -lyn <= v.tyr <= lyp:
        vy += v_ty * v.inv_z
        v_inv_z += v_ty * v.y
    return vx, vy, v_inv_z


@njit(cache=True, fastmath=False, inline="always")
def _camera_point_vjp(v: _View, vx: float, vy: float, v_inv_z: float, v_means2d: np.ndarray, v_depths: np.ndarray,
                      cam: np.ndarray, i: int) -> tuple[float, float, float]:
    """Adds the means2d and depth cotangents of row i to dL/d(x, y, 1/z); returns dL/dp_c."""
    fx, fy = cam[0], cam[1]
    vu, vv = float(v_means2d[i, 0]), float(v_means2d[i, 1])
    vx += vu * fx * v.inv_z
    vy += vv * fy * v.inv_z
    v_inv_z += vu * fx * v.x + vv * fy * v.y
    vz = float(v_depths[i])
    if v.front:
        vz -= v_inv_z * v.inv_z * v.inv_z
    return vx, vy, vz


@njit(cache=True, fastmath=False, inline="always")
def _rigid_vjp(R: tuple[float, ...], mx: float, my: float, mz: float, vx: float, vy: float, vz: float,
               g: np.ndarray) -> tuple[float, float, float]:
    """p_c = R m + t: adds dL/dR to g[0:9] and dL/dt to g[9:12], returns dL/dm."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    _add_scaled3(g, 0, vx, mx, my, mz)
    _add_scaled3(g, 3, vy, mx, my, mz)
    _add_scaled3(g, 6, vz, mx, my, mz)
    g[9] += vx
    g[10] += vy
    g[11] += vz
    return r00 * vx + r10 * vy + r20 * vz, r01 * vx + r11 * vy + r21 * vz, r02 * vx + r12 * vy + r22 * vz


@njit(cache=True, fastmath=False, inline="always")
def _colour_vjp(b: np.ndarray, vb: np.ndarray, dc: np.ndarray, rest: np.ndarray, v_colors: np.ndarray,
                v_dc: np.ndarray, v_rest: np.ndarray, i: int, degree: int, n_basis: int) -> None:
    """Clamped SH colour of row i: writes dL/d(dc) and, above degree 0, dL/d(rest) (0 above the
    active degree) and dL/d(basis) into vb[1:n_basis]."""
    for k in range(1, n_basis):
        vb[k] = 0.0
    for ch in range(3):
        v = float(v_colors[i, ch]) if _sh_raw(b, dc, rest, i, ch, n_basis) >= 0.0 else 0.0
        v_dc[i, ch] = SH_C0 * v
        if degree == 0:
            continue
        for k in range(1, n_basis):
            v_rest[i, k - 1, ch] = b[k] * v
            vb[k] += float(rest[i, k - 1, ch]) * v
        for k in range(n_basis - 1, v_rest.shape[1]):
            v_rest[i, k, ch] = 0.0


@njit(cache=True, fastmath=False, inline="always")
def _dir_vjp(d: tuple[float, float, float], dnorm: float, dn: float, u: tuple[float, float, float], degree: int,
             vb: np.ndarray) -> tuple[float, float, float]:
    """u = d / max(|d|, 1e-12): dL/dd from dL/d(basis) (no gradient through the norm below 1e-12)."""
    gx, gy, gz = _sh_basis_vjp(u[0], u[1], u[2], degree, vb)
    vd0, vd1, vd2 = gx / dn, gy / dn, gz / dn
    if dnorm >= 1e-12:
        p = (gx * d[0] + gy * d[1] + gz * d[2]) / (dn * dn * dn)
        vd0 -= p * d[0]
        vd1 -= p * d[1]
        vd2 -= p * d[2]
    return vd0, vd1, vd2


@njit(nogil=True, cache=True, fastmath=False)
def project_backward(lo: int, hi: int, args: tuple[Any, ...], cots: tuple[np.ndarray, ...],
                     grads: tuple[np.ndarray, ...], acc: np.ndarray) -> None:
    """Recomputes rows [lo, hi)'s forward intermediates, then applies the stages' vjps in reverse.

    args: as project_forward's; cots: (v_means2d [N, 2], v_cov2d [N, 3], v_conics [N, 3], v_depths [N],
    v_opac [N], v_colors [N, 3]); grads (written): (v_means [N, 3], v_quats [N, 4], v_log_scales [N, 3],
    v_logits [N], v_dc [N, 3], v_rest [N, K, 3]: bands above the active degree get 0, untouched at
    degree 0); acc [ACC_COLS] (written): this range's pose gradient.
    """
    means, quats, log_scales, logits, dc, rest, pose, cam, degree = args
    v_means2d, v_cov2d, v_conics, v_depths, v_opac, v_colors = cots
    v_means, v_quats, v_log_scales, v_logits, v_dc, v_rest = grads
    R, t, cc = _pose(pose)
    n_basis = (degree + 1) * (degree + 1)
    b = np.empty(16)
    vb = np.zeros(16)
    g = np.zeros(ACC_COLS)  # dL/dR (row-major), dL/dt, sum of dL/d(mean - camera centre)
    for i in range(lo, hi):
        mx, my, mz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        v = _view(R, t, cam, mx, my, mz)
        c = _cov2d(v.J, quats, log_scales, i)
        v_sxx, v_sxy, v_syy = _conic_vjp(c, v_cov2d, v_conics, i)
        vB = _cov2d_vjp(c, v_sxx, v_sxy, v_syy, v_log_scales, i)
        vJ, gM = _jwm_vjp(vB, v.J, c.M)
        _quat_vjp(c, gM, v_quats, i)
        vx, vy, v_inv_z = _jw_vjp(v, vJ, R, cam, g)
        vx, vy, vz = _camera_point_vjp(v, vx, vy, v_inv_z, v_means2d, v_depths, cam, i)
        vmx, vmy, vmz = _rigid_vjp(R, mx, my, mz, vx, vy, vz, g)
        o = _sigmoid(float(logits[i]))
        v_logits[i] = float(v_opac[i]) * o * (1.0 - o)
        if degree > 0:
            d, dnorm, dn, u = _view_dir(mx, my, mz, cc)
            _sh_basis(u[0], u[1], u[2], degree, b)
        _colour_vjp(b, vb, dc, rest, v_colors, v_dc, v_rest, i, degree, n_basis)
        if degree > 0:
            vd0, vd1, vd2 = _dir_vjp(d, dnorm, dn, u, degree, vb)
            vmx += vd0
            vmy += vd1
            vmz += vd2
            g[12] += vd0
            g[13] += vd1
            g[14] += vd2
        v_means[i, 0], v_means[i, 1], v_means[i, 2] = vmx, vmy, vmz
    acc[:] = g
