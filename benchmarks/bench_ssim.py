"""SSIM forward+backward timing on CPU: the fast path (grouped separable filter, hand-written
backward) against its plain twin (explicit 2-D window, autograd).

    python benchmarks/bench_ssim.py [--threads 1] [--repeats 20] [--out results/bench_ssim.json]

Prints wall and process-CPU medians (CPU time is less distorted when other processes share
the cores) and the load average; writes the same as JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from memgs_ros.core.ssim import _ssim_map, ssim


def _time(fn, repeats: int) -> dict[str, float]:
    wall, cpu = [], []
    for _ in range(repeats + 2):  # two warm-up runs, dropped
        t, c = time.perf_counter(), time.process_time()
        (1.0 - fn()).backward()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return {"wall_median_ms": statistics.median(wall[2:]) * 1e3, "wall_min_ms": min(wall[2:]) * 1e3,
            "cpu_median_ms": statistics.median(cpu[2:]) * 1e3}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--out", type=Path, default=Path("results/bench_ssim.json"))
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    rows = []
    load_before = os.getloadavg()
    for h, w in [(480, 640), (240, 320)]:
        a = torch.rand(3, h, w, generator=g, requires_grad=True)
        b = torch.rand(3, h, w, generator=g)
        for name, fn, reps in [("fast", lambda: ssim(a, b), args.repeats),
                               ("2-D twin", lambda: _ssim_map(a, b).mean(), max(3, args.repeats // 4))]:
            rows.append({"size": f"{w}x{h}", "impl": name, **_time(fn, reps)})
    load_after = os.getloadavg()
    print(f"threads={args.threads}  load average before {load_before[0]:.2f}, after {load_after[0]:.2f}")
    print(f"{'size':>8} {'impl':>9} {'wall med ms':>12} {'wall min ms':>12} {'cpu med ms':>11}")
    for r in rows:
        print(f"{r['size']:>8} {r['impl']:>9} {r['wall_median_ms']:12.1f} {r['wall_min_ms']:12.1f} {r['cpu_median_ms']:11.1f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"threads": args.threads, "loadavg_before": load_before,
                                    "loadavg_after": load_after, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
