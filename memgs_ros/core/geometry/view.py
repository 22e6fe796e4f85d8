"""One view preparation: incoming images -> the undistorted, resized images the map lives in.

The mapper trains on these images, the evaluation scores renders against them, the keyframe
sampler seeds from them (at full size) and the mapper node renders with their camera, so all
of them go through :func:`view_preparation`: one :class:`ViewPreparation` per (source camera,
resolution scale), shared by every caller.

Steps: undistort (colour bilinear, depth nearest so no depth is a blend of two surfaces; the
output camera is OpenCV's optimal new camera matrix at alpha 0, see :class:`Undistorter`), then
resize by ``resolution_scale`` (colour area-averaged, depth nearest). The valid mask marks the
output pixels whose full-resolution pixels all sampled the source image.

Depth comes in as metres (float, NaN/0 invalid) or as the camera's raw 16-bit units with a
``depth_scale`` (units per metre, 0 invalid; :func:`depth_to_metres`): raw depth is undistorted
and resized as it is (2 bytes a pixel) and turned into metres once, at the output size.

This module is also the one home of the undistortion pieces (:class:`Undistorter`,
:func:`undistorter_for`, :func:`undistort_uv`) and of the check that a keyframe's depth image
and the depths its producer measured agree (:func:`depth_scale_ratio`).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.errors import ConfigError, DataError

__all__ = [
    "VALID_DEPTH_M", "DepthUnits", "Undistorter", "ViewPreparation",
    "depth_to_metres", "depth_to_metres_checked", "load_kernels", "undistort_uv",
    "undistorter_for", "valid_pixel_mask", "view_preparation",
]

# A pixel of the resized image is valid when at least this fraction of the full-resolution
# pixels it averages carry content: all of them (a partly black pixel is no clean observation).
DEFAULT_MIN_VALID_FRACTION = 0.999
_CACHE_SIZE = 16  # (camera, scale) pairs: a few cameras x a few scales in one process
# Depths (metres, open interval) that count as a measurement (``Frame.has_valid_depth``).
VALID_DEPTH_M = (1e-6, 40.0)


def depth_to_metres(depth: np.ndarray,  # [H, W] uint16 units or float metres
                    depth_scale: float = 1.0) -> np.ndarray:
    """Raw depth -> [H, W] float32 metres, NaN where invalid, a new array.

    uint16 (16UC1, mono16): ``depth_scale`` units per metre, 0 = no measurement. Float: metres
    (``depth_scale`` 1.0); zero, negative and non-finite values become NaN.

    Compiled where numba is (one pass instead of numpy's several; a 640x480 frame 0.23 -> 0.07 ms
    as float, 0.18 -> 0.04 ms as 16-bit units), equal to ``_depth_to_metres_reference`` value for value.
    """
    return depth_to_metres_checked(depth, depth_scale)[0]


def depth_to_metres_checked(depth: np.ndarray,  # [H, W] uint16 units or float metres
                            depth_scale: float = 1.0, valid_m: tuple[float, float] = VALID_DEPTH_M
                            ) -> tuple[np.ndarray, bool]:
    """:func:`depth_to_metres` and whether one depth lies inside ``valid_m`` (open interval,
    metres: ``Frame.has_valid_depth``'s test), found in the same pass."""
    lo, hi = (np.float32(v) for v in valid_m)
    if _depth_kernels is not None and depth.ndim == 2 and depth.dtype in (np.uint16, np.float32):
        units_kernel, float_kernel = _depth_kernels
        out = np.empty(depth.shape, np.float32)
        kernel = units_kernel if depth.dtype == np.uint16 else float_kernel
        return out, bool(kernel(depth, np.float32(depth_scale), out, lo, hi))
    out = _depth_to_metres_reference(depth, depth_scale)
    with np.errstate(invalid="ignore"):
        return out, bool(np.any((out > lo) & (out < hi)))


@dataclass(frozen=True, eq=False)
class DepthUnits:
    """A depth image as the camera gave it, turned into metres only where read: raw [H, W] uint16
    units (``scale`` per metre, 0 = no measurement) or float32 (metres times ``scale``), as
    :func:`depth_to_metres` reads them. A tracker reads depth at its keypoints alone
    (``orb.keypoint_depths`` reads the units there), so the node hands it this (a read-only view
    on the message) rather than a converted float image: 1.2 MB less written and read again a
    640x480 frame."""

    raw: np.ndarray
    scale: float

    def __post_init__(self) -> None:
        if self.raw.ndim != 2 or self.raw.dtype not in (np.uint16, np.float32):
            raise DataError(f"raw depth must be uint16 or float32 [H, W], got {self.raw.dtype} {self.raw.shape}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise DataError(f"depth scale must be a positive number of units per metre, got {self.scale}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.raw.shape[0], self.raw.shape[1]

    def metres(self) -> np.ndarray:
        """The whole image in metres: ``depth_to_metres(raw, scale)``."""
        return depth_to_metres(_kernel_layout(self.raw), self.scale)

    def has_valid(self, valid_m: tuple[float, float] = VALID_DEPTH_M) -> bool:
        """Whether one depth lies inside ``valid_m`` (``Frame.has_valid_depth``): a sparse grid of
        pixels first, which settles it for any frame with depth, then the whole image."""
        return (depth_to_metres_checked(np.ascontiguousarray(self.raw[::16, ::16]), self.scale, valid_m)[1]
                or depth_to_metres_checked(_kernel_layout(self.raw), self.scale, valid_m)[1])


def _kernel_layout(a: np.ndarray) -> np.ndarray:
    """``a`` C-contiguous and writable, copied only where it is not (a message's read-only view):
    the layout the depth kernels are warmed for, so that no frame compiles a second signature."""
    return a if a.flags.c_contiguous and a.flags.writeable else np.array(a)


def _depth_to_metres_reference(depth: np.ndarray, depth_scale: float = 1.0) -> np.ndarray:
    """numpy twin of :func:`depth_to_metres`."""
    if depth.dtype == np.uint16:
        d = depth.astype(np.float32) / np.float32(depth_scale)
        d[depth == 0] = np.nan
        return d
    d = np.array(depth, dtype=np.float32)
    if depth_scale != 1.0:
        d /= np.float32(depth_scale)
    with np.errstate(invalid="ignore"):
        d[~(d > 0) | ~np.isfinite(d)] = np.nan
    return d


def _units_to_metres(depth, scale, out, lo, hi):
    """Compiled :func:`depth_to_metres` of uint16 units: depth [H, W] uint16, scale float32 units
    per metre, out [H, W] float32 (the same float32 division as numpy's); returns whether a depth
    lies in (lo, hi) metres."""
    nan = np.float32(np.nan)
    found = False
    for r in range(depth.shape[0]):
        for c in range(depth.shape[1]):
            d = depth[r, c]
            m = nan if d == 0 else np.float32(d) / scale
            out[r, c] = m
            found |= (m > lo) & (m < hi)
    return found


def _float_to_metres(depth, scale, out, lo, hi):
    """Compiled :func:`depth_to_metres` of float32 depth [H, W] (metres times ``scale``); returns
    whether a depth lies in (lo, hi) metres."""
    nan = np.float32(np.nan)
    one = scale == np.float32(1.0)
    found = False
    for r in range(depth.shape[0]):
        for c in range(depth.shape[1]):
            m = depth[r, c] if one else depth[r, c] / scale
            m = m if (m > 0 and m < np.inf) else nan
            out[r, c] = m
            found |= (m > lo) & (m < hi)
    return found


def _metres_to_units(depth, scale, out):
    """Compiled :func:`metres_to_units`: depth [H, W] float32 metres, scale float64 units per metre,
    out [H, W] uint16 (rounded half to even in float64 as numpy's ``rint``; 0 where invalid or
    beyond 65535 units)."""
    for r in range(depth.shape[0]):
        for c in range(depth.shape[1]):
            d = depth[r, c]
            u = np.rint(np.float64(d) * scale) if (d > 0 and d < np.inf) else 0.0
            out[r, c] = np.uint16(u) if u <= 65535.0 else np.uint16(0)


# The compiled depth passes, once ``load_kernels`` ran in this process (None: the numpy twins).
_depth_kernels = None
_units_kernel = None


def load_kernels() -> bool:
    """Compile (or load from numba's cache) the depth passes, so that this process converts depth
    compiled from now on; False where numba is missing. Only a process that converts every frame
    calls it (the tracker's warm-up, a player that encodes depth): numba costs a process ~100 MB,
    which the sampler and merger, converting a keyframe now and then, do without."""
    global _depth_kernels, _units_kernel
    if _depth_kernels is None and numba_available():
        import numba

        _depth_kernels = (numba.njit(cache=True, nogil=True)(_units_to_metres),
                          numba.njit(cache=True, nogil=True)(_float_to_metres))
        _units_kernel = numba.njit(cache=True, nogil=True)(_metres_to_units)
        depth_to_metres_checked(np.ones((2, 2), np.uint16), 1000.0)  # both depth encodings
        depth_to_metres_checked(np.ones((2, 2), np.float32))
        metres_to_units(np.ones((2, 2), np.float32), 1000.0)
    return _depth_kernels is not None


def metres_to_units(depth_m: np.ndarray,  # [H, W] float32 metres
                    depth_scale: float) -> np.ndarray:
    """[H, W] float32 metres -> [H, W] uint16 units (``depth_scale`` per metre), the inverse of
    :func:`depth_to_metres`: rounded to nearest (ties to even); non-finite, non-positive depths and
    depths beyond 65535 units become 0 (invalid) rather than clamped, so no wrong depth reaches the
    tracker. Compiled where numba is (one pass instead of numpy's six: 2.9 ms a 640x480 frame
    before, the replay's largest cost), equal to ``_metres_to_units_reference`` value for value."""
    d = np.asarray(depth_m, dtype=np.float32)
    if _units_kernel is not None and d.ndim == 2:
        out = np.empty(d.shape, np.uint16)
        _units_kernel(d, float(depth_scale), out)
        return out
    return _metres_to_units_reference(d, depth_scale)


def _metres_to_units_reference(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """numpy twin of :func:`metres_to_units`."""
    d = np.asarray(depth_m, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
    units = np.where(valid, np.rint(d.astype(np.float64) * depth_scale), 0.0)
    units[units > 65535] = 0
    return units.astype(np.uint16)


class Undistorter:
    """Undistorts colour (bilinear) and depth (nearest neighbour, so no depth is ever a blend of
    two surfaces) images of one camera to a pinhole camera of the same size without distortion.

    With ``crop_to_valid`` (default) the output camera is OpenCV's optimal new camera matrix at
    alpha 0: a slight zoom (fr1: fx 517 -> 547) chosen so that every output pixel samples the
    source image. Without it the output keeps K, and the corners and edges that no source pixel
    reaches stay black (colour) / NaN (depth): on fr1 that border is 6 % of the image, no
    observation at all, yet a map renders scene there, which costs whole-image PSNR several dB.
    The remap tables are built once per camera; ``camera_undistorted`` is the output camera.
    """

    def __init__(self, camera: PinholeCamera, crop_to_valid: bool = True) -> None:
        self.camera = camera
        self.camera_undistorted = camera.undistorted()
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        if camera.has_distortion:
            K = camera.K
            size = (camera.width, camera.height)
            K_out = K
            if crop_to_valid:
                K_out, _ = cv2.getOptimalNewCameraMatrix(K, camera.dist_coeffs, size, 0.0, size)
                if not np.all(np.isfinite(K_out)) or K_out[0, 0] <= 0 or K_out[1, 1] <= 0:
                    raise DataError(f"distortion {camera.dist} has no valid undistorted region")
                self.camera_undistorted = PinholeCamera(
                    camera.width, camera.height, float(K_out[0, 0]), float(K_out[1, 1]),
                    float(K_out[0, 2]), float(K_out[1, 2]))
            self._maps = cv2.initUndistortRectifyMap(
                K, camera.dist_coeffs, None, K_out, size, cv2.CV_32FC1)

    def __call__(self, rgb: np.ndarray,  # [H, W, 3] uint8
                 depth_m: np.ndarray | None = None,  # [H, W] float32 metres or uint16 raw units, or None
                 ) -> tuple[np.ndarray, np.ndarray | None, PinholeCamera]:
        """Returns (rgb [H, W, 3] uint8, depth [H, W] (float32, or uint16 as given) or None,
        undistorted camera). Pixels no source pixel reaches: black, depth NaN (uint16: 0)."""
        h, w = self.camera.height, self.camera.width
        if rgb.shape[:2] != (h, w):
            raise DataError(f"image is {rgb.shape[1]}x{rgb.shape[0]} but the camera is {w}x{h}")
        if depth_m is not None and depth_m.shape != (h, w):
            raise DataError(f"depth is {depth_m.shape[1]}x{depth_m.shape[0]} but the camera is {w}x{h}")
        if self._maps is None:
            return rgb, depth_m, self.camera_undistorted
        mx, my = self._maps
        rgb_u = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        depth_u = None
        if depth_m is not None:
            raw = depth_m.dtype == np.uint16
            depth_u = cv2.remap(depth_m if raw else np.ascontiguousarray(depth_m, dtype=np.float32), mx, my,
                                cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                borderValue=0 if raw else float("nan"))
        return rgb_u, depth_u, self.camera_undistorted

    @property
    def maps(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The remap tables (x, y: [H, W] float32 source positions), None without distortion."""
        return self._maps

    def undistort_uv(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixel positions [M, 2] -> [M, 2] float64 in the output image."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if not self.camera.has_distortion or pts.shape[0] == 0:
            return pts.reshape(-1, 2).copy()
        out = cv2.undistortPoints(pts, self.camera.K, self.camera.dist_coeffs, P=self.camera_undistorted.K)
        return out.reshape(-1, 2).astype(np.float64)

    def from_pinhole_uv(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted pixel positions [M, 2] in the source camera's own K (what
        :func:`undistort_uv` and the tracker's keypoints give) -> [M, 2] float64 in the output
        image (``camera_undistorted``)."""
        src, dst = self.camera, self.camera_undistorted
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        scale = np.array([dst.fx / src.fx, dst.fy / src.fy])
        return (uv - np.array([src.cx, src.cy])) * scale + np.array([dst.cx, dst.cy])

    @functools.cached_property
    def valid_mask(self) -> np.ndarray | None:
        """[H, W] bool: undistorted pixels whose source lies inside the image (the rest are the
        black / NaN border); None without distortion (every pixel valid)."""
        if self._maps is None:
            return None
        mx, my = self._maps
        w, h = self.camera.width, self.camera.height
        return np.ascontiguousarray((mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1))


@functools.lru_cache(maxsize=8)
def undistorter_for(camera: PinholeCamera) -> Undistorter:
    """Remap tables per camera (building them costs ~12 ms at 640x480; applying them ~7 ms)."""
    return Undistorter(camera)


def undistort_uv(uv: np.ndarray,  # [M, 2] distorted px
                 camera: PinholeCamera) -> np.ndarray:
    """Keypoint positions [M, 2] in the distorted image -> [M, 2] float64 undistorted with the
    camera's own K (the tracker's frame; :meth:`Undistorter.from_pinhole_uv` maps them into the
    undistorted images)."""
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    if not camera.has_distortion or pts.shape[0] == 0:
        return pts.reshape(-1, 2).copy()
    out = cv2.undistortPoints(pts, camera.K, camera.dist_coeffs, P=camera.K)
    return out.reshape(-1, 2).astype(np.float64)


def _check_scale(resolution_scale: float) -> float:
    s = float(resolution_scale)
    if not (math.isfinite(s) and s > 0.0):
        raise ConfigError(f"resolution_scale must be a positive finite number, got {resolution_scale}")
    return s


def valid_pixel_mask(camera: PinholeCamera, resolution_scale: float = 1.0,
                     min_fraction: float = DEFAULT_MIN_VALID_FRACTION) -> np.ndarray | None:
    """Pixels of the prepared image that carry image content: [h, w] bool, None when ``camera``
    has no distortion (every pixel valid).

    Undistortion samples the source image at a remapped position; pixels whose bilinear sample
    lies outside the source are filled with black and are no observation. After the resize a
    pixel is valid when at least ``min_fraction`` of the full-resolution pixels it averages are
    (default: all of them; a small value keeps any pixel with content). The mask of a
    :class:`ViewPreparation` is this with the default ``min_fraction``.
    """
    scale = _check_scale(resolution_scale)
    valid = undistorter_for(camera).valid_mask
    if valid is None:
        return None
    if scale != 1.0:
        out = camera.scaled(scale)
        frac = cv2.resize(valid.astype(np.float32), (out.width, out.height), interpolation=cv2.INTER_AREA)
        valid = frac >= min_fraction
    return np.ascontiguousarray(valid)


@dataclass(frozen=True, eq=False)
class ViewPreparation:
    """Built once per (source camera, resolution scale); get it from :func:`view_preparation`.

    source: camera of the incoming images (may carry distortion); camera: output camera
    (undistorted, cropped to the valid region, scaled; no distortion); valid_mask: [h, w] bool,
    output pixels with image content, None when all are valid. The mask is shared by every
    caller: read it, do not write it.
    """

    source: PinholeCamera
    resolution_scale: float
    camera: PinholeCamera
    valid_mask: np.ndarray | None  # [h, w] bool
    _undistorter: Undistorter = field(repr=False)

    def __call__(self, rgb: np.ndarray,  # [H, W, 3] uint8 at source size
                 depth: np.ndarray | None = None,  # [H, W] float metres or uint16 raw units, or None
                 depth_scale: float = 1.0,  # raw units per metre (uint16 depth)
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """rgb [H, W, 3] uint8 and depth [H, W] at the source size -> (rgb [h, w, 3] uint8,
        depth_m [h, w] float32 metres or None) at the output size.

        Colour: bilinear undistortion then area-averaged resize; depth: nearest for both, so no
        depth is invented across an edge (raw depth goes through both steps as 16-bit units and
        becomes metres at the output size). Pixels outside ``valid_mask`` are black / NaN.
        """
        h, w = self.source.height, self.source.width
        if rgb.dtype != np.uint8 or rgb.shape != (h, w, 3):
            raise DataError(f"image must be uint8 [{h}, {w}, 3] to match the camera "
                            f"({w}x{h}), got {rgb.dtype} {list(rgb.shape)}")
        if depth is not None and depth.dtype != np.uint16:
            depth = np.asarray(depth, dtype=np.float32)
        rgb_u, depth_u, _ = self._undistorter(rgb, depth)
        if self.resolution_scale != 1.0:
            size = (self.camera.width, self.camera.height)
            rgb_u = cv2.resize(rgb_u, size, interpolation=cv2.INTER_AREA)
            if depth_u is not None:
                depth_u = cv2.resize(depth_u, size, interpolation=cv2.INTER_NEAREST)
        if depth_u is not None and (depth_u.dtype == np.uint16 or depth_scale != 1.0):
            depth_u = depth_to_metres(depth_u, depth_scale)
        return np.ascontiguousarray(rgb_u), depth_u

    def undistortion_maps(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The full-size remap tables (x, y source positions [H, W] float32 per output pixel), None
        without distortion. Read them, do not write them."""
        return self._undistorter.maps

    @functools.cached_property
    def depth_source_index(self) -> np.ndarray:
        """[h, w] int64: the source pixel (row-major linear index) each output depth pixel takes,
        -1 where none (the border undistortion leaves). Made with the very remap and resize
        ``__call__`` applies, so a gather with it is that depth path exactly (the device
        preparation gathers with it)."""
        h, w = self.source.height, self.source.width
        if h * w >= 2**24:
            raise DataError(f"a {w}x{h} image is too large for a float32 pixel index")
        index = np.arange(1, h * w + 1, dtype=np.float32).reshape(h, w)  # exact below 2**24; 0 is no pixel
        _, idx, _ = self._undistorter(np.zeros((h, w, 3), np.uint8), index)  # the border becomes NaN
        assert idx is not None
        if self.resolution_scale != 1.0:
            idx = cv2.resize(idx, (self.camera.width, self.camera.height), interpolation=cv2.INTER_NEAREST)
        return np.where(np.isfinite(idx), idx, 0.0).astype(np.int64) - 1


def view_preparation(camera: PinholeCamera, resolution_scale: float = 1.0) -> ViewPreparation:
    """The shared :class:`ViewPreparation` of ``camera`` at ``resolution_scale`` (bounded LRU
    cache, so every caller gets the same object for the same pair). ConfigError for a scale
    that is not positive and finite."""
    # Normalise before the cache: view_preparation(cam) and view_preparation(cam, 1) are one entry.
    return _view_preparation(camera, _check_scale(resolution_scale))


@functools.lru_cache(maxsize=_CACHE_SIZE)
def _view_preparation(camera: PinholeCamera, scale: float) -> ViewPreparation:
    undistorter = undistorter_for(camera)
    out = undistorter.camera_undistorted
    if scale != 1.0:
        out = out.scaled(scale)
    return ViewPreparation(source=camera, resolution_scale=scale, camera=out,
                           valid_mask=valid_pixel_mask(camera, scale), _undistorter=undistorter)
