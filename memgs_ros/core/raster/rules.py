"""The compositing rules every rasterizer backend shares (3DGS): torch, numba, the brute-force
reference and, through its own kernels, gsplat.

A Gaussian contributes to a pixel only where its alpha reaches ``MIN_ALPHA``; alpha is clamped
at ``MAX_ALPHA``; a pixel's list stops once its transmittance falls below ``MIN_TRANSMITTANCE``.
"""
from __future__ import annotations

MIN_ALPHA = 1.0 / 255.0
MAX_ALPHA = 0.99
MIN_TRANSMITTANCE = 1e-4
