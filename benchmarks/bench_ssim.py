"""SSIM forward+backward timing on CPU: the numba path (fused row sweeps, what ``ssim`` uses on
CPU when numba is available), the torch path (grouped separable convolution, hand-written
backward: CUDA and installs without numba) and their plain twin (explicit 2-D window, autograd),
plus the photometric loss ((1 - lambda) L1 + lambda (1 - SSIM), with and without a pixel mask)
on either path.

    python benchmarks/bench_ssim.py [--threads 1] [--repeats 20] [--out results/bench_ssim.json]

Each repeat runs every implementation once, in turn, so a change in the machine's load hits
them alike. Prints wall and process-CPU medians (CPU time is less distorted when other
processes share the cores), the CPU-time ratio against the numba path of the same size and
kind, and the load average; writes the same as JSON. The image being differentiated is the
first; the target needs no gradient, as in the mapper.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from _common import write_results

from memgs_ros.core.mapping.losses import photometric_loss
from memgs_ros.core.metrics import ssim as ssim_module
from memgs_ros.core.metrics.ssim import _ssim_map
from memgs_ros.core.runtime.cpu import numba_available


def _ssim_on(compiled: bool) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """Mean SSIM on one path (default window and constants), as ``ssim`` computes it."""
    return lambda a, b: ssim_module._fast_ssim_map(a, b, 11, 1.5, 0.01 ** 2, 0.03 ** 2, 1.0,
                                                   compiled=compiled).mean()


def _loss_on(compiled: bool, mask: torch.Tensor | None) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """photometric_loss (lambda 0.2) with its SSIM forced onto one path."""
    def run(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        saved = ssim_module._use_numba
        ssim_module._use_numba = lambda x: compiled  # benchmark only: pick the path under the loss
        try:
            return photometric_loss(a, b, 0.2, mask)[0]
        finally:
            ssim_module._use_numba = saved
    return run


def _bind(f: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], x: torch.Tensor,  # [3, H, W]
          y: torch.Tensor,  # [3, H, W]
          ) -> Callable[[], torch.Tensor]:
    """A scalar to minimise, 1 - f(x, y), as the loss uses SSIM."""
    return lambda: 1.0 - f(x, y)


def _time_interleaved(fns: dict[str, Callable[[], torch.Tensor]], repeats: int) -> dict[str, dict[str, float]]:
    """Median wall / process-CPU ms of fn().backward() per name; two warm-up rounds dropped."""
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats + 2):
        for name, fn in fns.items():
            t, c = time.perf_counter(), time.process_time()
            fn().backward()
            wall[name].append(time.perf_counter() - t)
            cpu[name].append(time.process_time() - c)
    return {k: {"wall_median_ms": statistics.median(wall[k][2:]) * 1e3,
                "wall_min_ms": min(wall[k][2:]) * 1e3,
                "cpu_median_ms": statistics.median(cpu[k][2:]) * 1e3} for k in fns}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--out", type=Path, default=Path("results/bench_ssim.json"))
    args = p.parse_args()
    if not numba_available():
        raise SystemExit("bench_ssim: numba is not available (or MEMGS_DISABLE_NUMBA is set)")
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    rows = []
    load_before = os.getloadavg()
    for h, w in [(480, 640), (240, 320)]:
        x = torch.rand(3, h, w, generator=g, requires_grad=True)
        y = torch.rand(3, h, w, generator=g)
        mask = torch.rand(h, w, generator=g) > 0.05
        groups = [
            ("ssim", {"numba": _bind(_ssim_on(True), x, y), "torch": _bind(_ssim_on(False), x, y)}, args.repeats),
            ("ssim", {"2-D twin": _bind(lambda a, b: _ssim_map(a, b).mean(), x, y)}, max(3, args.repeats // 4)),
            ("loss", {"numba": _bind(_loss_on(True, None), x, y), "torch": _bind(_loss_on(False, None), x, y)},
             args.repeats),
            ("loss+mask", {"numba": _bind(_loss_on(True, mask), x, y), "torch": _bind(_loss_on(False, mask), x, y)},
             args.repeats),
        ]
        base: dict[str, float] = {}
        for kind, fns, reps in groups:
            for name, r in _time_interleaved(fns, reps).items():
                if name == "numba":
                    base[kind] = r["cpu_median_ms"]
                rows.append({"size": f"{w}x{h}", "kind": kind, "impl": name, **r,
                             "cpu_ratio_vs_numba": r["cpu_median_ms"] / base[kind]})
    load_after = os.getloadavg()
    print(f"threads={args.threads}  load average before {load_before[0]:.2f}, after {load_after[0]:.2f}")
    print(f"{'size':>8} {'kind':>9} {'impl':>9} {'wall med ms':>12} {'wall min ms':>12} {'cpu med ms':>11} "
          f"{'cpu / numba':>12}")
    for r in rows:
        print(f"{r['size']:>8} {r['kind']:>9} {r['impl']:>9} {r['wall_median_ms']:12.1f} {r['wall_min_ms']:12.1f} "
              f"{r['cpu_median_ms']:11.2f} {r['cpu_ratio_vs_numba']:12.2f}")
    write_results(args.out, {"threads": args.threads, "loadavg_before": load_before,
                             "loadavg_after": load_after, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
