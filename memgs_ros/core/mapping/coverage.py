"""Gaussians only where the map lacks them: which of a keyframe's seeds the current map already explains.

Before a keyframe's seeds become Gaussians, the mapper renders the map at the keyframe's pose
(accumulated opacity and depth, at a coarse level of its pyramid) and keeps a seed only where the
render is thin (accumulated opacity below ``alpha_max``) or where the seed lies in front of the
rendered surface by more than ``depth_abs_m + depth_rel`` times its depth (new geometry the map
lacks: SplaTAM's test). A seed behind the rendered surface is not added: a render's blended depth
sits in front of an oblique surface's true depth (the nearer Gaussians of a pixel blend first),
and whatever lies behind a surface the map shows would not be seen from here. On a place flown
again the map already covers the view and the keyframe seeds little or nothing: the surfaces it
shows are refined by training, not doubled (MonoGS and SplaTAM densify by the same silhouette and
depth test).
"""
from __future__ import annotations

import numpy as np
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianMap
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.mapping.config import MappingConfig

__all__ = ["settled_uncovered", "uncovered_seeds"]


def uncovered_seeds(points_w: np.ndarray,  # [M, 3] the seeds, world
                    T_wc: np.ndarray,  # [4, 4] the keyframe's camera-to-world pose
                    camera: PinholeCamera,  # of the render (undistorted, its size)
                    alpha: torch.Tensor,  # [h, w] the map's accumulated opacity there
                    depth: torch.Tensor,  # [h, w] its alpha-blended depth, sum_i w_i z_i (RenderOutput.depth)
                    alpha_max: float, depth_abs_m: float, depth_rel: float) -> np.ndarray:  # [M] bool
    """[M] True for the seeds the map does not explain (module docstring): thin there, or in front of
    its surface. Outside the render or
    behind the camera counts as explained (nothing there to judge by, and nothing the render would
    show). ``depth`` is divided by ``alpha`` into the rendered surface's depth."""
    p = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, dtype=bool)
    T_cw = invert_pose(np.asarray(T_wc, dtype=np.float64))
    p_c = p @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = p_c[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = np.rint(camera.fx * p_c[:, 0] / zs + camera.cx).astype(np.int64)
    v = np.rint(camera.fy * p_c[:, 1] / zs + camera.cy).astype(np.int64)
    inside = front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    a = alpha.detach().to("cpu", torch.float32).numpy()
    d = depth.detach().to("cpu", torch.float32).numpy()
    out = np.zeros(len(p), dtype=bool)
    idx = np.flatnonzero(inside)
    a_px = a[v[idx], u[idx]]
    thin = a_px < alpha_max
    surface = d[v[idx], u[idx]] / np.maximum(a_px, 1e-6)
    in_front = z[idx] < surface - (depth_abs_m + depth_rel * surface)
    out[idx] = thin | in_front
    return out


def settled_uncovered(gmap: GaussianMap, settled_kf_ids: list[int], points_w: np.ndarray,  # [M, 3]
                      T_wc: np.ndarray,  # [4, 4]
                      camera: PinholeCamera, cfg: MappingConfig,
                      background: torch.Tensor | None = None) -> np.ndarray | None:  # [M] bool
    """``uncovered_seeds`` against the settled map: the Gaussians the keyframes ``settled_kf_ids``
    made (the mapper's ``KeyframeAnchors.settled``), rendered at ``T_wc`` with ``camera`` scaled by
    ``cfg.seed_coverage_scale``, with the config's thresholds; None (keep every seed) when nothing
    is settled. A surface the last seconds' keyframes seeded is still being trained, and its blobs
    would hide the detail the new seeds bring."""
    from memgs_ros.core.raster import Gaussians, rasterize

    if not settled_kf_ids or len(gmap) == 0:
        return None
    ids = torch.tensor(settled_kf_ids, dtype=torch.int64, device=gmap.device)
    rows = torch.nonzero(torch.isin(gmap.keyframe_ids, ids)).reshape(-1)
    if rows.numel() == 0:
        return None
    cam = camera.scaled(cfg.seed_coverage_scale) if cfg.seed_coverage_scale != 1.0 else camera
    T_cw = torch.as_tensor(invert_pose(np.asarray(T_wc, dtype=np.float64)), dtype=torch.float32, device=gmap.device)
    with torch.no_grad():
        part = Gaussians(*(t.detach()[rows] for t in gmap.gaussians()))
        out = rasterize(part, T_cw, cam, gmap.active_sh_degree, background=background, near=cfg.near_m,
                        backend=cfg.raster_backend)
    return uncovered_seeds(points_w, T_wc, cam, out.alpha, out.depth, cfg.seed_alpha_max, cfg.seed_depth_abs_m,
                           cfg.seed_depth_rel)
