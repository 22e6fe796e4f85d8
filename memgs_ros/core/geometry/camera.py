"""Pinhole camera with plumb_bob (k1, k2, p1, p2, k3) or rational_polynomial (+ k4, k5, k6)
distortion, and the TUM presets."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any, ClassVar

import numpy as np

from memgs_ros.errors import ConfigError, DataError

# Prefix of a calibration in node parameters (CameraCalibration fields as "camera.fx", ...).
CAMERA_PREFIX = "camera"

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

    def as_dict(self) -> dict[str, Any]:
        """The camera as a file records it (JSON-able): width, height, fx, fy, cx, cy, dist."""
        return {"width": int(self.width), "height": int(self.height), "fx": float(self.fx), "fy": float(self.fy),
                "cx": float(self.cx), "cy": float(self.cy), "dist": [float(x) for x in self.dist]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PinholeCamera:
        """The camera of an ``as_dict`` record (no ``dist``: none)."""
        return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                   tuple(float(x) for x in d.get("dist") or (0.0,) * 5))

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

    def scaled(self, factor: float) -> PinholeCamera:
        """The same camera for an image resized by ``factor`` (pixel-centre convention)."""
        w = max(1, round(self.width * factor))
        h = max(1, round(self.height * factor))
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

    def fitted(self, width: int, height: int) -> PinholeCamera:
        """This camera for images of ``width`` x ``height``: itself when the size matches, rescaled
        when only the resolution differs (same aspect ratio within a pixel); DataError otherwise."""
        if (width, height) == (self.width, self.height):
            return self
        f = width / self.width
        if abs(height - self.height * f) > 1.0:
            raise DataError(f"images are {width}x{height}, the camera is {self.width}x{self.height} "
                            "with another aspect ratio")
        return self.scaled(f)

    def undistorted(self) -> PinholeCamera:
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


def calibration_differences(measured: PinholeCamera, reference: PinholeCamera,
                            rel_tol: float = 0.01) -> list[str]:
    """Where ``measured`` (a camera_info) departs from ``reference`` (a calibration) by more than
    ``rel_tol`` in fx, fy, cx or cy, or where one has distortion and the other none; [] when
    they agree. ``reference`` is first fitted to ``measured``'s image size, so a calibration of
    the full-size sensor compares with a camera_info of scaled images."""
    try:
        ref = reference.fitted(measured.width, measured.height)
    except DataError:
        return [f"image size {measured.width}x{measured.height} vs {reference.width}x{reference.height}"]
    out = []
    for name in ("fx", "fy", "cx", "cy"):
        m, r = float(getattr(measured, name)), float(getattr(ref, name))
        if abs(m - r) > rel_tol * abs(r):
            out.append(f"{name} {m:.1f} vs {r:.1f} ({(m - r) / abs(r) * 100:+.1f} %)")
    if measured.has_distortion != ref.has_distortion:
        out.append("distortion " + ("present vs none" if measured.has_distortion else "none vs present"))
    return out


def describe_camera(camera: PinholeCamera) -> str:
    """One line for messages: 'fx 525.0, fy 525.0, cx 319.5, cy 239.5, no distortion (640x480)'."""
    dist = (f"{camera.distortion_model} distortion" if camera.has_distortion else "no distortion")
    return (f"fx {camera.fx:.1f}, fy {camera.fy:.1f}, cx {camera.cx:.1f}, cy {camera.cy:.1f}, {dist} "
            f"({camera.width}x{camera.height})")


@dataclass(frozen=True)
class CameraCalibration:
    """A calibration given as parameters (``camera.<field>``), used instead of camera_info.

    Every field 0 means no calibration is given. width and height are the image size the
    intrinsics belong to: images of another size with the same aspect ratio get them rescaled.
    Distortion is plumb_bob (k1 k2 p1 p2 k3), or rational_polynomial when k4..k6 are not all 0.
    """

    width: int = 0  # image width the intrinsics belong to, px (0: no calibration given)
    height: int = 0  # image height the intrinsics belong to, px
    fx: float = 0.0  # focal length x, px
    fy: float = 0.0  # focal length y, px
    cx: float = 0.0  # principal point x, px
    cy: float = 0.0  # principal point y, px
    k1: float = 0.0  # radial distortion (OpenCV order k1 k2 p1 p2 k3 k4 k5 k6)
    k2: float = 0.0  # radial distortion
    p1: float = 0.0  # tangential distortion
    p2: float = 0.0  # tangential distortion
    k3: float = 0.0  # radial distortion
    k4: float = 0.0  # rational_polynomial numerator (0 for plumb_bob)
    k5: float = 0.0  # rational_polynomial numerator (0 for plumb_bob)
    k6: float = 0.0  # rational_polynomial numerator (0 for plumb_bob)

    # Distortion coefficients take either sign; 0 everywhere means "no calibration given".
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "width": (0, 100_000), "height": (0, 100_000), "fx": (0.0, 1e6), "fy": (0.0, 1e6),
        "cx": (-1e6, 1e6), "cy": (-1e6, 1e6),
        **dict.fromkeys(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), (-1000000.0, 1000000.0)),
    }

    def __post_init__(self) -> None:
        if not self.given:
            if any(getattr(self, f.name) for f in fields(self)):
                raise ConfigError("a camera calibration needs camera.width, height, fx, fy, cx and cy; "
                                  f"only some are set ({self._set_names()})")
            return
        missing = [n for n in ("width", "height", "fx", "fy", "cx", "cy") if not getattr(self, n)]
        if missing:
            raise ConfigError(f"camera calibration: camera.{', camera.'.join(missing)} missing or 0")
        try:
            self.camera()
        except DataError as err:
            raise ConfigError(f"camera calibration: {err}") from err

    @property
    def given(self) -> bool:
        """True when a calibration is set (fx > 0); all-zero fields mean none."""
        return self.fx != 0.0

    def _set_names(self) -> str:
        return ", ".join(f.name for f in fields(self) if getattr(self, f.name))

    def camera(self) -> PinholeCamera | None:
        """The calibrated camera, or None when no calibration is given."""
        if not self.given:
            return None
        dist: tuple[float, ...] = (self.k1, self.k2, self.p1, self.p2, self.k3)
        if self.k4 or self.k5 or self.k6:
            dist = (*dist, self.k4, self.k5, self.k6)
        return PinholeCamera(int(self.width), int(self.height), float(self.fx), float(self.fy),
                             float(self.cx), float(self.cy), tuple(float(d) for d in dist))

    @classmethod
    def from_camera(cls, camera: PinholeCamera) -> CameraCalibration:
        d = tuple(camera.dist) + (0.0,) * (8 - len(camera.dist))
        return cls(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
                   k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4], k4=d[5], k5=d[6], k6=d[7])

    @classmethod
    def from_params(cls, params: Mapping[str, object], prefix: str = "camera.") -> CameraCalibration:
        """From a node's parameter dict (``camera.fx`` ...); other keys are ignored. ConfigError
        names a value that is not a number."""
        values: dict[str, object] = {}
        for f in fields(cls):
            key = prefix + f.name
            if key not in params:
                continue
            v = params[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"parameter '{key}' must be a number, got {v!r}")
            values[f.name] = int(v) if f.type in (int, "int") else float(v)
        return cls(**values)  # type: ignore[arg-type]


# TUM RGB-D calibrations (reference section 6), 640x480.
TUM_FR1 = PinholeCamera(640, 480, 517.306408, 516.469215, 318.643040, 255.313989,
                        (0.262383, -0.953104, -0.005358, 0.002628, 1.163314))
TUM_FR2 = PinholeCamera(640, 480, 520.908620, 521.007327, 325.141442, 249.701764,
                        (0.231222, -0.784899, -0.003257, -0.000105, 0.917205))
TUM_FR3 = PinholeCamera(640, 480, 535.4, 539.2, 320.1, 247.6)

TUM_CAMERAS: dict[str, PinholeCamera] = {"fr1": TUM_FR1, "fr2": TUM_FR2, "fr3": TUM_FR3}
# Depth PNG value per metre for each TUM camera.
TUM_DEPTH_FACTORS: dict[str, float] = {"fr1": 5000.0, "fr2": 5208.0, "fr3": 5000.0}
