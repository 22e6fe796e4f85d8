"""The values the rasterizer takes and returns: :class:`Gaussians` in, :class:`RenderOutput` out,
and between projection and compositing :class:`Splats2D`.

Every backend (:func:`memgs_ros.core.raster.rasterize`'s torch, numba and gsplat paths, the
projection twins and the brute-force reference) takes one :class:`Gaussians` instead of six
separate tensors, so a new parameter or a check is written once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor


class Splats2D(NamedTuple):
    """N projected Gaussians, what every compositor takes (screen space, activated).

    means2d: [N, 2] px; conics: [N, 3] (a, b, c) of Sigma2D^-1; opacities: [N] in (0, 1);
    colors: [N, 3]; depths: [N] camera z (also the value blended into the depth image).
    """

    means2d: Tensor
    conics: Tensor
    opacities: Tensor
    colors: Tensor
    depths: Tensor

    def contiguous(self) -> Splats2D:
        """The same splats with every tensor contiguous (what the compositors' kernels read)."""
        return Splats2D(*(t.contiguous() for t in self))


@dataclass(frozen=True)
class RenderOutput:
    """One rendered view.

    color: [3, H, W]; depth: [H, W] alpha-blended camera z, sum_i w_i z_i (not divided by
    alpha); alpha: [H, W] accumulated opacity; means2d: [N, 2] screen-space means whose
    ``.grad`` holds dL/d(means2d) after backward (densification statistic); radii: [N] int32
    3-sigma screen radius in px, 0 where not visible; visible: [N] bool, the Gaussian is in
    front of the camera and can reach alpha >= 1/255 inside the image.
    """

    color: Tensor
    depth: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    visible: Tensor


def render_rgb8(color: Tensor) -> np.ndarray:  # [3, H, W] -> [H, W, 3]
    """A rendered colour image as 8-bit RGB on the host: round(255 clamp(color, 0, 1)), [H, W, 3] uint8."""
    return (color.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
