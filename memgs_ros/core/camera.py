"""Pinhole camera with plumb_bob (k1, k2, p1, p2, k3) or rational_polynomial (+ k4, k5, k6)
distortion, and the TUM presets."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from memgs_ros.errors import DataError

# plumb_bob: k1 k2 p1 p2 k3; rational_polynomial adds k4 k5 k6. Both are OpenCV's order, so
# dist_coeffs goes to cv2 as it is.
DIST_LENS = (5, 8)


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of one camera, in pixels. ``dist`` is plumb_bob (k1, k2, p1, p2, k3) or
    rational_polynomial (k1, k2, p1, p2, k3, k4, k5, k6)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise DataError(f"camera size must be positive, got {self.width}x{self.height}")
        for name in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise DataError(f"camera {name} is not finite ({v})")
        if not (self.fx > 0 and self.fy > 0):
            raise DataError(f"camera focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        if len(self.dist) not in DIST_LENS:
            raise DataError(f"distortion needs 5 (plumb_bob) or 8 (rational_polynomial) coefficients, "
                            f"got {len(self.dist)}")
        if not all(np.isfinite(d) for d in self.dist):
            raise DataError(f"distortion coefficients must be finite, got {self.dist}")

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """Distortion as the float64 array OpenCV expects: [5] or [8]."""
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def distortion_model(self) -> str:
        """The CameraInfo name of ``dist``: plumb_bob or rational_polynomial."""
        return "plumb_bob" if len(self.dist) == 5 else "rational_polynomial"

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0.0 for d in self.dist)

    def scaled(self, factor: float) -> "PinholeCamera":
        """The same camera for an image resized by ``factor`` (pixel-centre convention)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return replace(
            self,
            width=w,
            height=h,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )

    def undistorted(self) -> "PinholeCamera":
        """The same intrinsics with zero distortion (after undistorting the images)."""
        return replace(self, dist=(0.0, 0.0, 0.0, 0.0, 0.0))

    def backproject(self, u: np.ndarray, v: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """Pixels (undistorted) and depths to camera-frame points.

        u, v, depth_m: [M]. Returns p_c: [M, 3].
        """
        z = np.asarray(depth_m, dtype=np.float64)
        x = (np.asarray(u, dtype=np.float64) - self.cx) / self.fx * z
        y = (np.asarray(v, dtype=np.float64) - self.cy) / self.fy * z
        return np.stack([x, y, z], axis=-1)

    def project(self, p_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points [M, 3] to pixel coordinates (u [M], v [M]); no distortion."""
        p = np.asarray(p_c, dtype=np.float64)
        z = p[:, 2]
        return self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy


# TUM RGB-D calibrations (reference section 6), 640x480.
TUM_FR1 = PinholeCamera(640, 480, 517.306408, 516.469215, 318.643040, 255.313989,
                        (0.262383, -0.953104, -0.005358, 0.002628, 1.163314))
TUM_FR2 = PinholeCamera(640, 480, 520.908620, 521.007327, 325.141442, 249.701764,
                        (0.231222, -0.784899, -0.003257, -0.000105, 0.917205))
TUM_FR3 = PinholeCamera(640, 480, 535.4, 539.2, 320.1, 247.6)

TUM_CAMERAS: dict[str, PinholeCamera] = {"fr1": TUM_FR1, "fr2": TUM_FR2, "fr3": TUM_FR3}
# Depth PNG value per metre for each TUM camera.
TUM_DEPTH_FACTORS: dict[str, float] = {"fr1": 5000.0, "fr2": 5208.0, "fr3": 5000.0}
