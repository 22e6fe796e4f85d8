"""Benchmark: where the mapper's memory goes, part by part, on the map a run ended with.

    python benchmarks/bench_memory.py RUN_DIR [--device cuda] [--json results/bench_memory.json]
    python benchmarks/bench_memory.py --table JSON   # a saved breakdown (bench_gpu.py's too)

RUN_DIR is a finished ``memgs run`` / ``memgs eval`` output folder: its ``mapper_checkpoint.npz``
(the final map and training keyframes) and ``params.yaml`` (the mapper's config) are loaded into a
mapper on ``--device`` (default: the run's), which then does each kind of work once. Per part,
the bytes it holds and the peak it adds above what was allocated when it began (on CUDA
``torch.cuda.max_memory_allocated``, what the issue's 1.70 GB is; on the CPU torch's allocation
events from its profiler, the same measure without a caching allocator):

  parameters, gradients, Adam moments   the map's trained state (GaussianMap.memory_bytes)
  keyframes                             the stored training views (uint8 colour, float16 depth, mask)
  step: forward / loss / backward / Adam a training step at full resolution on the largest keyframe
  merge pass, densify pass              one each, as the schedule runs them
  render (live view, evaluation)        a render without gradients at the training resolution
  snapshot                              the map copied to host records (deltas, checkpoints)
  caching allocator (CUDA)              reserved minus allocated at the end: what the GPU keeps

Run nothing else on the GPU meanwhile; figures are MiB.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from _common import ROOT, write_results

if str(ROOT) not in sys.path:  # run as a script from a checkout without an install (a lent GPU machine)
    sys.path.insert(0, str(ROOT))

MB = 2**20


def measure(fn: Callable[[], Any], device: Any) -> tuple[Any, int, int]:
    """(fn's result, peak bytes allocated above the start, bytes still allocated at the end above
    the start) of torch tensors on ``device``."""
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)
        start = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        out = fn()
        torch.cuda.synchronize(device)
        return out, torch.cuda.max_memory_allocated(device) - start, torch.cuda.memory_allocated(device) - start
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        out = fn()
    current = peak = 0
    for event in sorted(prof.events(), key=lambda e: e.time_range.start):
        current += event.self_cpu_memory_usage
        peak = max(peak, current)
    return out, peak, current


def load_mapper(run_dir: Path, device: str | None) -> Any:
    import yaml

    from memgs_ros.core.mapping import checkpoint
    from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig
    from memgs_ros.core.merge.config import MergeConfig
    from memgs_ros.core.raster.backend_choice import resolve_device

    params = yaml.safe_load((run_dir / "params.yaml").read_text())
    mapper_params = next(v["ros__parameters"] for k, v in params.items() if str(k).endswith("mapper"))
    section = {k.split(".", 1)[1]: v for k, v in mapper_params.items() if k.startswith("mapping.")}
    merge = {k.split(".", 1)[1]: v for k, v in mapper_params.items() if k.startswith("merge.")}
    dev = device or resolve_device(str(mapper_params.get("device", "auto")))
    mapper = GaussianMapper(MappingConfig.from_dict(section), device=dev, merge_cfg=MergeConfig(**merge))
    mapper.load_state_dict(checkpoint.load(run_dir / "mapper_checkpoint.npz"))
    return mapper


def breakdown(mapper: Any) -> dict[str, Any]:
    """Each part's held and peak bytes (see the module docstring)."""
    import torch

    from memgs_ros.core.mapping.losses import mapping_loss
    from memgs_ros.core.raster import warm_up

    dev, cfg, gmap = mapper.device, mapper.cfg, mapper.gmap
    warm_up(dev, cfg.raster_backend, cfg.max_sh_degree)
    rows: list[dict[str, Any]] = []

    def row(part: str, held: int, peak: int | None = None, note: str = "") -> None:
        rows.append({"part": part, "held_mb": round(held / MB, 1),
                     "peak_above_mb": None if peak is None else round(peak / MB, 1), "note": note})

    kf = max(mapper.keyframes.all(), key=lambda k: k.camera.width * k.camera.height)
    level = kf.level(kf.n_levels - 1)  # full resolution: the costliest draw
    out, peak, held = measure(lambda: mapper._rasterize(kf.T_wc, level.camera), dev)  # noqa: SLF001
    fwd = (peak, held)
    (loss, _), peak, held = measure(lambda: mapping_loss(
        out.color, level.image, gmap.log_scales, out.depth, level.depth_m, ssim_lambda=cfg.ssim_lambda,
        iso_weight=cfg.iso_weight, depth_weight=cfg.depth_weight, mask=level.valid_mask), dev)
    loss_mem = (peak, held)
    _, peak, held = measure(loss.backward, dev)
    bwd = (peak, held)
    out = loss = None  # the step's tensors go before the optimizer step, as in GaussianMapper.step
    _, peak, held = measure(gmap.optimizer_step, dev)
    adam = (peak, held)
    mem = gmap.memory_bytes()
    row("parameters", mem.params, note=f"{len(gmap)} Gaussians, SH degree {gmap.active_sh_degree}")
    row("gradients", mem.grads, note="freed after each step (set_to_none)")
    row("Adam moments", mem.optimizer)
    row("keyframes", mapper.keyframes.nbytes(), note=f"{len(mapper.keyframes)} at {kf.camera.width}x{kf.camera.height}")
    row("step: forward (rasterizer)", fwd[1], fwd[0], f"{cfg.raster_backend} backend; held: saved for backward")
    row("step: loss (L1 + SSIM + depth)", loss_mem[1], loss_mem[0])
    row("step: backward", bwd[1], bwd[0], "held: the gradients")
    row("step: Adam", adam[1], adam[0])
    for _ in range(3):  # gradient statistics for densification
        mapper.step(densify=False, final=True)
    newest = max(k.kf_id for k in mapper.keyframes.all())
    _, peak, held = measure(lambda: mapper.merge.run(gmap, newest, mapper.iteration), dev)
    row("merge pass", max(held, 0), peak, f"{len(gmap)} Gaussians after")
    _, peak, held = measure(mapper.densify_and_prune, dev)
    row("densify pass", max(held, 0), peak, f"{len(gmap)} Gaussians after")
    with torch.no_grad():
        _, peak, _ = measure(lambda: mapper.render(kf.T_wc, kf.camera), dev)
    row("render without gradients", 0, peak, "live view, evaluation")
    _, peak, _ = measure(mapper.snapshot, dev)
    row("snapshot to host records", 0, peak, "deltas, checkpoints")
    out_d: dict[str, Any] = {"rows": rows, "device": str(dev), "gaussians": len(gmap),
                             "keyframes": len(mapper.keyframes), "backend": cfg.raster_backend}
    if dev.type == "cuda":
        out_d["cuda_max_allocated_mb"] = round(torch.cuda.max_memory_allocated(dev) / MB, 1)
        out_d["cuda_reserved_mb"] = round(torch.cuda.memory_reserved(dev) / MB, 1)
        out_d["cuda_allocated_mb"] = round(torch.cuda.memory_allocated(dev) / MB, 1)
        row("caching allocator", torch.cuda.memory_reserved(dev) - torch.cuda.memory_allocated(dev),
            note="reserved minus allocated at the end")
    return out_d


def table(res: dict[str, Any]) -> str:
    lines = [f"{res['gaussians']} Gaussians, {res['keyframes']} keyframes, {res['backend']} on {res['device']}", "",
             "| part | held MiB | peak above its start MiB | note |", "|---|---|---|---|"]
    for r in res["rows"]:
        peak = "" if r["peak_above_mb"] is None else f"{r['peak_above_mb']:g}"
        lines.append(f"| {r['part']} | {r['held_mb']:g} | {peak} | {r['note']} |")
    if "cuda_max_allocated_mb" in res:
        lines.append(f"\nCUDA at the end: allocated {res['cuda_allocated_mb']:g} MiB, "
                     f"reserved {res['cuda_reserved_mb']:g} MiB")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path, nargs="?", help="a finished memgs run/eval output folder")
    ap.add_argument("--device", default=None, help="torch device (default: the run's mapper device)")
    ap.add_argument("--json", type=Path, default=ROOT / "results/bench_memory.json")
    ap.add_argument("--table", type=Path, default=None, metavar="JSON",
                    help="print the table of a saved breakdown (this script's JSON, or bench_gpu.py's, whose "
                         "memory stage it is) and exit")
    args = ap.parse_args(argv)
    if args.table is not None:
        saved = json.loads(args.table.read_text())
        print(table(saved.get("memory", saved)), end="")
        return 0
    if args.run_dir is None:
        ap.error("give RUN_DIR (or --table JSON)")
    from memgs_ros.core.runtime.cpu import configure_cpu_runtime

    configure_cpu_runtime()
    t0 = time.perf_counter()
    res = breakdown(load_mapper(args.run_dir, args.device))
    res["seconds"] = round(time.perf_counter() - t0, 1)
    res["run_dir"] = str(args.run_dir)
    write_results(args.json, res)
    print(table(res), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
