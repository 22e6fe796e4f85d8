"""``memgs eval``: run the graph on a sequence and reproduce the paper's table for it.

Writes into ``--out``: ``eval.json`` (every number, per-frame values, map size over time),
``table.md`` (the paper's PSNR / Mem / Points layout plus SSIM, ATE and speeds) and PNG plots
(trajectory vs ground truth, PSNR per frame, map size over time, rendered-vs-real strip).
With ``--ablation`` the full system, no merging and no Patch-Grid run on the same data and seed,
each in ``--out/<variant>``, and ``ablation.md`` / ``ablation.json`` put them side by side.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from memgs_ros.cli.rerun_options import add_rerun_arguments, rerun_target
from memgs_ros.cli.run import add_map_arguments, add_record_argument, check_inputs, check_repeat, guess_config, run_log
from memgs_ros.errors import ConfigError
from memgs_ros.orchestration.run_files import check_record_path

logger = logging.getLogger(__name__)

if TYPE_CHECKING:
    from memgs_ros.evaluation.runs import EvalResult
    from memgs_ros.viz import RerunTarget

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
    p.add_argument("--out", type=Path, default=Path("memgs_eval"),
                   help="output folder: eval.json, table.md, plots, and the run's files (default: %(default)s)")
    p.add_argument("--ablation", action="store_true",
                   help="also run without merging and without Patch-Grid (same data and seed)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                   help="override a node parameter, e.g. mapper.final_iterations=500 (repeatable)")
    p.add_argument("--max-frames", type=int, default=0, help="use only the first N frames (0 = all)")
    p.add_argument("--repeat", type=int, default=1, metavar="N",
                   help="play the source N times, every other pass backward (a long flight over the same room); "
                        "every pass is scored (default: %(default)s)")
    p.add_argument("--repeat-forward", action="store_true",
                   help="with --repeat: every pass forward, the camera jumping back to the start between them")
    p.add_argument("--domain-id", type=int, default=None,
                   help="ROS_DOMAIN_ID (default: a random one no other node is using)")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up a run after this many seconds")
    p.add_argument("--composed", "--single-process", dest="composed", action="store_true",
                   help="the nodes as components of one process (this one): the libraries load once")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS even when the lpips package is there")
    p.add_argument("--no-plots", action="store_true", help="write JSON and tables only")
    add_map_arguments(p, ("--map-mode",))
    add_record_argument(p)
    add_rerun_arguments(p)


def _overrides(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or "." not in key:
            raise ConfigError(f"--set needs NODE.PARAM=VALUE, got '{item}'")
        out[key.strip()] = yaml.safe_load(value)
    return out


def _print_result(r: EvalResult) -> None:
    q, k, m = r.frames_quality, r.keyframes_quality, r.memory
    print(f"[{r.variant}] frames {r.frames} ({r.poses} poses, {r.lost_frames} lost), keyframes {r.keyframes}, "
          f"wall {r.wall_s:.1f} s, scoring {r.eval_s:.1f} s")
    print(f"[{r.variant}] PSNR {q.psnr_db if q.psnr_db is not None else float('nan'):.2f} dB over {q.n} frames "
          f"({r.render_size[0]}x{r.render_size[1]}), keyframes "
          f"{k.psnr_db if k.psnr_db is not None else float('nan'):.2f} dB over {k.n}; SSIM "
          f"{q.ssim if q.ssim is not None else float('nan'):.3f}"
          + (f", LPIPS {q.lpips:.3f}" if q.lpips is not None else ", LPIPS n/a"))
    if r.trajectory is not None:
        print(f"[{r.variant}] ATE {r.trajectory.rmse_m * 100:.2f} cm, "
              f"rotation {r.trajectory.rotation_rmse_deg:.2f} deg "
              f"({r.trajectory.n_matched} poses)")
    rss = ", ".join(f"{n} {v:.0f}" for n, v in m.peak_rss_mb.items())
    graph = "" if m.graph_mb is None else f"; the graph {m.graph_mb:.0f} MB (peak RSS + CUDA peak)"
    print(f"[{r.variant}] Gaussians {r.gaussians} (peak {r.gaussians_peak}), memory {m.headline_kind} "
          f"{m.headline_bytes / 1e6:.1f} MB, peak RSS MB: {rss}{graph}")
    rate = r.mapping_iters_per_s_training
    print(f"[{r.variant}] tracking {r.tracking_fps:.1f} FPS, mapping {r.mapping_iterations} iterations "
          f"({'n/a' if rate is None else f'{rate:.2f}'} it/s while training, "
          f"{r.mapping_iters_per_s:.2f} it/s over the whole run)")
    for note in r.notes:
        print(f"[{r.variant}] note: {note}")


def run(args: argparse.Namespace) -> int:
    source = str(args.source)
    config = args.config or guess_config(source)
    overrides = _overrides(args.set)
    if args.record is not None:
        if args.ablation:
            raise ConfigError("--record records one run; run the variants one at a time to record them")
        args.record = check_record_path(args.record)
    rerun = rerun_target(args)  # ConfigError without rerun-sdk, before anything starts
    check_repeat(args.repeat)
    if args.map is not None and args.ablation:
        raise ConfigError("--map scores one session; drop --ablation")
    warnings = check_inputs(source, config, args.max_frames, overrides, args.out, args.repeat,
                            args.repeat_forward, map_bundle=args.map, map_mode=args.map_mode)  # before torch, nodes
    with run_log(args.out):
        for warning in warnings:
            logger.warning(warning)
        return _evaluate(args, source, config, overrides, rerun)


def _evaluate(args: argparse.Namespace, source: str, config: str, overrides: dict[str, Any],
              rerun: RerunTarget | None) -> int:
    # Loaded here, not at the top: every subcommand module is imported to build the parser, and
    # these pull in torch and matplotlib (seconds), which `memgs --help` and `memgs run` never need.
    import matplotlib

    matplotlib.use("Agg")
    import torch

    from memgs_ros.core.runtime.cpu import configure_cpu_runtime
    from memgs_ros.evaluation import runs as evaluation
    from memgs_ros.evaluation.figures import save_ablation_plot, save_plots
    from memgs_ros.evaluation.tables import ablation_json, ablation_table, markdown_table

    if not torch.cuda.is_available():
        configure_cpu_runtime()  # this process renders every frame on CPU
    kwargs = {"max_frames": args.max_frames, "repeat": args.repeat, "repeat_forward": args.repeat_forward,
              "domain_id": args.domain_id,
              "timeout_s": args.timeout,
                  "composed": args.composed, "use_lpips": not args.no_lpips, "rerun": rerun}
    if args.map is not None:
        kwargs.update(map_bundle=args.map, map_mode=args.map_mode)
    if args.record is not None:
        kwargs["record"] = args.record
    out = Path(args.out)
    if args.ablation:
        res = evaluation.ablation(source, config, args.mode, args.scale, args.seed, out, overrides, **kwargs)
        results = list(res.results)
        table = ablation_table(results)
        evaluation.write_json(out / "ablation.json", ablation_json(res))
        (out / "ablation.md").write_text(table)
    else:
        results = [evaluation.evaluate(source, config, args.mode, args.scale, args.seed, out, overrides, **kwargs)]
        table = markdown_table(results)
    for r in results:
        (Path(r.out_dir) / "table.md").write_text(markdown_table([r]))
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
    if args.record is not None:
        print(f"recording {args.record} ({args.record.stat().st_size / 1e6:.1f} MB)")
    return 0
