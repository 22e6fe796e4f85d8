"""Map records as the arrays a splat viewer takes: linear scales, xyzw quaternions, RGBA colours.

numpy only (no rerun, no torch): the conversion is tested alone and costs the same wherever it runs.
The 3DGS PLY stores training parameters (log-scales, opacity logits, SH coefficients, wxyz
quaternions, reference section 10); a viewer wants their natural form.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.special import expit

from memgs_ros.core.gaussians.records import PLY_F_REST, GaussianRecords, base_rgb8

__all__ = ["SplatArrays", "psnr_db", "sh_rest_rgb", "splat_arrays"]

_SH_REST = PLY_F_REST // 3  # 15 coefficients a channel for degrees 1..3


class SplatArrays(NamedTuple):
    """N Gaussians in viewer form.

    centers: [N, 3] float32 world positions.
    scales: [N, 3] float32 standard deviations (m), exp of the log-scales.
    quaternions_xyzw: [N, 4] float32 unit quaternions, x y z w (the records hold w x y z).
    colors_rgba: [N, 4] uint8: base colour 0.5 + C0 * f_dc clipped to [0, 1], alpha sigmoid(opacity).
    sh_rest: [N, 15, 3] float32 degree 1..3 SH coefficients (coefficient, RGB), or None when not asked
        for or all zero (a degree-0 map).
    """

    centers: np.ndarray
    scales: np.ndarray
    quaternions_xyzw: np.ndarray
    colors_rgba: np.ndarray
    sh_rest: np.ndarray | None


def splat_arrays(records: GaussianRecords, sh: bool = True) -> SplatArrays:
    """Convert ``records`` (N Gaussians) to :class:`SplatArrays`; ``sh`` keeps the view-dependent terms."""
    q = records.rot[:, [1, 2, 3, 0]]  # [N, 4] wxyz -> xyzw
    norm = np.linalg.norm(q, axis=1, keepdims=True)  # [N, 1]
    # A zero quaternion (never trained, or a hand-made file) is the identity, not NaN.
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([0, 0, 0, 1], np.float32))
    alpha = expit(records.opacity)[:, None]  # [N, 1]; expit: no overflow warning for big logits
    colors = np.concatenate([base_rgb8(records.f_dc), np.rint(alpha * 255.0).astype(np.uint8)], axis=1)  # [N, 4]
    rest = sh_rest_rgb(records.f_rest) if sh and np.any(records.f_rest) else None
    return SplatArrays(np.ascontiguousarray(records.xyz, np.float32), np.exp(records.scale).astype(np.float32),
                       q.astype(np.float32), colors, rest)


def sh_rest_rgb(f_rest: np.ndarray) -> np.ndarray:  # [N, 45] -> [N, 15, 3]
    """Channel-major PLY ``f_rest`` [N, 45] (R 1..15, G 1..15, B 1..15) to [N, 15, 3] (coefficient, RGB)."""
    return np.ascontiguousarray(f_rest.reshape(-1, 3, _SH_REST).transpose(0, 2, 1), dtype=np.float32)


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two uint8 images of the same shape [H, W, 3]; inf when identical."""
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    mse = float(np.mean((a.astype(np.float32) - b.astype(np.float32)) ** 2)) / 255.0**2
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))
