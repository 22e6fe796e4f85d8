"""Benchmark: what the Rerun view costs.

``map``: logging one map of ``--gaussians`` (default 60k) Gaussians to a file sink, conversion
included and until rerun has written it (``flush``): median of ``--repeats`` (5), without SH (what
the live bridge sends by default) and with SH (what ``memgs view`` sends).

``run``: the same lockstep run (``memgs run``, the mapping run of ``memgs eval``; its scoring does
not involve Rerun) without and with ``--rerun-save``, alternately, ``--pairs`` times. Reports wall
time (the run's own, from its summary), the CPU time of every process of the run (this process's
children), and the bridge's CPU time, time in Rerun's log calls, peak RSS and file size. Load
(``uptime``) is printed before each run: on a shared machine compare the two medians and CPU
times, not single walls.

    python benchmarks/bench_rerun.py map
    python benchmarks/bench_rerun.py run --config tum_fr1   # the fr1/rpy head (or a SOURCE, $MEMGS_TUM)
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import TUM_ENV, run_memgs, tum_path_or_exit, uptime, write_results

from memgs_ros.core.gaussians.records import GaussianRecords


def _map(n: int, seed: int = 0) -> GaussianRecords:
    """A map of n Gaussians with trained-looking values (all 45 SH coefficients non-zero)."""
    rng = np.random.default_rng(seed)
    return GaussianRecords.from_arrays(
        np.arange(n), rng.uniform(-3, 3, (n, 3)), rng.normal(0, 1, (n, 3)), rng.normal(0, 0.1, (n, 45)),
        rng.normal(0, 2, n), rng.normal(-4, 0.5, (n, 3)), rng.normal(size=(n, 4)))


def bench_map(args: argparse.Namespace) -> dict[str, Any]:
    from memgs_ros.viz import RerunTarget
    from memgs_ros.viz import rerun_log as rl
    from memgs_ros.viz.splats import splat_arrays

    records = _map(args.gaussians)
    print(f"machine: {os.cpu_count()} cores, {uptime()}")
    out: dict[str, Any] = {"gaussians": args.gaussians, "repeats": args.repeats, "uptime": uptime()}
    convert = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        splat_arrays(records, sh=True)
        convert.append(time.perf_counter() - t0)
    out["convert_s_median"] = statistics.median(convert)
    with tempfile.TemporaryDirectory() as tmp:
        for sh in (False, True):
            path = Path(tmp) / f"map_sh{int(sh)}.rrd"
            rec = RerunTarget(save_path=path).open("memgs_bench")
            wall, cpu = [], []
            for i in range(args.repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                rl.log_map(rec, records, rl.LogTime(i), sh=sh)
                rec.flush()  # until rerun's threads have encoded and written it
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            rl.finish(rec)
            key = "with_sh" if sh else "no_sh"
            out[key] = {"wall_s_median": statistics.median(wall), "wall_s_max": max(wall),
                        "cpu_s_median": statistics.median(cpu), "bytes_per_map": path.stat().st_size / args.repeats}
    print(f"map of {args.gaussians} Gaussians, median of {args.repeats}: conversion {out['convert_s_median']:.3f} s")
    for key in ("no_sh", "with_sh"):
        r = out[key]
        print(f"  log + flush to file, {key:7s}: wall {r['wall_s_median']:.3f} s (max {r['wall_s_max']:.3f}), "
              f"CPU {r['cpu_s_median']:.3f} s, {r['bytes_per_map'] / 1e6:.1f} MB a map")
    return out


def _last(out: Path, node: str) -> dict[str, Any]:
    from memgs_ros.orchestration.run_files import read_stats_timeline

    rows = [r for r in read_stats_timeline(out) if r["node"] == node]
    return rows[-1] if rows else {}


def _one_run(args: argparse.Namespace, work: Path, i: int, rerun: bool) -> dict[str, Any]:
    out = work / f"run{i}_{'rerun' if rerun else 'plain'}"
    cmd = ["run", "--bag", args.source]
    cmd += ["--config", args.config] if args.config else []
    cmd += ["--max-frames", str(args.max_frames)] if args.max_frames else []
    for item in args.set:
        cmd += ["--set", item]
    if rerun:
        cmd += ["--rerun-save", str(out / "run.rrd")]
    load = uptime()
    run = run_memgs(cmd, out)
    if run.summary is None:
        raise SystemExit(f"run {i} failed ({run.returncode}):\n{run.output[-3000:]}")
    s = run.summary
    r: dict[str, Any] = {
        "rerun": rerun, "uptime_before": load, "wall_s": s.wall_s, "command_s": run.wall_s,
        "cpu_s_all_processes": run.cpu_s, "frames": s.frames, "gaussians": s.gaussians, "cpu_s_by_process": s.cpu_s}
    if rerun:
        b = _last(out, "rerun_bridge")
        r.update(bridge_cpu_s=float(b.get("cpu_s", "nan")), bridge_log_s=float(b.get("log_us_total", 0)) * 1e-6,
                 bridge_peak_rss_mb=float(b.get("peak_rss_mb", "nan")), maps_logged=int(b.get("logged.map", 0)),
                 rrd_mb=(out / "run.rrd").stat().st_size / 1e6)
    print(f"  run {i} {'with' if rerun else 'without'} Rerun: wall {r['wall_s']:.1f} s, CPU (all processes) "
          f"{r['cpu_s_all_processes']:.1f} s" + (f", bridge CPU {r['bridge_cpu_s']:.1f} s (log calls "
          f"{r['bridge_log_s']:.1f} s), {r['maps_logged']} maps, {r['rrd_mb']:.0f} MB" if rerun else "")
          + f"  [{load.split('load average:')[-1].strip()}]", flush=True)
    return r


def bench_run(args: argparse.Namespace) -> dict[str, Any]:
    print(f"machine: {os.cpu_count()} cores; {args.pairs} pairs, alternating without / with --rerun-save")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(2 * args.pairs):
            runs.append(_one_run(args, Path(tmp), i, rerun=i % 2 == 1))
    plain = [r for r in runs if not r["rerun"]]
    view = [r for r in runs if r["rerun"]]
    med = lambda rs, k: statistics.median(r[k] for r in rs)  # noqa: E731
    out = {"source": args.source, "config": args.config, "max_frames": args.max_frames, "runs": runs,
           "wall_s_median": {"plain": med(plain, "wall_s"), "rerun": med(view, "wall_s")},
           "cpu_s_median": {"plain": med(plain, "cpu_s_all_processes"), "rerun": med(view, "cpu_s_all_processes")},
           "bridge_cpu_s_median": med(view, "bridge_cpu_s")}
    # Each with-run against the without-run just before it: load drifts less within a pair.
    ratios = [v["wall_s"] / p["wall_s"] for p, v in zip(plain, view)]
    out["pair_wall_ratios"] = ratios
    by_process = {n: statistics.median(r["cpu_s_by_process"].get(n, 0.0) for r in view) -
                  statistics.median(r["cpu_s_by_process"].get(n, 0.0) for r in plain)
                  for n in view[0]["cpu_s_by_process"]}
    out["cpu_s_by_process_median_difference"] = by_process
    w, c = out["wall_s_median"], out["cpu_s_median"]
    print(f"median wall: without {w['plain']:.1f} s, with {w['rerun']:.1f} s ({100 * (w['rerun'] / w['plain'] - 1):+.1f} %); "
          f"pair ratios {', '.join(f'{100 * (r - 1):+.1f} %' for r in ratios)} "
          f"(median {100 * (statistics.median(ratios) - 1):+.1f} %)")
    print("CPU with minus without, medians by process: "
          + ", ".join(f"{n} {d:+.1f} s" for n, d in by_process.items()))
    print(f"median CPU of all processes: without {c['plain']:.1f} s, with {c['rerun']:.1f} s "
          f"({100 * (c['rerun'] / c['plain'] - 1):+.1f} %); bridge alone {out['bridge_cpu_s_median']:.1f} s "
          f"({100 * out['bridge_cpu_s_median'] / c['plain']:.1f} % of the run's CPU)")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    m = sub.add_parser("map", help="cost of logging one map")
    m.add_argument("--gaussians", type=int, default=60_000)
    m.add_argument("--repeats", type=int, default=5)
    r = sub.add_parser("run", help="a run without and with --rerun-save, alternately")
    r.add_argument("source", nargs="?", default=None,
                   help=f"bag, TUM folder or synthetic spec (default: ${TUM_ENV}, else the shared fr1/rpy head)")
    r.add_argument("--config", default=None)
    r.add_argument("--max-frames", type=int, default=0)
    r.add_argument("--pairs", type=int, default=2)
    r.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE")
    for q in (m, r):
        q.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = p.parse_args(argv)
    if args.what == "run" and args.source is None:
        args.source = str(tum_path_or_exit(p, flag="SOURCE"))
    result = bench_map(args) if args.what == "map" else bench_run(args)
    if args.json is not None:
        write_results(args.json, result)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
