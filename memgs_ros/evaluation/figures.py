"""PNG plots of evaluation results, the figures ``memgs eval`` writes (the drawing into an
``Axes`` is :mod:`memgs_ros.evaluation.plots`). Loaded only when ``memgs eval`` runs.
"""
from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from memgs_ros.evaluation import plots
from memgs_ros.evaluation.runs import EvalResult

__all__ = ["save_ablation_plot", "save_plots"]


PLOTS = ("trajectory", "psnr", "map_size", "strip")


def save_plots(result: EvalResult, out_dir: Path, prefix: str = "", kinds: Collection[str] = PLOTS,
               metadata: Mapping[str, str] | None = None) -> list[Path]:
    """Trajectory, PSNR per frame, map size over time and frame strip PNGs (``kinds`` of them,
    named ``<prefix><kind>.png``, with PNG text ``metadata``) for one EvalResult."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    title = f"{result.variant}: {Path(result.source).name or result.source}"

    def save(fig: Figure, name: str) -> None:
        FigureCanvasAgg(fig)
        fig.tight_layout()
        path = out_dir / f"{prefix}{name}"
        fig.savefig(path, dpi=110, metadata=dict(metadata or {}))
        written.append(path)

    tr = result.trajectory
    if "trajectory" in kinds and tr is not None and tr.n_matched:
        fig = Figure(figsize=(11, 4.5))
        ax1, ax2 = fig.subplots(1, 2)
        plots.plot_trajectory_top(ax1, np.array(tr.est_xyz_aligned), np.array(tr.gt_xyz),
                                  keyframe_xyz=np.array(tr.keyframe_xyz_aligned) if tr.keyframe_xyz_aligned else None,
                                  est_label=f"estimate ({'Sim(3)' if tr.sim3 else 'SE(3)'} aligned)")
        ax1.set_title(f"{title}, top view")
        t = (np.array(tr.stamps_ns, dtype=np.int64) - tr.stamps_ns[0]) * 1e-9
        plots.plot_ate_errors(ax2, t, np.array(tr.errors_m))
        ax2.set_title(f"ATE {tr.rmse_m * 100:.2f} cm, rotation {tr.rotation_rmse_deg:.2f} deg")
        save(fig, "trajectory.png")

    q = result.frames_quality
    if "psnr" in kinds and q.n:
        stamps = np.array(q.stamps_ns, dtype=np.int64)
        kf = np.isin(stamps, np.array(result.keyframes_quality.stamps_ns, dtype=np.int64))
        fig = Figure(figsize=(8, 3.8))
        ax = fig.subplots()
        psnr = np.array([np.nan if v is None else v for v in q.psnr_db_per_frame], dtype=np.float64)
        plots.plot_psnr_per_frame(ax, (stamps - stamps[0]) * 1e-9, psnr, is_keyframe=kf)
        ax.set_title(f"{title}, every tracked frame at {result.render_size[0]}x{result.render_size[1]}")
        save(fig, "psnr.png")

    if "map_size" in kinds and result.map_samples:
        s = result.map_samples
        fig = Figure(figsize=(8, 3.8))
        ax = fig.subplots()
        cuda = all(m.cuda_max_allocated is not None for m in s)
        mem = np.array([m.cuda_max_allocated if cuda else m.model_bytes for m in s], dtype=np.float64)
        twin = plots.plot_map_size(ax, np.array([m.t_s for m in s]), np.array([m.gaussians for m in s]), mem)
        if twin is not None:
            twin.set_ylabel("CUDA max allocated [GiB]" if cuda else "model bytes (params+grads+Adam) [GiB]",
                            color="tab:purple")
        ax.set_title(f"{title}, mapper stats over the run (1 Hz)")
        save(fig, "map_size.png")

    if "strip" in kinds and result.strip_path and Path(result.strip_path).is_file():
        data = np.load(result.strip_path, allow_pickle=False)
        t0 = q.stamps_ns[0] if q.n else int(data["stamps_ns"][0])
        titles = [f"t={(int(s) - t0) * 1e-9:.1f}s {p:.1f}dB" for s, p in zip(data["stamps_ns"], data["psnr_db"])]
        n = len(titles)
        fig = Figure(figsize=(2.4 * n + 0.6, 4.2))
        ax = fig.subplots()
        plots.plot_frame_strip(ax, list(data["renders"]), list(data["reals"]), titles)
        ax.set_title(f"{title}: rendered (top) vs real (bottom)", pad=18)
        save(fig, "strip.png")
    return written


def save_ablation_plot(results: Sequence[EvalResult], out_dir: Path, prefix: str = "",
                       metadata: Mapping[str, str] | None = None) -> Path | None:
    """Gaussians against mapping iteration for every ablation variant on one axes
    (``<prefix>ablation_map_size.png``)."""
    if not any(r.map_samples for r in results):
        return None
    fig = Figure(figsize=(8, 3.8))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for r in results:
        if r.map_samples:
            # Against the mapping iteration, not wall time: variants run at different speeds.
            ax.plot(np.array([m.iteration for m in r.map_samples]),
                    np.array([m.gaussians for m in r.map_samples]) / 1000.0,
                    label=f"{r.variant} (final {r.gaussians / 1000:.1f}k)")
    ax.set_xlabel("mapping iteration")
    ax.set_ylabel("Gaussians [k]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title("ablation: map size over the run (mapper stats, 1 Hz)")
    fig.tight_layout()
    path = out_dir / f"{prefix}ablation_map_size.png"
    fig.savefig(path, dpi=110, metadata=dict(metadata or {}))
    return path
