"""N Gaussians as tensors: :class:`Gaussians`, what every rasterizer backend takes and the
trainable map hands out (one tuple instead of six tensors, so a new parameter or a check is written once)."""
from __future__ import annotations

from typing import NamedTuple

from torch import Tensor


class Gaussians(NamedTuple):
    """N Gaussians, each tensor on one device (a tuple: ``means, *_ = g`` unpacks it).

    means: [N, 3] world; quats_wxyz: [N, 4] unnormalised; log_scales: [N, 3]; opacity_logits:
    [N, 1]; sh_dc: [N, 1, 3]; sh_rest: [N, K, 3], K = (deg_max + 1)^2 - 1 (may be 0).
    """

    means: Tensor
    quats_wxyz: Tensor
    log_scales: Tensor
    opacity_logits: Tensor
    sh_dc: Tensor
    sh_rest: Tensor

    def check(self, sh_degree: int) -> None:
        """ValueError naming the first tensor whose shape or device does not fit."""
        n = self.means.shape[0]
        expected = {"means": (n, 3), "quats_wxyz": (n, 4), "log_scales": (n, 3), "opacity_logits": (n, 1),
                    "sh_dc": (n, 1, 3)}
        for name, shape in expected.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise ValueError(f"rasterize: {name} must have shape {list(shape)}, got {list(t.shape)}")
            if t.device != self.means.device:
                raise ValueError(f"rasterize: {name} is on {t.device}, means on {self.means.device}")
        rest = self.sh_rest
        if rest.dim() != 3 or rest.shape[0] != n or rest.shape[2] != 3:
            raise ValueError(f"rasterize: sh_rest must have shape [{n}, K, 3], got {list(rest.shape)}")
        if rest.device != self.means.device:
            raise ValueError(f"rasterize: sh_rest is on {rest.device}, means on {self.means.device}")
        if not 0 <= sh_degree <= 3 or rest.shape[1] < (sh_degree + 1) ** 2 - 1:
            raise ValueError(
                f"rasterize: sh_degree {sh_degree} needs 0..3 and sh_rest with >= {(sh_degree + 1) ** 2 - 1} "
                f"coefficients, got {rest.shape[1]}"
            )
