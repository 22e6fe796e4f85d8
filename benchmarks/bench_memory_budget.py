"""Benchmark: the PSNR cost of a mapper memory budget at half the unbudgeted map size.

Protocol: ``benchmarks/bench_mapping.py``'s (ground-truth poses, grid seeds, all keyframes
inserted then ``iterations`` training steps, the ``cpu`` preset), run twice with the same seed:

  unbudgeted  MappingConfig as bench_mapping builds it;
  budgeted    the same plus ``max_gaussians`` = ``--fraction`` (default 0.5) x the unbudgeted
              run's final Gaussian count (or ``--budget N``).

``--set KEY=VALUE`` overrides both arms, ``--budget-set KEY=VALUE`` only the budgeted one (e.g.
``--budget-set budget_merge=False`` for the prune-only ablation). ``--unbudgeted-json PATH``
reuses the unbudgeted arm of an earlier run of this benchmark (or a bench_mapping JSON) instead
of training it again. Reported per arm: final Gaussians, model MiB (``memory_bytes().total``:
params + grads + Adam), keyframe and all-frames PSNR (whole image, the reference protocol),
training wall time, what the budget removed, and the PSNR cost (unbudgeted - budgeted, dB).
``uptime`` load is recorded (the machine is shared). JSON to ``--out`` (default
results/bench_memory_budget.json).

    python benchmarks/bench_memory_budget.py                 # synthetic
    python benchmarks/bench_memory_budget.py --dataset tum
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import asdict
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_mapping  # benchmarks/ is not a package: found through the path above
from _common import TUM_HELP, TumNotFound, tum_path, write_results


def mapping_args(args: argparse.Namespace, overrides: list[str]) -> argparse.Namespace:
    """The namespace ``bench_mapping.run`` reads, with its defaults and ``overrides``."""
    return argparse.Namespace(
        tum=args.tum, iterations=args.iterations, kf_every=args.kf_every, grid=args.grid, max_frames=0,
        max_keyframes=args.max_keyframes, set=list(overrides), depth_weight=bench_mapping.MAPPING_DEPTH_WEIGHT,
        no_merge=args.no_merge, preset="cpu", dedup_voxel=0.0, no_depth_fill=False, pyramid_uses=2,
        skip_all_frames=args.skip_all_frames, device=args.device)


def run_arm(name: str, args: argparse.Namespace, overrides: list[str]) -> dict:
    """One bench_mapping run plus what the budget removed over the run."""
    from memgs_ros.core.mapping import mapper as mapping

    removed = {"budget_merged": 0, "budget_pruned": 0}
    step = mapping.GaussianMapper.step

    def counting_step(self):
        st = step(self)
        if st is not None:
            removed["budget_merged"] += st.budget_merged
            removed["budget_pruned"] += st.budget_pruned
        return st

    mapping.GaussianMapper.step = counting_step
    try:
        result = bench_mapping.run(name, mapping_args(args, overrides))
    finally:
        mapping.GaussianMapper.step = step
    result.pop("config", None)
    result.update(removed)
    result["overrides"] = list(overrides)
    return result


def summary(r: dict) -> dict:
    return {"gaussians": r["final_gaussians"], "model_mib": r["memory_bytes"]["total"] / 2**20,
            "psnr_keyframes": r["psnr_keyframes"], "psnr_all_frames": r["psnr_all_frames"],
            "train_wall_s": r["train_wall_s"], "budget_merged": r.get("budget_merged", 0),
            "budget_pruned": r.get("budget_pruned", 0)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dataset", choices=["synthetic", "tum"], default="synthetic")
    p.add_argument("--tum", default=None, help=TUM_HELP)
    p.add_argument("--iterations", type=int, default=0, help="training steps (default per dataset)")
    p.add_argument("--kf-every", type=int, default=0)
    p.add_argument("--grid", type=int, default=0)
    p.add_argument("--max-keyframes", type=int, default=0)
    p.add_argument("--fraction", type=float, default=0.5, help="budget = this x the unbudgeted final count")
    p.add_argument("--budget", type=int, default=0, help="explicit max_gaussians (overrides --fraction)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="MappingConfig override, both arms")
    p.add_argument("--budget-set", action="append", default=[], metavar="KEY=VALUE",
                   help="MappingConfig override, budgeted arm only")
    p.add_argument("--unbudgeted-json", default=None, help="reuse the unbudgeted arm from this JSON")
    p.add_argument("--no-merge", action="store_true")
    p.add_argument("--skip-all-frames", action="store_true")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="results/bench_memory_budget.json")
    args = p.parse_args(argv)
    if not 0.0 < args.fraction <= 1.0:
        p.error("--fraction must be in (0, 1]")
    if args.dataset == "tum":
        try:
            tum_path(args.tum)
        except TumNotFound as err:
            print(f"[tum] {err}", file=sys.stderr)
            return 1

    from memgs_ros.core.runtime.cpu import configure_cpu_runtime

    rt = configure_cpu_runtime(torch_threads=args.threads)
    if args.unbudgeted_json:
        doc = json.loads(Path(args.unbudgeted_json).read_text())
        free = doc["unbudgeted"] if "unbudgeted" in doc else next(
            r for r in doc["results"] if r["dataset"] == args.dataset)
        print(f"[unbudgeted] reused from {args.unbudgeted_json}", flush=True)
    else:
        print("[unbudgeted]", flush=True)
        free = run_arm(args.dataset, args, args.set)
    budget = args.budget or max(int(args.fraction * free["final_gaussians"]), 1)
    print(f"[budgeted] max_gaussians={budget}", flush=True)
    capped = run_arm(args.dataset, args, [*args.set, f"max_gaussians={budget}", *args.budget_set])
    a, b = summary(free), summary(capped)
    cost_kf = a["psnr_keyframes"] - b["psnr_keyframes"]
    cost_all = (a["psnr_all_frames"] - b["psnr_all_frames"]
                if a["psnr_all_frames"] is not None and b["psnr_all_frames"] is not None else None)
    print(f"\n{args.dataset}: budget {budget} Gaussians ({args.fraction:g} x unbudgeted)"
          if not args.budget else f"\n{args.dataset}: budget {budget} Gaussians")
    print(f"{'arm':11s} {'Gaussians':>9s} {'MiB':>6s} {'PSNR kf':>8s} {'PSNR all':>8s} {'wall s':>7s} "
          f"{'merged':>7s} {'pruned':>7s}")
    for arm, s in (("unbudgeted", a), ("budgeted", b)):
        all_ = f"{s['psnr_all_frames']:8.2f}" if s["psnr_all_frames"] is not None else f"{'-':>8s}"
        print(f"{arm:11s} {s['gaussians']:9d} {s['model_mib']:6.2f} {s['psnr_keyframes']:8.2f} {all_} "
              f"{s['train_wall_s']:7.1f} {s['budget_merged']:7d} {s['budget_pruned']:7d}")
    print(f"PSNR cost: keyframes {cost_kf:+.2f} dB, all frames "
          + (f"{cost_all:+.2f} dB" if cost_all is not None else "-")
          + f"; load average {free['loadavg_before']:.2f} .. {capped['loadavg_after']:.2f}")
    out = write_results(args.out, {
        "dataset": args.dataset, "budget": budget, "fraction": None if args.budget else args.fraction,
        "psnr_cost_keyframes_db": cost_kf, "psnr_cost_all_frames_db": cost_all,
        "summary": {"unbudgeted": a, "budgeted": b}, "runtime": asdict(rt),
        "unbudgeted": free, "budgeted": capped})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
