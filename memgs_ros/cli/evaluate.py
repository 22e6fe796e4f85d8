"""``memgs eval``: run the graph on a sequence and reproduce the paper's table for it.

Writes into ``--out``: ``eval.json`` (every number, per-frame values, map size over time),
``table.md`` (the paper's PSNR / Mem / Points layout plus SSIM, ATE and speeds) and PNG plots
(trajectory vs ground truth, PSNR per frame, map size over time, rendered-vs-real strip).
With ``--ablation`` the full system, no merging and no Patch-Grid run on the same data and seed,
each in ``--out/<variant>``, and ``ablation.md`` / ``ablation.json`` put them side by side.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

HELP = "evaluate a run like the paper: PSNR/SSIM, memory, Gaussians, ATE, FPS (optionally an ablation)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", metavar="SOURCE",
                   help="TUM folder, ROS 2 bag (folder, .mcap, .db3), TUM ROS 1 .bag or 'synthetic:...' spec")
    p.add_argument("--config", default=None, help="config name (tum_fr1, synthetic, ...) or YAML path "
                   "(default: guessed from the source)")
    p.add_argument("--mode", choices=("rgbd", "mono"), default="rgbd", help="camera mode of tracker, sampler, mapper")
    p.add_argument("--scale", type=float, default=None,
                   help="mapping resolution scale (mapper.mapping.resolution_scale; default: the config's); "
                        "renders are scored at this resolution")
    p.add_argument("--seed", type=int, default=0, help="seed of mapper, Patch-Grid sampler and tracker")
    p.add_argument("--out", type=Path, default=Path("memgs_eval"), help="output folder")
    p.add_argument("--ablation", action="store_true",
                   help="also run without merging and without Patch-Grid (same data and seed)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                   help="override a node parameter, e.g. mapper.final_iterations=500 (repeatable)")
    p.add_argument("--max-frames", type=int, default=0, help="use only the first N frames (0 = all)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: random in 100..199)")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up a run after this many seconds")
    p.add_argument("--single-process", action="store_true", help="run the nodes in this process")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS even when the lpips package is there")
    p.add_argument("--no-plots", action="store_true", help="write JSON and tables only")


def _overrides(items: list[str]) -> dict[str, Any]:
    import yaml

    from memgs_ros.errors import ConfigError

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or "." not in key:
            raise ConfigError(f"--set needs NODE.PARAM=VALUE, got '{item}'")
        out[key.strip()] = yaml.safe_load(value)
    return out


def save_plots(result: Any, out_dir: Path) -> list[Path]:
    """Trajectory, PSNR per frame, map size over time and frame strip PNGs for one EvalResult."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from memgs_ros import plots

    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    title = f"{result.variant}: {Path(result.source).name or result.source}"

    def save(fig: Figure, name: str) -> None:
        FigureCanvasAgg(fig)
        fig.tight_layout()
        path = out_dir / name
        fig.savefig(path, dpi=110)
        written.append(path)

    tr = result.trajectory
    if tr is not None and tr.n_matched:
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
    if q.n:
        stamps = np.array(q.stamps_ns, dtype=np.int64)
        kf = np.isin(stamps, np.array(result.keyframes_quality.stamps_ns, dtype=np.int64))
        fig = Figure(figsize=(8, 3.8))
        ax = fig.subplots()
        psnr = np.array([np.nan if v is None else v for v in q.psnr_db_per_frame], dtype=np.float64)
        plots.plot_psnr_per_frame(ax, (stamps - stamps[0]) * 1e-9, psnr, is_keyframe=kf)
        ax.set_title(f"{title}, every tracked frame at {result.render_size[0]}x{result.render_size[1]}")
        save(fig, "psnr.png")

    if result.map_samples:
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

    if result.strip_path and Path(result.strip_path).is_file():
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


def save_ablation_plot(results: list[Any], out_dir: Path) -> Path | None:
    """Gaussians against mapping iteration for every ablation variant on one axes
    (``ablation_map_size.png``)."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

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
    path = out_dir / "ablation_map_size.png"
    fig.savefig(path, dpi=110)
    return path


def _print_result(r: Any) -> None:
    q, k, m = r.frames_quality, r.keyframes_quality, r.memory
    print(f"[{r.variant}] frames {r.frames} ({r.poses} poses, {r.lost_frames} lost), keyframes {r.keyframes}, "
          f"wall {r.wall_s:.1f} s, scoring {r.eval_s:.1f} s")
    print(f"[{r.variant}] PSNR {q.psnr_db if q.psnr_db is not None else float('nan'):.2f} dB over {q.n} frames "
          f"({r.render_size[0]}x{r.render_size[1]}), keyframes "
          f"{k.psnr_db if k.psnr_db is not None else float('nan'):.2f} dB over {k.n}; SSIM "
          f"{q.ssim if q.ssim is not None else float('nan'):.3f}"
          + (f", LPIPS {q.lpips:.3f}" if q.lpips is not None else ", LPIPS n/a"))
    if r.trajectory is not None:
        print(f"[{r.variant}] ATE {r.trajectory.rmse_m * 100:.2f} cm, rotation {r.trajectory.rotation_rmse_deg:.2f} deg "
              f"({r.trajectory.n_matched} poses)")
    rss = ", ".join(f"{n} {v:.0f}" for n, v in m.peak_rss_mb.items())
    print(f"[{r.variant}] Gaussians {r.gaussians} (peak {r.gaussians_peak}), memory {m.headline_kind} "
          f"{m.headline_bytes / 1e6:.1f} MB, peak RSS MB: {rss}")
    rate = r.mapping_iters_per_s_training
    print(f"[{r.variant}] tracking {r.tracking_fps:.1f} FPS, mapping {r.mapping_iterations} iterations "
          f"({'n/a' if rate is None else f'{rate:.2f}'} it/s while training, "
          f"{r.mapping_iters_per_s:.2f} it/s over the whole run)")
    for note in r.notes:
        print(f"[{r.variant}] note: {note}")


def run(args: argparse.Namespace) -> int:
    from memgs_ros.cli.run import check_inputs, guess_config

    source = str(args.source)
    config = args.config or guess_config(source)
    overrides = _overrides(args.set)
    check_inputs(source, config, args.max_frames, overrides, args.out)  # before torch, rclpy or any node

    import matplotlib

    matplotlib.use("Agg")
    import torch

    from memgs_ros import evaluation
    from memgs_ros.core.runtime import configure_cpu_runtime

    if not torch.cuda.is_available():
        configure_cpu_runtime()  # this process renders every frame on CPU
    kwargs = dict(max_frames=args.max_frames, domain_id=args.domain_id, timeout_s=args.timeout,
                  single_process=args.single_process, use_lpips=not args.no_lpips)
    out = Path(args.out)
    if args.ablation:
        res = evaluation.ablation(source, config, args.mode, args.scale, args.seed, out, overrides, **kwargs)
        results = list(res.results)
        table = evaluation.ablation_table(results)
        (out / "ablation.md").write_text(table)
    else:
        results = [evaluation.evaluate(source, config, args.mode, args.scale, args.seed, out, overrides, **kwargs)]
        table = evaluation.markdown_table(results)
    for r in results:
        (Path(r.out_dir) / "table.md").write_text(evaluation.markdown_table([r]))
        _print_result(r)
        if not args.no_plots:
            for path in save_plots(r, Path(r.out_dir)):
                print(f"[{r.variant}] wrote {path}")
    if args.ablation and not args.no_plots:
        path = save_ablation_plot(results, out)
        if path is not None:
            print(f"wrote {path}")
    print()
    print(table)
    return 0
