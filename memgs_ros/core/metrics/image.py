"""Image-quality metrics and the frame matching of the evaluation protocol (reference sec. 7).

PSNR = -10 log10(MSE) over the whole image with values in [0, 1]; SSIM with data range 1
(:mod:`memgs_ros.core.metrics.ssim`, zero-padded 11x11 Gaussian window); LPIPS (AlexNet) only when the
``lpips`` package is installed and the AlexNet weights are already in the torch hub cache
(nothing is ever downloaded). Rendered frames are matched to ground-truth frames within 0.08 s.

Images: numpy arrays are [H, W, 3] (uint8 0..255, or float in [0, 1]); torch tensors are
[3, H, W] float in [0, 1].
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from memgs_ros.core.metrics.ssim import ssim
from memgs_ros.core.metrics.trajectory import associate

__all__ = [
    "FRAME_MATCH_MAX_DT_S", "FrameScore", "make_lpips", "match_frames", "psnr", "score_frame",
    "ssim_value", "summarize_scores",
]

FRAME_MATCH_MAX_DT_S = 0.08
_ALEXNET_CHECKPOINT = "alexnet-owt-7be5be79.pth"  # the file torchvision's AlexNet weights load from

Image = np.ndarray | torch.Tensor
LpipsFn = Callable[[torch.Tensor, torch.Tensor], float]


def _to_chw(img: Image, device: torch.device | None = None,
            dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """[H, W, 3] numpy (uint8 or float in [0, 1]) or [3, H, W] tensor -> [3, H, W] ``dtype``
    tensor in [0, 1] (uint8 is divided by 255)."""
    if isinstance(img, torch.Tensor):
        assert img.dim() == 3 and img.shape[0] == 3, f"image tensors must be [3, H, W], got {tuple(img.shape)}"
        t = img.detach()
    else:
        a = np.asarray(img)
        assert a.ndim == 3 and a.shape[2] == 3, f"image arrays must be [H, W, 3], got {a.shape}"
        t = torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))
    t = t.to(dtype) / 255.0 if t.dtype == torch.uint8 else t.to(dtype)
    return t if device is None else t.to(device)


def psnr(img: Image, ref: Image) -> float:
    """PSNR in dB of ``img`` against ``ref`` (both in [0, 1] after conversion): -10 log10(MSE)
    over all pixels and channels, computed in float64. Identical images give +inf."""
    a = _to_chw(img, dtype=torch.float64)
    b = _to_chw(ref, a.device, dtype=torch.float64)
    assert a.shape == b.shape, f"psnr: image {tuple(a.shape)} and reference {tuple(b.shape)} differ"
    mse = float(torch.mean((a - b) ** 2))
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def ssim_value(img: Image, ref: Image) -> float:
    """Mean SSIM (data range 1, 11x11 window, sigma 1.5) of ``img`` against ``ref``."""
    a = _to_chw(img)
    b = _to_chw(ref, a.device)
    assert a.shape == b.shape, f"ssim: image {tuple(a.shape)} and reference {tuple(b.shape)} differ"
    with torch.no_grad():
        return float(ssim(a, b))


def make_lpips(device: torch.device | str = "cpu") -> LpipsFn | None:
    """An LPIPS (AlexNet) scorer ``f(img [3, H, W], ref [3, H, W]) -> float``, or None when the
    ``lpips`` package is missing or the AlexNet weights are not cached locally (this never
    downloads anything)."""
    try:
        import lpips  # noqa: PLC0415 - optional dependency, imported on demand
    except ImportError:
        return None
    if not os.path.isfile(os.path.join(torch.hub.get_dir(), "checkpoints", _ALEXNET_CHECKPOINT)):
        return None
    model = lpips.LPIPS(net="alex", verbose=False).to(device).eval()

    def score(img: torch.Tensor, ref: torch.Tensor) -> float:
        with torch.no_grad():  # LPIPS expects [-1, 1]
            return float(model(img.to(device)[None] * 2 - 1, ref.to(device)[None] * 2 - 1))

    return score


@dataclass(frozen=True)
class FrameScore:
    """Quality of one rendered frame against its ground-truth image."""

    stamp_ns: int
    psnr_db: float
    ssim: float
    lpips: float | None = None


def score_frame(stamp_ns: int, render: Image, gt: Image, lpips_fn: LpipsFn | None = None) -> FrameScore:
    """PSNR, SSIM (and LPIPS when ``lpips_fn`` is given) of a render against the ground truth.
    The render is clamped to [0, 1] first, as a displayed image would be."""
    r = _to_chw(render).clamp(0.0, 1.0)
    g = _to_chw(gt, r.device)
    return FrameScore(stamp_ns=int(stamp_ns), psnr_db=psnr(r, g), ssim=ssim_value(r, g),
                      lpips=None if lpips_fn is None else lpips_fn(r, g))


def match_frames(render_stamps_ns: np.ndarray,  # [R]
                 gt_stamps_ns: np.ndarray,  # [G]
                 max_dt_s: float = FRAME_MATCH_MAX_DT_S) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest matching of rendered frames to ground-truth frames within max_dt_s.
    Returns (ir [n], ig [n]) int64 indices, sorted by ir."""
    return associate(render_stamps_ns, gt_stamps_ns, round(max_dt_s * 1e9))


def summarize_scores(scores: Sequence[FrameScore]) -> dict[str, float | int | None]:
    """Means over frames: {"n", "psnr_db", "ssim", "lpips"} (lpips None unless every frame has
    it). Infinite PSNRs (identical frames) are left out of the PSNR mean."""
    if not scores:
        return {"n": 0, "psnr_db": None, "ssim": None, "lpips": None}
    p = np.array([s.psnr_db for s in scores], dtype=np.float64)
    finite = np.isfinite(p)
    lp = [s.lpips for s in scores]
    return {
        "n": len(scores),
        "psnr_db": float(p[finite].mean()) if finite.any() else math.inf,
        "ssim": float(np.mean([s.ssim for s in scores])),
        "lpips": float(np.mean([v for v in lp if v is not None])) if all(v is not None for v in lp) else None,
    }
