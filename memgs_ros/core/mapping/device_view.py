"""The view preparation on a torch device: the twin of ``ViewPreparation.__call__``
(``core/geometry/view.py``, OpenCV on the host, the reference).

A keyframe reaches the mapper as compact images (colour uint8, depth uint16 raw units or float
metres). On a GPU they are uploaded as they are (1.5 MB at 640x480 with 16-bit depth) and
undistorted, resized and turned into the training images there, instead of on the CPU beside
the tracker:

- colour: bilinear sampling at the undistortion map (``grid_sample``, zero border, as
  ``cv2.remap`` with a constant 0 border), then area averaging to the output size
  (``F.interpolate(mode="area")``, what ``cv2.INTER_AREA`` does for whole-number ratios), rounded to
  uint8. OpenCV interpolates 8-bit images in fixed point: the two agree to a level or two.
- depth: one gather with ``ViewPreparation.depth_source_index`` (made by OpenCV's own nearest
  remap and resize), then units -> metres: the same values as the host path, bit for bit.
- the valid mask is the preparation's, uploaded once.

``DeviceView`` holds those tables on one device; ``device_view(prep, device)`` caches one per
(preparation, device).
"""
from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F

from memgs_ros.core.geometry.view import ViewPreparation
from memgs_ros.errors import DataError

__all__ = ["DeviceView", "device_view"]


class DeviceView:
    """One ``ViewPreparation``'s tables on ``device`` (see module docstring)."""

    def __init__(self, prep: ViewPreparation, device: torch.device) -> None:
        self.prep = prep
        self.device = torch.device(device)
        src = prep.source
        maps = prep.undistortion_maps()
        self._grid: torch.Tensor | None = None  # [1, H, W, 2] in grid_sample's [-1, 1] (align_corners)
        if maps is not None:
            mx, my = maps
            gx = 2.0 * mx / max(src.width - 1, 1) - 1.0
            gy = 2.0 * my / max(src.height - 1, 1) - 1.0
            self._grid = torch.from_numpy(np.stack([gx, gy], axis=-1)[None].astype(np.float32)).to(self.device)
        index = prep.depth_source_index.reshape(-1)
        self._has_border = bool((index < 0).any())
        self._index = torch.from_numpy(np.maximum(index, 0)).to(self.device)  # [h * w]
        self._index_valid = torch.from_numpy(index >= 0).to(self.device) if self._has_border else None
        self.valid_mask = None if prep.valid_mask is None else torch.from_numpy(prep.valid_mask).to(self.device)

    def __call__(self, rgb: torch.Tensor,  # [H, W, 3] uint8 on the device
                 depth: torch.Tensor | None = None,  # [H, W] uint16 raw units or float metres
                 depth_scale: float = 1.0,  # raw units per metre
                 ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """-> (rgb [3, h, w] uint8, depth [h, w] float32 metres with 0 where invalid, or None)."""
        src, out = self.prep.source, self.prep.camera
        if rgb.dtype != torch.uint8 or tuple(rgb.shape) != (src.height, src.width, 3):
            raise DataError(f"image must be uint8 [{src.height}, {src.width}, 3], got {rgb.dtype} {tuple(rgb.shape)}")
        x = rgb.permute(2, 0, 1)[None].float()  # [1, 3, H, W]
        if self._grid is not None:
            x = F.grid_sample(x, self._grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        if (out.height, out.width) != (src.height, src.width):
            x = F.interpolate(x, size=(out.height, out.width), mode="area")
        color = x[0].round_().clamp_(0.0, 255.0).to(torch.uint8)
        if depth is None:
            return color, None
        if tuple(depth.shape) != (src.height, src.width):
            raise DataError(f"depth must be [{src.height}, {src.width}], got {tuple(depth.shape)}")
        flat = depth.reshape(-1)
        if flat.dtype == torch.uint16:  # gather on int32: uint16 has few kernels on some devices
            flat = flat.to(torch.int32)
        d = flat[self._index].reshape(out.height, out.width).float()
        if depth_scale != 1.0:
            d = d / float(depth_scale)
        d = torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d))
        if self._index_valid is not None:
            d = d * self._index_valid.reshape(out.height, out.width)
        return color, d


@functools.lru_cache(maxsize=16)
def _cached(prep: ViewPreparation, device: str) -> DeviceView:
    return DeviceView(prep, torch.device(device))


def device_view(prep: ViewPreparation, device: torch.device | str) -> DeviceView:
    """The shared ``DeviceView`` of ``prep`` on ``device``."""
    return _cached(prep, str(torch.device(device)))
