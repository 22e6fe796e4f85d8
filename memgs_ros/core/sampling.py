"""Patch-Grid (PG) sampling of a keyframe into seed points for new Gaussians (paper Sec. II-B,
reference sec. 2).

The image is split into square cells of ``grid_size`` px. A cell holding fewer than
``num_thr`` keypoints receives ``num_thr - count`` uniform random samples, kept
``margin_px`` inside its edges; border cells narrower or shorter than
``grid_size - skip_short_px`` are skipped, and a sample landing on a keypoint's pixel (or on
another sample's) is redrawn. Seeds are the keypoints that have a depth plus the samples that
get one: from the depth image (RGB-D) or from the nearest keypoint with a depth (monocular).

Pixel convention (OpenCV): pixel (u, v) with integer u, v has its centre at (u, v), so a
sub-pixel keypoint lies in pixel ``round(u), round(v)``. Samples are drawn on integer pixels,
so their depth and colour are read exactly at the pixel they back-project from.
All images here are undistorted: :func:`memgs_ros.core.geometry.view.view_preparation` makes them so, and
:meth:`memgs_ros.core.geometry.view.Undistorter.from_pinhole_uv` puts the tracker's keypoints into them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.errors import ConfigError, DataError

__all__ = [
    "PG_MONO_TUM",
    "PG_RGBD",
    "SOURCE_KEYPOINT",
    "SOURCE_PATCH_GRID",
    "PatchGridConfig",
    "SeedPoints",
    "patch_grid_uv",
    "seeds_mono",
    "seeds_rgbd",
]

SOURCE_KEYPOINT = 0
SOURCE_PATCH_GRID = 1
_MAX_REDRAW_ROUNDS = 64  # redraws needed are rare (8 samples in a >= 20x20 px box); bound the loop


@dataclass(frozen=True)
class PatchGridConfig:
    """Patch-Grid sampling parameters (reference sec. 2)."""

    enabled: bool = True  # False: seed from keypoints only (ablation of PG sampling)
    grid_size: int = 80  # cell size in px (RGB-D 80; monocular TUM 50, monocular Replica 80)
    num_thr: int = 8  # a cell with fewer keypoints than this is filled up to it with samples
    margin_px: int = 5  # samples stay this far inside the cell edges
    skip_short_px: int = 30  # border cells narrower or shorter than grid_size - this are skipped
    min_depth_m: float = 1e-10  # seeds need depth strictly above this
    max_depth_m: float = 40.0  # seeds need depth strictly below this
    # Monocular: a sample takes the depth of the nearest keypoint with depth within this many px.
    # The released code used a squared distance of 1 px, which keeps almost no samples; 20 px
    # keeps most samples near structure while refusing to extrapolate across empty regions.
    max_px_dist: float = 20.0
    seed: int = 0  # seed of the sampler's random generator (see rng_for)

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "grid_size": (4, 4096), "num_thr": (0, 10**4), "margin_px": (0, 1024), "skip_short_px": (0, 4096),
        "min_depth_m": (0.0, 1e3), "max_depth_m": (1e-3, 1e4), "max_px_dist": (0.0, 1e4), "seed": (0, 2**31 - 1),
    }

    def __post_init__(self) -> None:
        if self.grid_size < 1:
            raise ConfigError(f"patch_grid.grid_size must be >= 1 px, got {self.grid_size}")
        if self.num_thr < 0:
            raise ConfigError(f"patch_grid.num_thr must be >= 0, got {self.num_thr}")
        if self.margin_px < 0 or 2 * self.margin_px >= self.grid_size:
            raise ConfigError(
                f"patch_grid.margin_px must be in [0, grid_size / 2), got {self.margin_px} "
                f"with grid_size {self.grid_size}")
        if self.skip_short_px < 0:
            raise ConfigError(f"patch_grid.skip_short_px must be >= 0, got {self.skip_short_px}")
        if not (0.0 <= self.min_depth_m < self.max_depth_m):
            raise ConfigError(
                f"patch_grid depth range must satisfy 0 <= min_depth_m < max_depth_m, "
                f"got {self.min_depth_m} and {self.max_depth_m}")
        if not self.max_px_dist >= 0.0:
            raise ConfigError(f"patch_grid.max_px_dist must be >= 0, got {self.max_px_dist}")

    def rng_for(self, keyframe_id: int) -> np.random.Generator:
        """A generator that depends only on (seed, keyframe_id): reproducible per keyframe."""
        return np.random.default_rng([int(self.seed), int(keyframe_id)])


PG_RGBD = PatchGridConfig()
PG_MONO_TUM = PatchGridConfig(grid_size=50)


@dataclass(frozen=True, eq=False)
class SeedPoints:
    """Seeds of one keyframe. points_w: [S, 3] float32 world; colors: [S, 3] float32 RGB in
    [0, 1]; source: [S] uint8 (SOURCE_KEYPOINT 0, SOURCE_PATCH_GRID 1)."""

    points_w: np.ndarray
    colors: np.ndarray
    keyframe_id: int
    source: np.ndarray

    def __post_init__(self) -> None:
        s = self.points_w.shape[0] if self.points_w.ndim == 2 else -1
        if self.points_w.shape != (s, 3) or self.points_w.dtype != np.float32:
            raise DataError("SeedPoints.points_w must be float32 [S, 3], "
                            f"got {self.points_w.dtype} {self.points_w.shape}")
        if self.colors.shape != (s, 3) or self.colors.dtype != np.float32:
            raise DataError(f"SeedPoints.colors must be float32 [{s}, 3], got {self.colors.dtype} {self.colors.shape}")
        if self.source.shape != (s,) or self.source.dtype != np.uint8:
            raise DataError(f"SeedPoints.source must be uint8 [{s}], got {self.source.dtype} {self.source.shape}")

    def __len__(self) -> int:
        return int(self.points_w.shape[0])

    @property
    def n_keypoint(self) -> int:
        return int((self.source == SOURCE_KEYPOINT).sum())

    @property
    def n_patch_grid(self) -> int:
        return int((self.source == SOURCE_PATCH_GRID).sum())


def _pixel_of(uv: np.ndarray) -> np.ndarray:
    """Sub-pixel coordinates [M, 2] -> the integer pixel containing them [M, 2] (int64)."""
    return np.floor(np.asarray(uv, dtype=np.float64) + 0.5).astype(np.int64)


def patch_grid_uv(keypoints_uv: np.ndarray,  # [M, 2] undistorted px
                  width: int, height: int, grid_size: int = 80, num_thr: int = 8,
                  margin_px: int = 5, skip_short_px: int = 30,
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """Patch-Grid sample locations for one image.

    keypoints_uv: [M, 2] undistorted keypoint positions (u right, v down), px; keypoints outside
    the image are ignored. Cells are [i g, min((i+1) g, width)) x [j g, min((j+1) g, height));
    a cell narrower or shorter than ``grid_size - skip_short_px`` is skipped. Each kept cell
    with ``count < num_thr`` keypoints gets ``num_thr - count`` samples on integer pixels in
    [x0 + margin, x1 - margin) x [y0 + margin, y1 - margin), none on a keypoint's pixel and no
    two on the same pixel. Deterministic for a given ``rng`` state.
    Returns uv: [S, 2] float64 (integer-valued), grouped by cell in row-major cell order.
    """
    if rng is None:
        raise ValueError("patch_grid_uv needs an explicit rng (np.random.Generator) for reproducibility")
    kp = np.asarray(keypoints_uv, dtype=np.float64).reshape(-1, 2)
    g = int(grid_size)
    nx, ny = -(-int(width) // g), -(-int(height) // g)
    x0 = np.arange(nx) * g
    y0 = np.arange(ny) * g
    x1 = np.minimum(x0 + g, width)
    y1 = np.minimum(y0 + g, height)
    min_side = g - skip_short_px
    col_ok = (x1 - x0) >= min_side
    row_ok = (y1 - y0) >= min_side
    # Sampling boxes must hold at least one pixel after the margins.
    col_ok &= (x1 - margin_px) > (x0 + margin_px)
    row_ok &= (y1 - margin_px) > (y0 + margin_px)

    px = _pixel_of(kp)
    inside = (px[:, 0] >= 0) & (px[:, 0] < width) & (px[:, 1] >= 0) & (px[:, 1] < height)
    px = px[inside]
    cell_of_kp = (px[:, 1] // g) * nx + (px[:, 0] // g)
    counts = np.bincount(cell_of_kp, minlength=nx * ny)
    need = np.maximum(num_thr - counts, 0)
    need *= (row_ok[:, None] & col_ok[None, :]).reshape(-1)
    total = int(need.sum())
    if total == 0:
        return np.zeros((0, 2), dtype=np.float64)

    cell = np.repeat(np.arange(nx * ny), need)  # [S] cell index of each sample
    cx, cy = cell % nx, cell // nx
    lo_u, hi_u = x0[cx] + margin_px, x1[cx] - margin_px
    lo_v, hi_v = y0[cy] + margin_px, y1[cy] - margin_px
    taken = set((px[:, 1] * width + px[:, 0]).tolist())  # keypoint pixels, linear index
    u = np.empty(total, dtype=np.int64)
    v = np.empty(total, dtype=np.int64)
    todo = np.arange(total)
    for _ in range(_MAX_REDRAW_ROUNDS):
        u[todo] = rng.integers(lo_u[todo], hi_u[todo])
        v[todo] = rng.integers(lo_v[todo], hi_v[todo])
        # Accept samples in order; one that hits a keypoint or an earlier sample is redrawn.
        redo: list[int] = []
        for k, code in zip(todo.tolist(), (v[todo] * width + u[todo]).tolist()):
            if code in taken:
                redo.append(k)
            else:
                taken.add(code)
        if not redo:
            break
        todo = np.asarray(redo, dtype=np.int64)
    else:
        # Only reachable when a box is (almost) full of keypoints: drop what could not be placed.
        keep = np.ones(total, dtype=bool)
        keep[todo] = False
        u, v = u[keep], v[keep]
    return np.stack([u, v], axis=1).astype(np.float64)


def _check_keyframe(rgb: np.ndarray, camera: PinholeCamera, T_wc: np.ndarray,
                    keypoints_uv: np.ndarray, keypoint_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate the common inputs; returns (T_wc [4, 4] f64, uv [M, 2] f64, depth [M] f64)."""
    h, w = camera.height, camera.width
    if rgb.dtype != np.uint8 or rgb.shape != (h, w, 3):
        raise DataError(f"keyframe rgb must be uint8 [{h}, {w}, 3] to match the camera, got {rgb.dtype} {rgb.shape}")
    if camera.has_distortion:
        raise DataError("Patch-Grid seeds need an undistorted camera and images; prepare the keyframe with "
                        "memgs_ros.core.geometry.view.view_preparation first")
    T = np.asarray(T_wc, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise DataError(f"keyframe T_wc must be a finite 4x4 matrix, got shape {T.shape}")
    uv = np.asarray(keypoints_uv, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(keypoint_depth, dtype=np.float64).reshape(-1)
    if d.shape[0] != uv.shape[0]:
        raise DataError(f"keypoint_depth has {d.shape[0]} entries for {uv.shape[0]} keypoints")
    return T, uv, d


def _assemble(rgb: np.ndarray, camera: PinholeCamera, T_wc: np.ndarray, keyframe_id: int,
              parts: list[tuple[np.ndarray, np.ndarray, int]]) -> SeedPoints:
    """Back-project (pixel [S, 2] int, depth [S]) groups and colour them from ``rgb``."""
    pix = np.concatenate([p for p, _, _ in parts]).astype(np.int64).reshape(-1, 2)
    depth = np.concatenate([d for _, d, _ in parts])
    source = np.concatenate([np.full(len(d), s, dtype=np.uint8) for _, d, s in parts])
    p_c = camera.backproject(pix[:, 0], pix[:, 1], depth)  # [S, 3]
    p_w = p_c @ T_wc[:3, :3].T + T_wc[:3, 3]
    colors = rgb[pix[:, 1], pix[:, 0]].astype(np.float32) / np.float32(255.0)
    return SeedPoints(points_w=p_w.astype(np.float32), colors=colors.reshape(-1, 3),
                      keyframe_id=int(keyframe_id), source=source)


def _keypoint_part(uv: np.ndarray, depth: np.ndarray, width: int, height: int,
                   cfg: PatchGridConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints inside the image with a depth in range: (pixel [K, 2], depth [K], mask [M])."""
    pix = _pixel_of(uv)
    ok = ((pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
          & np.isfinite(depth) & (depth > cfg.min_depth_m) & (depth < cfg.max_depth_m))
    return pix[ok], depth[ok], ok


def seeds_rgbd(rgb: np.ndarray,  # [H, W, 3] uint8, undistorted
               depth_m: np.ndarray,  # [H, W] float metres, undistorted; NaN/0 invalid
               camera: PinholeCamera, T_wc: np.ndarray, keyframe_id: int,
               keypoints_uv: np.ndarray,  # [M, 2] undistorted px
               keypoint_depth: np.ndarray,  # [M] metres, NaN = none
               cfg: PatchGridConfig = PG_RGBD,
               rng: np.random.Generator | None = None) -> SeedPoints:
    """Seeds of an RGB-D keyframe: keypoints with a valid depth, plus Patch-Grid samples whose
    depth image value d satisfies min_depth_m < d < max_depth_m.

    The keypoint's own depth (from the tracker) is used for keypoints; samples read the depth
    image at their pixel. Colours come from ``rgb`` at the pixel. ``camera`` must be undistorted.
    rng: None uses ``cfg.rng_for(keyframe_id)``. Returns SeedPoints (keypoints first).
    """
    T, uv, kd = _check_keyframe(rgb, camera, T_wc, keypoints_uv, keypoint_depth)
    h, w = camera.height, camera.width
    if depth_m.shape != (h, w):
        raise DataError(f"keyframe depth must be [{h}, {w}] to match the camera, got {depth_m.shape}")
    kp_pix, kp_d, _ = _keypoint_part(uv, kd, w, h, cfg)
    parts = [(kp_pix, kp_d, SOURCE_KEYPOINT)]
    if cfg.enabled:
        rng = cfg.rng_for(keyframe_id) if rng is None else rng
        s_uv = patch_grid_uv(uv, w, h, cfg.grid_size, cfg.num_thr, cfg.margin_px,
                             cfg.skip_short_px, rng).astype(np.int64)
        s_d = np.asarray(depth_m[s_uv[:, 1], s_uv[:, 0]], dtype=np.float64)
        ok = np.isfinite(s_d) & (s_d > cfg.min_depth_m) & (s_d < cfg.max_depth_m)
        parts.append((s_uv[ok], s_d[ok], SOURCE_PATCH_GRID))
    return _assemble(rgb, camera, T, keyframe_id, parts)


def seeds_mono(rgb: np.ndarray,  # [H, W, 3] uint8, undistorted
               camera: PinholeCamera, T_wc: np.ndarray, keyframe_id: int,
               keypoints_uv: np.ndarray,  # [M, 2] undistorted px
               keypoint_depth: np.ndarray,  # [M] metres (depth of the keypoint's 3D point), NaN = none
               cfg: PatchGridConfig = PG_MONO_TUM,
               rng: np.random.Generator | None = None) -> SeedPoints:
    """Seeds of a monocular keyframe: keypoints that have a 3D point (finite depth in range), plus
    Patch-Grid samples that take the depth of the nearest such keypoint when it is within
    ``cfg.max_px_dist`` px (samples farther from any are dropped).

    Cells are counted with all keypoints (with or without a 3D point), as in the paper.
    rng: None uses ``cfg.rng_for(keyframe_id)``. Returns SeedPoints (keypoints first).
    """
    T, uv, kd = _check_keyframe(rgb, camera, T_wc, keypoints_uv, keypoint_depth)
    h, w = camera.height, camera.width
    kp_pix, kp_d, ok = _keypoint_part(uv, kd, w, h, cfg)
    parts = [(kp_pix, kp_d, SOURCE_KEYPOINT)]
    if cfg.enabled and kp_d.size > 0:
        rng = cfg.rng_for(keyframe_id) if rng is None else rng
        s_uv = patch_grid_uv(uv, w, h, cfg.grid_size, cfg.num_thr, cfg.margin_px,
                             cfg.skip_short_px, rng)
        if s_uv.shape[0] > 0:
            from scipy.spatial import cKDTree  # here: nodes that read PatchGridConfig need no scipy

            tree = cKDTree(uv[ok])
            dist, idx = tree.query(s_uv, k=1, distance_upper_bound=cfg.max_px_dist)
            near = np.isfinite(dist)  # misses come back as inf with idx == n
            parts.append((s_uv[near].astype(np.int64), kp_d[idx[near]], SOURCE_PATCH_GRID))
    return _assemble(rgb, camera, T, keyframe_id, parts)

