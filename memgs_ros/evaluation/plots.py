"""Plots for evaluation results. Every function draws into an ``Axes`` the caller passes in
(evo style); figures, backends and files are the caller's business (the CLI uses
``matplotlib.figure.Figure`` with the Agg canvas). Importing this module creates nothing.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = [
    "frame_strip_image", "plot_ate_errors", "plot_frame_strip", "plot_map_size",
    "plot_psnr_per_frame", "plot_trajectory_top",
]

_PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
_GiB = 1024.0 ** 3
_STRIP_GAP_PX = 4  # white gap between tiles of the frame strip



def _label_time_axes(ax: Axes, ylabel: str) -> None:
    """Time on x, ``ylabel`` on y, a light grid and the legend."""
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def plot_trajectory_top(ax: Axes,
                        est_xyz: np.ndarray,  # [M, 3] estimated positions (already aligned)
                        gt_xyz: np.ndarray | None = None,  # [K, 3] ground-truth positions
                        plane: str = "xy", est_label: str = "estimate",
                        gt_label: str = "ground truth", keyframe_xyz: np.ndarray | None = None) -> None:
    """Top view of a trajectory: ground truth dashed grey, estimate coloured, optional keyframe
    markers [F, 3]; equal axis scale, metres. ``plane`` picks the two world axes shown."""
    if plane not in _PLANES:
        raise ValueError(f"plane must be one of {sorted(_PLANES)}, got {plane!r}")
    i, j = _PLANES[plane]
    if gt_xyz is not None and len(gt_xyz):
        g = np.asarray(gt_xyz)
        ax.plot(g[:, i], g[:, j], linestyle="--", color="0.5", linewidth=1.2, label=gt_label)
    e = np.asarray(est_xyz)
    if len(e):
        ax.plot(e[:, i], e[:, j], color="tab:blue", linewidth=1.5, label=est_label)
        ax.plot(e[:1, i], e[:1, j], marker="o", color="tab:green", linestyle="none", label="start")
    if keyframe_xyz is not None and len(keyframe_xyz):
        k = np.asarray(keyframe_xyz)
        ax.plot(k[:, i], k[:, j], marker="^", markersize=4, color="tab:orange", linestyle="none",
                label="keyframes")
    ax.set_xlabel(f"{plane[0]} [m]")
    ax.set_ylabel(f"{plane[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def plot_ate_errors(ax: Axes, stamps_s: np.ndarray,  # [n] seconds
                    errors_m: np.ndarray,  # [n] metres
                    label: str = "ATE") -> None:
    """Position error over time, with its RMSE as a horizontal line."""
    t = np.asarray(stamps_s, dtype=np.float64)
    e = np.asarray(errors_m, dtype=np.float64)
    ax.plot(t, e * 100.0, color="tab:red", linewidth=1.2, label=label)
    if e.size:
        rmse = float(np.sqrt(np.mean(e ** 2)))
        ax.axhline(rmse * 100.0, color="tab:red", linestyle=":", label=f"RMSE {rmse * 100:.2f} cm")
    _label_time_axes(ax, "position error [cm]")


def plot_psnr_per_frame(ax: Axes, stamps_s: np.ndarray,  # [F] seconds
                        psnr_db: np.ndarray,  # [F]
                        is_keyframe: np.ndarray | None = None,  # [F] bool
                        label: str = "PSNR") -> None:
    """PSNR of every evaluated frame over time; keyframes marked; mean in the legend."""
    t = np.asarray(stamps_s, dtype=np.float64)
    p = np.asarray(psnr_db, dtype=np.float64)
    finite = np.isfinite(p)
    mean = float(p[finite].mean()) if finite.any() else float("nan")
    ax.plot(t, p, color="tab:blue", linewidth=1.0, label=f"{label} (mean {mean:.2f} dB)")
    if is_keyframe is not None:
        kf = np.asarray(is_keyframe, dtype=bool)
        if kf.any():
            kmean = float(p[kf & finite].mean()) if (kf & finite).any() else float("nan")
            ax.plot(t[kf], p[kf], marker="o", markersize=3, color="tab:orange", linestyle="none",
                    label=f"keyframes (mean {kmean:.2f} dB)")
    _label_time_axes(ax, "PSNR [dB]")


def plot_map_size(ax: Axes, stamps_s: np.ndarray,  # [T] seconds
                  n_gaussians: np.ndarray,  # [T]
                  memory_bytes: np.ndarray | None = None,  # [T]
                  ) -> Axes | None:
    """Number of Gaussians over time (left axis) and, when given, memory in GiB on a twin right
    axis. Returns the twin axis (or None) so the caller can style it."""
    t = np.asarray(stamps_s, dtype=np.float64)
    ax.plot(t, np.asarray(n_gaussians) / 1000.0, color="tab:blue", label="Gaussians")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("Gaussians [k]", color="tab:blue")
    ax.grid(True, alpha=0.3)
    if memory_bytes is None:
        return None
    twin = ax.twinx()
    twin.plot(t, np.asarray(memory_bytes, dtype=np.float64) / _GiB, color="tab:purple",
              linestyle="--", label="memory")
    twin.set_ylabel("memory [GiB]", color="tab:purple")
    return twin


def frame_strip_image(renders: Sequence[np.ndarray],  # F x [H, W, 3]
                      reals: Sequence[np.ndarray],  # F x [H, W, 3]
                      gap_px: int = _STRIP_GAP_PX) -> np.ndarray:
    """Tile rendered frames (top row) over the real ones (bottom row) into one image
    [2 H + gap, F W + (F - 1) gap, 3] float in [0, 1] (uint8 inputs are scaled by 1/255,
    renders are clamped); the gaps are white."""
    if len(renders) != len(reals) or not renders:
        raise ValueError(f"need as many renders as real frames (and at least one), got {len(renders)} and {len(reals)}")

    def norm(im: np.ndarray) -> np.ndarray:
        a = np.asarray(im)
        f = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
        return np.clip(f, 0.0, 1.0)

    h, w = np.asarray(reals[0]).shape[:2]
    f = len(renders)
    out = np.ones((2 * h + gap_px, f * w + (f - 1) * gap_px, 3), dtype=np.float32)
    for k, (r, g) in enumerate(zip(renders, reals)):
        if np.asarray(r).shape[:2] != (h, w) or np.asarray(g).shape[:2] != (h, w):
            raise ValueError(f"frame {k}: every image must be {w}x{h}")
        x = k * (w + gap_px)
        out[:h, x:x + w] = norm(r)
        out[h + gap_px:, x:x + w] = norm(g)
    return out


def plot_frame_strip(ax: Axes, renders: Sequence[np.ndarray], reals: Sequence[np.ndarray],
                     titles: Sequence[str] | None = None) -> None:
    """Rendered frames over real ones (see :func:`frame_strip_image`), one column per frame,
    with optional per-column titles (e.g. stamp and PSNR)."""
    img = frame_strip_image(renders, reals)
    ax.imshow(img, interpolation="nearest")
    h, w = np.asarray(reals[0]).shape[:2]
    ax.set_xticks([])
    ax.set_yticks([h / 2, 1.5 * h + _STRIP_GAP_PX])
    ax.set_yticklabels(["rendered", "real"])
    if titles is not None:
        for k, t in enumerate(titles):
            ax.text(k * (w + _STRIP_GAP_PX) + w / 2, -_STRIP_GAP_PX, t, ha="center", va="bottom", fontsize="small")
