"""The one frame type that flows from every dataset reader into the algorithms."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.view import VALID_DEPTH_M, DepthUnits
from memgs_ros.errors import DataError


@dataclass(frozen=True, eq=False)
class Frame:
    """One RGB(-D) frame.

    stamp_ns: capture time in integer nanoseconds.
    rgb: [H, W, 3] uint8, RGB order.
    depth_m: [H, W] float32 metres, NaN or 0 where invalid; or the camera's raw image
      (:class:`DepthUnits`, turned into metres where read: a tracker node's frames, whose tracker
      reads depth at its keypoints alone; ``depth_metres()`` gives the image); None for monocular input.
    camera: intrinsics (with distortion) of the colour image; depth is registered to it.
    T_wc_gt: [4, 4] float64 ground-truth camera-to-world pose, or None.
    """

    stamp_ns: int
    rgb: np.ndarray
    depth_m: np.ndarray | DepthUnits | None
    camera: PinholeCamera
    T_wc_gt: np.ndarray | None = None

    def __post_init__(self) -> None:
        h, w = self.camera.height, self.camera.width
        if self.rgb.dtype != np.uint8 or self.rgb.shape != (h, w, 3):
            raise DataError(
                f"rgb must be uint8 [{h}, {w}, 3] to match the camera, got {self.rgb.dtype} {self.rgb.shape}"
            )
        if isinstance(self.depth_m, DepthUnits):
            if self.depth_m.shape != (h, w):
                raise DataError(f"depth must be [{h}, {w}] to match the camera, got {self.depth_m.shape}")
        elif self.depth_m is not None and (self.depth_m.dtype != np.float32 or self.depth_m.shape != (h, w)):
            raise DataError(
                f"depth must be float32 [{h}, {w}] metres, got {self.depth_m.dtype} {self.depth_m.shape}"
            )
        if self.T_wc_gt is not None:
            T = np.asarray(self.T_wc_gt)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise DataError(f"T_wc_gt must be a finite 4x4 matrix, got shape {T.shape}")

    @property
    def stamp_s(self) -> float:
        return self.stamp_ns * 1e-9

    def depth_metres(self) -> np.ndarray | None:
        """[H, W] float32 metres (converted from ``DepthUnits``), None for monocular input."""
        return self.depth_m.metres() if isinstance(self.depth_m, DepthUnits) else self.depth_m

    def valid_depth_mask(self, min_m: float = VALID_DEPTH_M[0], max_m: float = VALID_DEPTH_M[1]) -> np.ndarray:
        """[H, W] bool: finite depth inside (min_m, max_m). All False when there is no depth."""
        d = self.depth_metres()
        if d is None:
            return np.zeros((self.camera.height, self.camera.width), dtype=bool)
        return np.isfinite(d) & (d > min_m) & (d < max_m)

    def has_valid_depth(self, min_m: float = VALID_DEPTH_M[0], max_m: float = VALID_DEPTH_M[1]) -> bool:
        """Whether ``valid_depth_mask(min_m, max_m)`` holds one True: a sparse grid of pixels first,
        which settles it for any frame with depth at a twentieth of the cost of the full mask."""
        if self.depth_m is None:
            return False
        if isinstance(self.depth_m, DepthUnits):
            return self.depth_m.has_valid((min_m, max_m))
        with np.errstate(invalid="ignore"):
            sparse = self.depth_m[::16, ::16]
            return bool(np.any((sparse > min_m) & (sparse < max_m))) or bool(self.valid_depth_mask(min_m, max_m).any())
