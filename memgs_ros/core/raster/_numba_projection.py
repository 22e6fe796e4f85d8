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

Camera array ``cam``: (fx, fy, cx, cy, x/z lower limit, x/z upper limit, y/z lower limit,
y/z upper limit, near). Pose array ``pose``: (R row-major, t) of T_cw, [12].
"""
from __future__ import annotations

import math

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


@njit(nogil=True, cache=True, fastmath=False)
def project_forward(
    lo: int,
    hi: int,
    means: np.ndarray,  # [N, 3]
    quats: np.ndarray,  # [N, 4] wxyz, unnormalised
    log_scales: np.ndarray,  # [N, 3]
    logits: np.ndarray,  # [N]
    dc: np.ndarray,  # [N, 3]
    rest: np.ndarray,  # [N, K, 3]
    pose: np.ndarray,  # [12]
    cam: np.ndarray,  # [9]
    degree: int,
    means2d: np.ndarray,  # [N, 2] out
    cov2d: np.ndarray,  # [N, 3] out
    conics: np.ndarray,  # [N, 3] out
    depths: np.ndarray,  # [N] out
    opac: np.ndarray,  # [N] out
    colors: np.ndarray,  # [N, 3] out
    in_front: np.ndarray,  # [N] bool out
) -> None:
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (pose[0], pose[1], pose[2], pose[3], pose[4], pose[5], pose[6],
                                                   pose[7], pose[8])
    t0, t1, t2 = pose[9], pose[10], pose[11]
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lxn, lxp, lyn, lyp, near = cam[4], cam[5], cam[6], cam[7], cam[8]
    cc0 = -(r00 * t0 + r10 * t1 + r20 * t2)  # camera centre -R^T t
    cc1 = -(r01 * t0 + r11 * t1 + r21 * t2)
    cc2 = -(r02 * t0 + r12 * t1 + r22 * t2)
    n_basis = (degree + 1) * (degree + 1)
    b = np.empty(16)
    for i in range(lo, hi):
        mx, my, mz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        x = r00 * mx + r01 * my + r02 * mz + t0
        y = r10 * mx + r11 * my + r12 * mz + t1
        z = r20 * mx + r21 * my + r22 * mz + t2
        front = z > near
        inv_z = 1.0 / z if front else 1.0
        means2d[i, 0] = fx * x * inv_z + cx
        means2d[i, 1] = fy * y * inv_z + cy
        tx = min(max(x * inv_z, -lxn), lxp)
        ty = min(max(y * inv_z, -lyn), lyp)
        # Rows of J W: jw0 = fx/z (R0 - tx R2), jw1 = fy/z (R1 - ty R2).
        ax, bx = fx * inv_z, fx * tx * inv_z
        ay, by = fy * inv_z, fy * ty * inv_z
        j00, j01, j02 = ax * r00 - bx * r20, ax * r01 - bx * r21, ax * r02 - bx * r22
        j10, j11, j12 = ay * r10 - by * r20, ay * r11 - by * r21, ay * r12 - by * r22
        qw, qx, qy, qz = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
        qn = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
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
        a00 = (j00 * m00 + j01 * m10 + j02 * m20) * s0
        a01 = (j00 * m01 + j01 * m11 + j02 * m21) * s1
        a02 = (j00 * m02 + j01 * m12 + j02 * m22) * s2
        a10 = (j10 * m00 + j11 * m10 + j12 * m20) * s0
        a11 = (j10 * m01 + j11 * m11 + j12 * m21) * s1
        a12 = (j10 * m02 + j11 * m12 + j12 * m22) * s2
        sxx = a00 * a00 + a01 * a01 + a02 * a02 + COV2D_DILATION
        sxy = a00 * a10 + a01 * a11 + a02 * a12
        syy = a10 * a10 + a11 * a11 + a12 * a12 + COV2D_DILATION
        inv_det = 1.0 / (sxx * syy - sxy * sxy)
        cov2d[i, 0], cov2d[i, 1], cov2d[i, 2] = sxx, sxy, syy
        conics[i, 0], conics[i, 1], conics[i, 2] = syy * inv_det, -sxy * inv_det, sxx * inv_det
        depths[i] = z
        in_front[i] = front
        opac[i] = 1.0 / (1.0 + math.exp(-float(logits[i])))
        if degree == 0:
            for ch in range(3):
                colors[i, ch] = max(SH_C0 * float(dc[i, ch]) + 0.5, 0.0)
            continue
        d0, d1, d2 = mx - cc0, my - cc1, mz - cc2
        dn = max(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-12)
        _sh_basis(d0 / dn, d1 / dn, d2 / dn, degree, b)
        for ch in range(3):
            acc = 0.0
            for k in range(1, n_basis):
                acc += b[k] * float(rest[i, k - 1, ch])
            colors[i, ch] = max(acc + (SH_C0 * float(dc[i, ch]) + 0.5), 0.0)


@njit(nogil=True, cache=True, fastmath=False)
def project_backward(
    lo: int,
    hi: int,
    means: np.ndarray,  # [N, 3]
    quats: np.ndarray,  # [N, 4]
    log_scales: np.ndarray,  # [N, 3]
    logits: np.ndarray,  # [N]
    dc: np.ndarray,  # [N, 3]
    rest: np.ndarray,  # [N, K, 3]
    pose: np.ndarray,  # [12]
    cam: np.ndarray,  # [9]
    degree: int,
    v_means2d: np.ndarray,  # [N, 2]
    v_cov2d: np.ndarray,  # [N, 3]
    v_conics: np.ndarray,  # [N, 3]
    v_depths: np.ndarray,  # [N]
    v_opac: np.ndarray,  # [N]
    v_colors: np.ndarray,  # [N, 3]
    v_means: np.ndarray,  # [N, 3] out
    v_quats: np.ndarray,  # [N, 4] out
    v_log_scales: np.ndarray,  # [N, 3] out
    v_logits: np.ndarray,  # [N] out
    v_dc: np.ndarray,  # [N, 3] out
    v_rest: np.ndarray,  # [N, K, 3] out (bands above the active degree get 0; untouched at degree 0)
    acc: np.ndarray,  # [ACC_COLS] out: this range's pose gradient
) -> None:
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (pose[0], pose[1], pose[2], pose[3], pose[4], pose[5], pose[6],
                                                   pose[7], pose[8])
    t0, t1, t2 = pose[9], pose[10], pose[11]
    fx, fy = cam[0], cam[1]
    lxn, lxp, lyn, lyp, near = cam[4], cam[5], cam[6], cam[7], cam[8]
    cc0 = -(r00 * t0 + r10 * t1 + r20 * t2)
    cc1 = -(r01 * t0 + r11 * t1 + r21 * t2)
    cc2 = -(r02 * t0 + r12 * t1 + r22 * t2)
    n_basis = (degree + 1) * (degree + 1)
    b = np.empty(16)
    vb = np.zeros(16)
    g00 = g01 = g02 = g10 = g11 = g12 = g20 = g21 = g22 = 0.0  # dL/dR
    gt0 = gt1 = gt2 = 0.0  # dL/dt
    gd0 = gd1 = gd2 = 0.0  # sum of dL/d(mean - camera centre)
    for i in range(lo, hi):
        # ---- forward recomputation
        mx, my, mz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        x = r00 * mx + r01 * my + r02 * mz + t0
        y = r10 * mx + r11 * my + r12 * mz + t1
        z = r20 * mx + r21 * my + r22 * mz + t2
        front = z > near
        inv_z = 1.0 / z if front else 1.0
        txr, tyr = x * inv_z, y * inv_z
        tx = min(max(txr, -lxn), lxp)
        ty = min(max(tyr, -lyn), lyp)
        ax, bx = fx * inv_z, fx * tx * inv_z
        ay, by = fy * inv_z, fy * ty * inv_z
        e0, e1, e2 = r00 - tx * r20, r01 - tx * r21, r02 - tx * r22  # jw0 = ax (R0 - tx R2)
        f0, f1, f2 = r10 - ty * r20, r11 - ty * r21, r12 - ty * r22  # jw1 = ay (R1 - ty R2)
        j00, j01, j02 = ax * r00 - bx * r20, ax * r01 - bx * r21, ax * r02 - bx * r22
        j10, j11, j12 = ay * r10 - by * r20, ay * r11 - by * r21, ay * r12 - by * r22
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
        b00 = j00 * m00 + j01 * m10 + j02 * m20  # B = J W M, A = B diag(s)
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
        inv_det = 1.0 / (sxx * syy - sxy * sxy)

        # ---- conics and cov2d -> (sxx, sxy, syy)
        ca, cb, cc = syy * inv_det, -sxy * inv_det, sxx * inv_det
        va, vb_, vc = float(v_conics[i, 0]), float(v_conics[i, 1]), float(v_conics[i, 2])
        # d(Sigma^-1) = -Sigma^-1 dSigma Sigma^-1 with conic (a, b, c) = ([0,0], [0,1], [1,1]) entries.
        v_sxx = float(v_cov2d[i, 0]) - (va * ca * ca + vb_ * ca * cb + vc * cb * cb)
        v_sxy = float(v_cov2d[i, 1]) - (2.0 * va * ca * cb + vb_ * (ca * cc + cb * cb) + 2.0 * vc * cb * cc)
        v_syy = float(v_cov2d[i, 2]) - (va * cb * cb + vb_ * cb * cc + vc * cc * cc)
        # ---- A rows
        va00 = 2.0 * v_sxx * a00 + v_sxy * a10
        va01 = 2.0 * v_sxx * a01 + v_sxy * a11
        va02 = 2.0 * v_sxx * a02 + v_sxy * a12
        va10 = 2.0 * v_syy * a10 + v_sxy * a00
        va11 = 2.0 * v_syy * a11 + v_sxy * a01
        va12 = 2.0 * v_syy * a12 + v_sxy * a02
        v_log_scales[i, 0] = (va00 * b00 + va10 * b10) * s0
        v_log_scales[i, 1] = (va01 * b01 + va11 * b11) * s1
        v_log_scales[i, 2] = (va02 * b02 + va12 * b12) * s2
        vb00, vb01, vb02 = va00 * s0, va01 * s1, va02 * s2
        vb10, vb11, vb12 = va10 * s0, va11 * s1, va12 * s2
        # ---- B = (J W) M
        vj00 = vb00 * m00 + vb01 * m01 + vb02 * m02
        vj01 = vb00 * m10 + vb01 * m11 + vb02 * m12
        vj02 = vb00 * m20 + vb01 * m21 + vb02 * m22
        vj10 = vb10 * m00 + vb11 * m01 + vb12 * m02
        vj11 = vb10 * m10 + vb11 * m11 + vb12 * m12
        vj12 = vb10 * m20 + vb11 * m21 + vb12 * m22
        gm00, gm01, gm02 = vb00 * j00 + vb10 * j10, vb01 * j00 + vb11 * j10, vb02 * j00 + vb12 * j10
        gm10, gm11, gm12 = vb00 * j01 + vb10 * j11, vb01 * j01 + vb11 * j11, vb02 * j01 + vb12 * j11
        gm20, gm21, gm22 = vb00 * j02 + vb10 * j12, vb01 * j02 + vb11 * j12, vb02 * j02 + vb12 * j12
        # ---- M(q normalised) -> q
        vqw = 2.0 * (-qz * gm01 + qy * gm02 + qz * gm10 - qx * gm12 - qy * gm20 + qx * gm21)
        vqx = 2.0 * (qy * gm01 + qz * gm02 + qy * gm10 - 2.0 * qx * gm11 - qw * gm12 + qz * gm20 + qw * gm21
                     - 2.0 * qx * gm22)
        vqy = 2.0 * (-2.0 * qy * gm00 + qx * gm01 + qw * gm02 + qx * gm10 + qz * gm12 - qw * gm20 + qz * gm21
                     - 2.0 * qy * gm22)
        vqz = 2.0 * (-2.0 * qz * gm00 - qw * gm01 + qx * gm02 + qw * gm10 - 2.0 * qz * gm11 + qy * gm12 + qx * gm20
                     + qy * gm21)
        inv_qn = 1.0 / qn
        proj_q = 0.0
        if qnorm >= 1e-12:
            proj_q = (vqw * qw0 + vqx * qx0 + vqy * qy0 + vqz * qz0) * inv_qn * inv_qn * inv_qn
        v_quats[i, 0] = vqw * inv_qn - proj_q * qw0
        v_quats[i, 1] = vqx * inv_qn - proj_q * qx0
        v_quats[i, 2] = vqy * inv_qn - proj_q * qy0
        v_quats[i, 3] = vqz * inv_qn - proj_q * qz0
        # ---- J W rows: jw0 = ax e, jw1 = ay f with e = R0 - tx R2, f = R1 - ty R2
        g00 += vj00 * ax
        g01 += vj01 * ax
        g02 += vj02 * ax
        g10 += vj10 * ay
        g11 += vj11 * ay
        g12 += vj12 * ay
        g20 -= vj00 * ax * tx + vj10 * ay * ty
        g21 -= vj01 * ax * tx + vj11 * ay * ty
        g22 -= vj02 * ax * tx + vj12 * ay * ty
        v_inv_z = fx * (vj00 * e0 + vj01 * e1 + vj02 * e2) + fy * (vj10 * f0 + vj11 * f1 + vj12 * f2)
        v_tx = -ax * (vj00 * r20 + vj01 * r21 + vj02 * r22)
        v_ty = -ay * (vj10 * r20 + vj11 * r21 + vj12 * r22)
        vx = 0.0
        vy = 0.0
        if -lxn <= txr <= lxp:
            vx += v_tx * inv_z
            v_inv_z += v_tx * x
        if -lyn <= tyr <= lyp:
            vy += v_ty * inv_z
            v_inv_z += v_ty * y
        # ---- means2d, depth
        vu, vv = float(v_means2d[i, 0]), float(v_means2d[i, 1])
        vx += vu * fx * inv_z
        vy += vv * fy * inv_z
        v_inv_z += vu * fx * x + vv * fy * y
        vz = float(v_depths[i])
        if front:
            vz -= v_inv_z * inv_z * inv_z
        # ---- p_c = R m + t
        g00 += vx * mx
        g01 += vx * my
        g02 += vx * mz
        g10 += vy * mx
        g11 += vy * my
        g12 += vy * mz
        g20 += vz * mx
        g21 += vz * my
        g22 += vz * mz
        gt0 += vx
        gt1 += vy
        gt2 += vz
        vmx = r00 * vx + r10 * vy + r20 * vz
        vmy = r01 * vx + r11 * vy + r21 * vz
        vmz = r02 * vx + r12 * vy + r22 * vz
        # ---- opacity
        o = 1.0 / (1.0 + math.exp(-float(logits[i])))
        v_logits[i] = float(v_opac[i]) * o * (1.0 - o)
        # ---- colours
        if degree == 0:
            for ch in range(3):
                v = float(v_colors[i, ch]) if SH_C0 * float(dc[i, ch]) + 0.5 >= 0.0 else 0.0
                v_dc[i, ch] = SH_C0 * v
        else:
            d0, d1, d2 = mx - cc0, my - cc1, mz - cc2
            dnorm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            dn = max(dnorm, 1e-12)
            ux, uy, uz = d0 / dn, d1 / dn, d2 / dn
            _sh_basis(ux, uy, uz, degree, b)
            for k in range(1, n_basis):
                vb[k] = 0.0
            for ch in range(3):
                raw = 0.0
                for k in range(1, n_basis):
                    raw += b[k] * float(rest[i, k - 1, ch])
                raw += SH_C0 * float(dc[i, ch]) + 0.5
                v = float(v_colors[i, ch]) if raw >= 0.0 else 0.0
                v_dc[i, ch] = SH_C0 * v
                for k in range(1, n_basis):
                    v_rest[i, k - 1, ch] = b[k] * v
                    vb[k] += float(rest[i, k - 1, ch]) * v
                for k in range(n_basis - 1, v_rest.shape[1]):
                    v_rest[i, k, ch] = 0.0
            gx, gy, gz = _sh_basis_vjp(ux, uy, uz, degree, vb)
            vd0, vd1, vd2 = gx / dn, gy / dn, gz / dn
            if dnorm >= 1e-12:
                p = (gx * d0 + gy * d1 + gz * d2) / (dn * dn * dn)
                vd0 -= p * d0
                vd1 -= p * d1
                vd2 -= p * d2
            vmx += vd0
            vmy += vd1
            vmz += vd2
            gd0 += vd0
            gd1 += vd1
            gd2 += vd2
        v_means[i, 0], v_means[i, 1], v_means[i, 2] = vmx, vmy, vmz
    acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6], acc[7], acc[8] = g00, g01, g02, g10, g11, g12, g20, g21, g22
    acc[9], acc[10], acc[11] = gt0, gt1, gt2
    acc[12], acc[13], acc[14] = gd0, gd1, gd2
