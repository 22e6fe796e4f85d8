"""Benchmark: forward + backward of the CPU rasterizer on a synthetic room scene.

Scene (deterministic, seed 0): the camera looks into a 4 m x 2.7 m room (back wall at z = 4 m,
floor, ceiling, side walls) with three spheres between 1.8 m and 3 m. Gaussians are placed
where rays through uniformly random pixel positions (10 % margin beyond the image border) first
hit a surface, so the map is uniformly dense on screen as a SLAM map seen from a keyframe is.
Each Gaussian is a flat disc in its surface (normal scale 0.15x the tangent scale) with a
tangent sigma of ``SIGMA_PX`` px (log-normal, x/1.5) at its depth and a random spin; opacity
logits ~ N(1.5, 1.5), SH degree 3 with small random higher bands. Scales do not change with the
count, so 50k and 100k are 2.5x and 5x denser than 20k (about 20 Gaussians per pixel within
3 sigma at 20k, 320x240). Loss: L1 to a fixed random target colour + 0.1 x L1 depth.

``--backend`` picks the CPU compositor as ``rasterize(backend=...)`` does (auto: the compiled
numba one when numba imports, else torch). Each count runs in its own subprocess (clean peak RSS); per count: ``--warmup`` untimed
iterations, then the median of ``--runs`` timed ones. Prints a table and writes JSON
(default results/bench_raster.json).

    python benchmarks/bench_raster.py --width 320 --height 240 --counts 20000 50000 100000
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _common import write_results

SIGMA_PX = 1.8  # median tangent sigma in pixels (before the 0.3 px^2 dilation)


def build_scene(n: int, width: int, height: int, seed: int = 0):  # -> (params, T_cw, camera)
    import torch

    from memgs_ros.core.geometry.camera import TUM_FR1, PinholeCamera
    from memgs_ros.core.geometry.poses import rotmat_to_quat_wxyz_torch

    base = TUM_FR1.undistorted()
    cam = PinholeCamera(
        width,
        height,
        base.fx * width / base.width,
        base.fy * height / base.height,
        (base.cx + 0.5) * width / base.width - 0.5,
        (base.cy + 0.5) * height / base.height - 0.5,
    )
    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    u = torch.rand(n, generator=g, dtype=dt) * 1.2 * width - 0.1 * width
    v = torch.rand(n, generator=g, dtype=dt) * 1.2 * height - 0.1 * height
    rays = torch.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, torch.ones_like(u)], -1)  # [n, 3], z = 1

    # Planes: (normal, offset) with n . p = offset; the camera (origin) is inside the room.
    planes = [((0, 0, -1.0), -4.0), ((0, -1.0, 0), -1.2), ((0, 1.0, 0), -1.5), ((1.0, 0, 0), -2.0), ((-1.0, 0, 0), -2.0)]
    best_t = torch.full((n,), math.inf, dtype=dt)
    best_n = torch.zeros(n, 3, dtype=dt)
    for normal, off in planes:
        nn = torch.tensor(normal, dtype=dt)
        denom = rays @ nn
        t = torch.where(denom.abs() > 1e-9, off / denom, torch.full_like(denom, math.inf))
        t = torch.where(t > 0, t, torch.full_like(t, math.inf))
        better = t < best_t
        best_t = torch.where(better, t, best_t)
        best_n[better] = -nn  # facing the camera
    spheres = [((-0.6, 0.3, 2.2), 0.45), ((0.7, 0.5, 3.0), 0.6), ((0.2, -0.4, 1.8), 0.3)]
    for centre, radius in spheres:
        c = torch.tensor(centre, dtype=dt)
        # |t r - c|^2 = R^2  ->  a t^2 - 2 b t + (|c|^2 - R^2) = 0
        a = (rays * rays).sum(-1)
        b = rays @ c
        disc = b * b - a * (c @ c - radius * radius)
        t = (b - torch.sqrt(disc.clamp_min(0))) / a
        t = torch.where((disc > 0) & (t > 0), t, torch.full_like(t, math.inf))
        better = t < best_t
        best_t = torch.where(better, t, best_t)
        hit = rays[better] * t[better, None]
        best_n[better] = (hit - c) / radius
    p_c = rays * best_t[:, None]  # [n, 3]
    z = p_c[:, 2]

    # Local frame: third axis along the surface normal, random spin about it.
    nrm = best_n / best_n.norm(dim=-1, keepdim=True)
    helper = torch.where((nrm[:, :1].abs() < 0.9), torch.tensor([1.0, 0, 0], dtype=dt), torch.tensor([0, 1.0, 0], dtype=dt))
    t1 = torch.linalg.cross(nrm, helper)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(nrm, t1)
    spin = torch.rand(n, generator=g, dtype=dt) * 2 * math.pi
    a1 = t1 * torch.cos(spin)[:, None] + t2 * torch.sin(spin)[:, None]
    a2 = torch.linalg.cross(nrm, a1)
    R = torch.stack([a1, a2, nrm], dim=-1)  # columns = local axes, [n, 3, 3]
    sigma_px = SIGMA_PX * torch.exp(torch.randn(n, generator=g, dtype=dt) * math.log(1.5))
    s_tan = sigma_px * z / cam.fx
    aniso = torch.exp(torch.randn(n, 2, generator=g, dtype=dt) * 0.3)
    scales = torch.stack([s_tan * aniso[:, 0], s_tan * aniso[:, 1], 0.15 * s_tan], -1)

    # World = camera rotated by a small yaw/pitch and shifted, so T_cw is a real pose.
    T_cw = torch.eye(4, dtype=dt)
    yaw, pitch = 0.2, -0.1
    Ry = torch.tensor([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]], dtype=dt)
    Rx = torch.tensor([[1, 0, 0], [0, math.cos(pitch), -math.sin(pitch)], [0, math.sin(pitch), math.cos(pitch)]], dtype=dt)
    T_cw[:3, :3] = Rx @ Ry
    T_cw[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=dt)
    Rcw, tcw = T_cw[:3, :3], T_cw[:3, 3]
    means = (p_c - tcw) @ Rcw  # R^T (p_c - t)
    R_w = Rcw.T @ R  # Gaussian axes in world
    quats = rotmat_to_quat_wxyz_torch(R_w)
    f32 = torch.float32
    params = [
        means.to(f32),
        quats.to(f32),
        torch.log(scales).to(f32),
        (1.5 + 1.5 * torch.randn(n, 1, generator=g, dtype=dt)).to(f32),
        torch.randn(n, 1, 3, generator=g, dtype=dt).to(f32),
        (0.1 * torch.randn(n, 15, 3, generator=g, dtype=dt)).to(f32),
    ]
    return [p.requires_grad_() for p in params], T_cw.to(f32), cam


def _rss_mb() -> tuple[float, float]:
    """(current RSS, peak RSS) of this process in MiB."""
    cur = 0.0
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                cur = int(line.split()[1]) / 1024
    return cur, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def resolve_backend(backend: str) -> str:
    """The CPU compositor that rasterize(..., backend=backend) uses: "torch" or "numba"."""
    from memgs_ros.core.runtime.cpu import numba_available

    if backend == "auto":
        return "numba" if numba_available() else "torch"
    return backend


def _compositor(backend: str, threads: int | None):  # -> (composite function, tile size)
    """The composite function and tile size rasterize() uses for ``backend`` on the CPU, pinned to
    ``threads`` threads (None: its default)."""
    from memgs_ros.core.raster.composite import composite
    from memgs_ros.core.raster.composite_numba import NUMBA_TILE_SIZE, composite_numba
    from memgs_ros.core.raster.tiles import TILE_SIZE

    if resolve_backend(backend) == "numba":
        return (lambda *a: composite_numba(*a, threads=threads)), NUMBA_TILE_SIZE
    return (lambda *a: composite(*a, workers=threads)), TILE_SIZE


def run_one(
    n: int, width: int, height: int, runs: int, warmup: int, threads: int, keep_heap: bool, backend: str
) -> dict:
    """Time forward/backward for one Gaussian count in this process; returns a result row."""
    import torch

    from memgs_ros.core.raster import Gaussians, rasterize
    from memgs_ros.core.raster.projection import alpha_cutoff_sq, project_gaussians
    from memgs_ros.core.raster.rules import MIN_ALPHA
    from memgs_ros.core.raster.tiles import build_tile_plan
    from memgs_ros.core.raster.values import Splats2D
    from memgs_ros.core.runtime.cpu import configure_cpu_runtime

    composite_fn, tile_size = _compositor(backend, None)

    rt = configure_cpu_runtime(torch_threads=threads, keep_heap=keep_heap)
    params, T_cw, cam = build_scene(n, width, height)
    g = torch.Generator().manual_seed(1)
    target = torch.rand(3, height, width, generator=g)
    target_depth = torch.full((height, width), 3.0)

    with torch.no_grad():
        proj = project_gaussians(Gaussians(*params), T_cw, cam, 3, 0.01)
        det = proj.cov2d[:, 0] * proj.cov2d[:, 2] - proj.cov2d[:, 1] ** 2
        on_img = (
            proj.in_front
            & (proj.means2d[:, 0] >= 0) & (proj.means2d[:, 0] < width)
            & (proj.means2d[:, 1] >= 0) & (proj.means2d[:, 1] < height)
        )
        coverage = float((9 * math.pi * det.sqrt())[on_img].sum()) / (width * height)
        plan = build_tile_plan(
            proj.means2d, proj.cov2d, alpha_cutoff_sq(proj.opacities, MIN_ALPHA), proj.depths, proj.in_front, width, height,
            tile_size,
        )
        p = plan.tile_size ** 2
        pairs = plan.num_pairs * p
        padded = sum(int(c.tiles.numel()) * p * c.k for c in plan.chunks) if resolve_backend(backend) == "torch" else 0

    rss_before, _ = _rss_mb()
    fwd, bwd, tot, cpu = [], [], [], []
    for it in range(warmup + runs):
        for q in params:
            q.grad = None
        c0 = time.process_time()
        t0 = time.perf_counter()
        out = rasterize(Gaussians(*params), T_cw, cam, 3, backend=backend)
        t1 = time.perf_counter()
        loss = (out.color - target).abs().mean() + 0.1 * (out.depth - target_depth).abs().mean()
        loss.backward()
        t2 = time.perf_counter()
        c2 = time.process_time()
        if it >= warmup:
            cpu.append(c2 - c0)
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            tot.append(t2 - t0)
    rss_after, peak = _rss_mb()

    # The compositor alone (forward + backward, default threads): CPU ns per pixel-Gaussian pair.
    proj = project_gaussians(Gaussians(*params), T_cw, cam, 3, 0.01)
    inputs = [proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths, torch.zeros(3)]
    cot = [torch.rand(3, height, width, generator=g), torch.rand(height, width, generator=g), torch.rand(height, width, generator=g)]
    comp = []
    for it in range(warmup + runs):
        c0 = time.process_time()
        outs = composite_fn(Splats2D(*inputs[:5]), inputs[5], plan)
        torch.autograd.grad(outs, inputs[:5], cot, retain_graph=True)
        if it >= warmup:
            comp.append(time.process_time() - c0)
    return {
        "gaussians": n,
        "backend": resolve_backend(backend),
        "tile_size": plan.tile_size,
        "width": width,
        "height": height,
        "torch_threads": rt.torch_threads,
        "heap_kept": rt.heap_kept,
        "coverage_3sigma_per_px": round(coverage, 1),
        "pixel_pairs_per_px": round(pairs / (width * height), 1),
        "padded_pairs_per_px": round(padded / (width * height), 1),
        "visible": int(out.visible.sum()),
        "fwd_ms_median": 1e3 * statistics.median(fwd),
        "bwd_ms_median": 1e3 * statistics.median(bwd),
        "total_ms_median": 1e3 * statistics.median(tot),
        "total_ms_min": 1e3 * min(tot),
        "cpu_ms_median": 1e3 * statistics.median(cpu),
        "composite_cpu_ms_median": 1e3 * statistics.median(comp),
        "composite_ns_per_pair": 1e9 * statistics.median(comp) / max(pairs, 1),
        "total_ms_all": [round(1e3 * t, 1) for t in tot],
        "rss_mb_before_loop": round(rss_before, 1),
        "rss_mb_after_loop": round(rss_after, 1),
        "peak_rss_mb": round(peak, 1),
        "saved_pair_mb": round(padded * 8 / 2**20, 1),
    }


def stage_breakdown(n: int, width: int, height: int, runs: int, backend: str) -> dict[str, float]:
    """CPU ms per stage (min over ``runs``), compositing on this thread only (one thread)."""
    import torch

    from memgs_ros.core.raster import Gaussians
    from memgs_ros.core.raster.projection import alpha_cutoff_sq, project_gaussians
    from memgs_ros.core.raster.rules import MIN_ALPHA
    from memgs_ros.core.raster.tiles import build_tile_plan
    from memgs_ros.core.raster.values import Splats2D
    from memgs_ros.core.runtime.cpu import configure_cpu_runtime

    configure_cpu_runtime(torch_threads=1)
    composite, tile_size = _compositor(backend, 1)
    if resolve_backend(backend) == "numba":  # rasterize() projects with the compiled twin then
        from memgs_ros.core.raster.projection_numba import project_gaussians_numba

        def project_gaussians(*a):  # noqa: F811
            return project_gaussians_numba(*a, threads=1)
    params, T_cw, cam = build_scene(n, width, height)
    target = torch.rand(3, height, width, generator=torch.Generator().manual_seed(1))
    times: dict[str, list[float]] = {}
    for _ in range(runs + 2):
        for q in params:
            q.grad = None
        marks = [("start", time.thread_time())]
        proj = project_gaussians(Gaussians(*params), T_cw, cam, 3, 0.01)
        proj.means2d.retain_grad()
        marks.append(("project", time.thread_time()))
        cut = alpha_cutoff_sq(proj.opacities.detach(), MIN_ALPHA)
        plan = build_tile_plan(proj.means2d, proj.cov2d, cut, proj.depths, proj.in_front, width, height, tile_size)
        marks.append(("bin", time.thread_time()))
        bg = torch.zeros(3)
        inputs = [proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths]
        color, depth, _ = composite(Splats2D(*inputs), bg, plan)
        marks.append(("composite fwd", time.thread_time()))
        loss = (color - target).abs().mean() + 0.1 * depth.abs().mean()
        v_color, v_depth = torch.autograd.grad(loss, [color, depth], retain_graph=True)
        marks.append(("loss", time.thread_time()))
        v_inputs = torch.autograd.grad([color, depth], inputs, [v_color, v_depth], retain_graph=True)
        marks.append(("composite bwd", time.thread_time()))
        torch.autograd.backward(inputs, list(v_inputs))
        marks.append(("project bwd", time.thread_time()))
        for (_, t0), (name, t1) in zip(marks, marks[1:]):
            times.setdefault(name, []).append(1e3 * (t1 - t0))
    return {name: min(v[2:]) for name, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--counts", type=int, nargs="+", default=[20000, 50000, 100000])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (1 = Python threads per chunk)")
    ap.add_argument("--backend", choices=("auto", "torch", "numba"), default="auto",
                    help="CPU compositor (auto: numba when importable)")
    ap.add_argument("--no-keep-heap", action="store_true", help="skip the mallopt tuning")
    ap.add_argument("--out", type=Path, default=Path("results/bench_raster.json"))
    ap.add_argument("--stages", action="store_true", help="also print a CPU-time breakdown per stage (one thread)")
    ap.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker is not None:
        row = run_one(
            args.worker, args.width, args.height, args.runs, args.warmup, args.threads, not args.no_keep_heap, args.backend
        )
        print(json.dumps(row))
        return 0

    load_before = os.getloadavg()
    rows = []
    for n in args.counts:
        cmd = [
            sys.executable, __file__, "--worker", str(n), "--width", str(args.width), "--height", str(args.height),
            "--runs", str(args.runs), "--warmup", str(args.warmup), "--threads", str(args.threads),
            "--backend", args.backend,
        ] + (["--no-keep-heap"] if args.no_keep_heap else [])
        res = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if res.returncode != 0:
            print(res.stderr, file=sys.stderr)
            return res.returncode
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    load_after = os.getloadavg()

    head = f"{'N':>7} {'cover/px':>8} {'pairs/px':>8} {'ns/pair':>7} {'fwd ms':>8} {'bwd ms':>8} {'total ms':>9} {'min ms':>7} {'cpu ms':>7} {'peak RSS MB':>11} {'saved MB':>8}"
    backend = resolve_backend(args.backend)
    tile = rows[0]["tile_size"] if rows else "-"
    print(
        f"rasterizer fwd+bwd, {args.width}x{args.height}, compositor {backend} ({tile} px tiles), "
        f"torch threads {args.threads}, median of {args.runs}"
    )
    print(head)
    for r in rows:
        print(
            f"{r['gaussians']:>7} {r['coverage_3sigma_per_px']:>8} {r['pixel_pairs_per_px']:>8}"
            f" {r['composite_ns_per_pair']:>7.2f} {r['fwd_ms_median']:>8.1f}"
            f" {r['bwd_ms_median']:>8.1f} {r['total_ms_median']:>9.1f} {r['total_ms_min']:>7.1f} {r['cpu_ms_median']:>7.1f} {r['peak_rss_mb']:>11.1f}"
            f" {r['saved_pair_mb']:>8.1f}"
        )
    print("cpu ms = process CPU time (all threads) per iteration: what the work costs regardless of load")
    print(
        "pairs/px = pixel-Gaussian pairs of the tile plan per pixel (tile pairs x tile pixels); ns/pair = CPU ns "
        "of the compositor alone (forward + backward) per such pair"
    )
    print(f"load average before {load_before[0]:.2f}, after {load_after[0]:.2f} (1 min), cpus {os.cpu_count()}")
    write_results(args.out, {"rows": rows, "loadavg_before": load_before, "loadavg_after": load_after,
                             "argv": sys.argv})
    if args.stages:
        print(f"CPU ms per stage, one thread, min of {args.runs} (N = {args.counts[0]}):")
        stages = stage_breakdown(args.counts[0], args.width, args.height, args.runs, args.backend)
        for name, ms in stages.items():
            print(f"  {name:14s} {ms:7.1f}")
        print(f"  {'total':14s} {sum(stages.values()):7.1f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
