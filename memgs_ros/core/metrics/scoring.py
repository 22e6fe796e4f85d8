"""Scoring a map against images and a trajectory against ground truth (reference section 7).

Pure functions on arrays and a ``GaussianMap``: no files, no ROS, no plotting. The run tier
(:mod:`memgs_ros.evaluation.runs`) reads a finished run's files and calls these.

- :func:`score_map`: render the map at every pose that matches a ground-truth image within
  ``FRAME_MATCH_MAX_DT_S`` and score it (PSNR, SSIM, LPIPS when given a function; PSNR also
  over the pixels with image content);
- :func:`score_trajectory`: ATE (SE(3), or Sim(3) for monocular) and rotation RMSE,
  association within ``ATE_MAX_DT_S``, through :func:`memgs_ros.core.metrics.trajectory.ate`.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from memgs_ros.core.gaussians.gaussian_map import GaussianMap
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.metrics.image import FrameScore, LpipsFn, match_frames, score_frame, summarize_scores
from memgs_ros.core.metrics.trajectory import ate
from memgs_ros.core.raster import rasterize
from memgs_ros.core.raster.values import render_rgb8

__all__ = [
    "ATE_MAX_DT_S", "FRAME_MATCH_MAX_DT_S", "QualityResult", "StripFrame", "TrajectoryResult",
    "masked_psnr", "score_map", "score_trajectory",
]

FRAME_MATCH_MAX_DT_S = 0.08  # rendered frame <-> ground-truth image (reference section 7)
ATE_MAX_DT_S = 0.1  # estimate <-> ground-truth pose (reference section 7)
STRIP_FRAMES = 5  # rendered-vs-real frames kept for the strip plot

# (stamp_ns, render [h, w, 3] uint8, real [h, w, 3] uint8, PSNR dB)
StripFrame = tuple[int, np.ndarray, np.ndarray, float]


@dataclass(frozen=True)
class QualityResult:
    """Rendering quality over a set of frames (means; per-frame values in stamp order).

    stamps_ns / psnr_db_per_frame / ssim_per_frame: [F]; lpips is None unless every frame has it.
    """

    n: int
    psnr_db: float | None
    ssim: float | None
    lpips: float | None
    stamps_ns: tuple[int, ...] = ()
    psnr_db_per_frame: tuple[float, ...] = ()
    ssim_per_frame: tuple[float, ...] = ()
    # PSNR over the pixels that carry image content after undistortion (the black border of an
    # undistorted image is no observation and the mapper does not train on it); equals psnr_db
    # for cameras without distortion.
    psnr_db_valid: float | None = None
    psnr_db_valid_per_frame: tuple[float, ...] = ()


@dataclass(frozen=True)
class TrajectoryResult:
    """ATE of the tracked trajectory against ground truth (metres, degrees).

    est_xyz_aligned / gt_xyz: [n, 3] matched positions after alignment; keyframe_xyz_aligned:
    [K, 3]; stamps_ns / errors_m: [n].
    """

    sim3: bool
    rmse_m: float
    rotation_rmse_deg: float
    n_matched: int
    scale: float
    stamps_ns: tuple[int, ...] = ()
    errors_m: tuple[float, ...] = ()
    est_xyz_aligned: tuple[tuple[float, float, float], ...] = ()
    gt_xyz: tuple[tuple[float, float, float], ...] = ()
    keyframe_xyz_aligned: tuple[tuple[float, float, float], ...] = ()


def masked_psnr(render: torch.Tensor,  # [3, H, W] in [0, 1]
                gt: torch.Tensor,  # [3, H, W] in [0, 1]
                mask: torch.Tensor | None,  # [H, W] bool, None = every pixel
                ) -> float:
    """PSNR (dB) over the pixels where ``mask`` is true; NaN when it selects none, inf when equal."""
    if mask is None:
        mse = float(torch.mean((render.double() - gt.double()) ** 2))
    else:
        m = mask.to(render.device)
        n = int(m.sum())
        if n == 0:
            return math.nan
        mse = float(((render.double() - gt.double()) ** 2)[:, m].sum()) / (3 * n)
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def _quality(stamps: Sequence[int], scores: Sequence[FrameScore], psnr_valid: Sequence[float]) -> QualityResult:
    s = summarize_scores(scores)
    pv = np.asarray(psnr_valid, dtype=np.float64)
    finite = np.isfinite(pv)
    return QualityResult(
        n=int(s["n"] or 0), psnr_db=s["psnr_db"], ssim=s["ssim"], lpips=s["lpips"],
        stamps_ns=tuple(int(t) for t in stamps),
        psnr_db_per_frame=tuple(float(x.psnr_db) for x in scores),
        ssim_per_frame=tuple(float(x.ssim) for x in scores),
        psnr_db_valid=float(pv[finite].mean()) if finite.any() else None,
        psnr_db_valid_per_frame=tuple(float(v) for v in pv))


def score_map(gmap: GaussianMap,
              pose_sets: Mapping[str, tuple[np.ndarray, np.ndarray]],  # name -> (stamps [M], T_wc [M, 4, 4])
              gt_stamps_ns: np.ndarray,  # [G]
              gt_images: Sequence[np.ndarray],  # G x [h, w, 3] uint8, prepared like the keyframes
              camera: PinholeCamera,  # of the renders and images (pinhole, mapping resolution)
              background: Sequence[float] = (0.0, 0.0, 0.0),
              lpips_fn: LpipsFn | None = None,
              valid_mask: np.ndarray | None = None,  # [h, w] bool: pixels with image content
              strip_from: str | None = None, strip_frames: int = STRIP_FRAMES,
              progress: Callable[[int, int], None] | None = None,  # (frames rendered, total)
              ) -> tuple[dict[str, QualityResult], list[StripFrame]]:
    """Render ``gmap`` at every pose of each pose set that matches a ground-truth image within
    ``FRAME_MATCH_MAX_DT_S`` and score it. Poses with non-finite entries (lost frames) are skipped.

    Renders are cached by (stamp, image), so a keyframe that is also a tracked frame is rendered
    once. Returns ({name: QualityResult}, strip frames taken evenly from ``strip_from``'s scored
    frames).
    """
    device = gmap.device
    bg = torch.tensor(list(background), dtype=torch.float32, device=device)
    jobs: dict[str, list[tuple[int, np.ndarray, int]]] = {}
    for name, (stamps, poses) in pose_sets.items():
        stamps = np.asarray(stamps, dtype=np.int64)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        finite = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
        ir, ig = match_frames(stamps[finite], gt_stamps_ns, FRAME_MATCH_MAX_DT_S)
        jobs[name] = [(int(stamps[finite[a]]), poses[finite[a]], int(b)) for a, b in zip(ir, ig)]
    total = len({(s, gi) for js in jobs.values() for s, _, gi in js})
    mask_t = None if valid_mask is None else torch.from_numpy(np.asarray(valid_mask, dtype=bool))
    scored: dict[tuple[int, int], FrameScore] = {}
    scored_valid: dict[tuple[int, int], float] = {}
    renders: dict[tuple[int, int], np.ndarray] = {}
    results: dict[str, QualityResult] = {}
    for name, js in jobs.items():
        for stamp, T_wc, gi in js:
            key = (stamp, gi)
            if key in scored:
                continue
            T_cw = torch.from_numpy(invert_pose(T_wc)).float().to(device)
            if len(gmap):
                with torch.no_grad():
                    out = rasterize(gmap.gaussians(), T_cw, camera, sh_degree=3, background=bg)
                color = out.color.clamp(0.0, 1.0)
            else:  # an empty map renders the background
                color = bg.reshape(3, 1, 1).expand(3, camera.height, camera.width)
            gt = torch.from_numpy(gt_images[gi]).to(device).permute(2, 0, 1).float() / 255.0
            scored[key] = score_frame(stamp, color, gt, lpips_fn)
            scored_valid[key] = masked_psnr(color, gt, mask_t)
            if name == strip_from:
                renders[key] = render_rgb8(color)
            if progress is not None:
                progress(len(scored), total)
        results[name] = _quality([s for s, _, _ in js], [scored[(s, gi)] for s, _, gi in js],
                                 [scored_valid[(s, gi)] for s, _, gi in js])
    strip: list[StripFrame] = []
    if strip_from is not None and jobs.get(strip_from):
        js = jobs[strip_from]
        picks = np.unique(np.linspace(0, len(js) - 1, min(strip_frames, len(js))).round().astype(int))
        for k in picks:
            stamp, _, gi = js[int(k)]
            if (stamp, gi) in renders:
                strip.append((stamp, renders[(stamp, gi)], gt_images[gi], float(scored[(stamp, gi)].psnr_db)))
    return results, strip


def _rows(a: np.ndarray) -> tuple[tuple[float, float, float], ...]:
    return tuple((float(x), float(y), float(z)) for x, y, z in np.asarray(a).reshape(-1, 3))


def score_trajectory(stamps_ns: np.ndarray,  # [M]
                     T_wc: np.ndarray,  # [M, 4, 4] estimate
                     gt_stamps_ns: np.ndarray,  # [K]
                     gt_T_wc: np.ndarray,  # [K, 4, 4]
                     sim3: bool,
                     keyframe_T_wc: np.ndarray | None = None,  # [F, 4, 4], shown aligned
                     ) -> TrajectoryResult:
    """ATE (SE(3), or Sim(3) when ``sim3``) against ground truth, association within
    ``ATE_MAX_DT_S``. Raises DataError (from :func:`ate`) when fewer than 3 poses match."""
    poses = np.asarray(T_wc, dtype=np.float64).reshape(-1, 4, 4)
    res = ate(np.asarray(stamps_ns, dtype=np.int64), poses, gt_stamps_ns, gt_T_wc,
              max_dt_s=ATE_MAX_DT_S, sim3=sim3)
    est = res.alignment.apply(poses[res.est_index, :3, 3])
    gt = np.asarray(gt_T_wc)[res.gt_index, :3, 3]
    kf_xyz = np.zeros((0, 3))
    if keyframe_T_wc is not None and len(keyframe_T_wc):
        kf_xyz = res.alignment.apply(np.asarray(keyframe_T_wc, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3])
    return TrajectoryResult(
        sim3=sim3, rmse_m=res.rmse_m, rotation_rmse_deg=res.rotation_rmse_deg, n_matched=res.n_matched,
        scale=float(res.alignment.s), stamps_ns=tuple(int(s) for s in res.stamps_ns),
        errors_m=tuple(float(e) for e in res.errors_m), est_xyz_aligned=_rows(est), gt_xyz=_rows(gt),
        keyframe_xyz_aligned=_rows(kf_xyz))
