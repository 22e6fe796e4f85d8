"""Benchmark: what ``--record`` adds to ``memgs demo`` (wall time, recorder CPU, file size).

Runs ``memgs demo`` (separate node processes over DDS, lockstep) ``--pairs`` times without and
with ``--record``, alternating which goes first in each pair so a drift in the machine's load
falls on both. Each run gets its own output folder. Reports per run the command's wall time
(what the user waits for, bag generation included), the run's own ``wall_s`` (summary.json:
graph start to saved map), the 1-minute load average before it, and for recorded runs the
recorder process's CPU time (from its shutdown line in ``logs/recorder.log``) and the mcap size,
and the CPU time of the whole command (demo and every node process: on a saturated shared machine
it drifts far less with the load than wall time does);
then medians, the ratio of the medians (with / without) and the median of the per-pair ratios.
JSON to ``--json``.

    python benchmarks/bench_record.py                 # 3 pairs on the default demo sequence
    python benchmarks/bench_record.py --pairs 5 --spec synthetic:w=320,h=240,n=30,seed=0
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

from _common import run_memgs, uptime, write_results

CPU_LINE = re.compile(r"cpu_s=([0-9.]+) startup_cpu_s=([0-9.]+)")


def run_demo(out: Path, spec: str, record: bool, timeout_s: float, extra: list[str]) -> dict[str, Any]:
    """One ``memgs demo`` in ``out``; its timings and, when recording, the recorder's figures."""
    # demo's own --timeout: a run that hangs fails and stops its nodes (a killed demo would not)
    args = ["demo", "--spec", spec, "--timeout", str(timeout_s), *extra]
    rec = out / "record.mcap"
    if record:
        args += ["--record", str(rec)]
    load = os.getloadavg()[0]
    run = run_memgs(args, out)  # its CPU: demo and every node it waited for
    if run.summary is None:
        raise SystemExit(f"memgs demo failed ({run.returncode}):\n{run.output[-3000:]}")
    s = run.summary
    row: dict[str, Any] = {"record": record, "command_wall_s": round(run.wall_s, 2), "run_wall_s": round(s.wall_s, 2),
                           "command_cpu_s": round(run.cpu_s, 2),
                           "load_1min_before": load, "frames": s.frames, "gaussians": s.gaussians}
    if record:
        m = CPU_LINE.search((out / "logs" / "recorder.log").read_text(errors="replace"))
        row.update(recorder_cpu_s=float(m.group(1)) if m else None,
                   recorder_startup_cpu_s=float(m.group(2)) if m else None, mcap_bytes=rec.stat().st_size)
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=3, help="runs without and with --record (default 3 each)")
    p.add_argument("--spec", default="synthetic:w=320,h=240,n=60,seed=0", help="demo sequence (memgs demo's default)")
    p.add_argument("--json", type=Path, default=Path("results/bench_record.json"))
    p.add_argument("--keep", action="store_true", help="keep the run folders (printed)")
    p.add_argument("--run-timeout", type=float, default=900.0, help="give up a run after this many seconds")
    p.add_argument("demo_args", nargs="*", help="more memgs demo arguments, after --")
    args = p.parse_args(argv)
    if args.pairs < 1:
        p.error("--pairs must be >= 1")
    uptime_before = uptime()
    print(f"machine: {os.cpu_count()} cores, {uptime_before}")
    root = Path(tempfile.mkdtemp(prefix="bench_record_"))
    rows: list[dict[str, Any]] = []
    try:
        for i in range(args.pairs):
            for record in ((False, True) if i % 2 == 0 else (True, False)):
                row = run_demo(root / f"{i}_{'rec' if record else 'plain'}", args.spec, record, args.run_timeout,
                               args.demo_args)
                rows.append(row)
                extra = (f", recorder cpu {row['recorder_cpu_s']:.2f} s (startup {row['recorder_startup_cpu_s']:.2f}),"
                         f" mcap {row['mcap_bytes'] / 1e6:.1f} MB") if record else ""
                print(f"pair {i} {'record' if record else 'plain '}: command {row['command_wall_s']:.1f} s "
                      f"(cpu {row['command_cpu_s']:.1f} s), "
                      f"run {row['run_wall_s']:.1f} s, load {row['load_1min_before']:.2f}{extra}", flush=True)
    finally:
        if args.keep:
            print(f"run folders in {root}")
        else:
            shutil.rmtree(root, ignore_errors=True)
    uptime_after = uptime()

    def med(key: str, record: bool) -> float:
        return statistics.median(r[key] for r in rows if r["record"] is record)

    result: dict[str, Any] = {"argv": sys.argv[1:], "spec": args.spec, "uptime_before": uptime_before,
                              "uptime_after": uptime_after, "runs": rows}
    for key in ("command_wall_s", "run_wall_s", "command_cpu_s"):
        plain, rec = med(key, False), med(key, True)
        # each pair ran back to back: its ratio is the least exposed to the load drifting
        pair_ratios = [b[key] / a[key] for a, b in (sorted(rows[i:i + 2], key=lambda r: r["record"])
                                                    for i in range(0, len(rows), 2))]
        result[key] = {"plain_median": plain, "record_median": rec, "ratio": rec / plain,
                       "pair_ratios": pair_ratios, "pair_ratio_median": statistics.median(pair_ratios)}
        print(f"{key:15s} median plain {plain:.1f} s, record {rec:.1f} s, ratio of medians {rec / plain:.3f}, "
              f"median pair ratio {statistics.median(pair_ratios):.3f} ({', '.join(f'{r:.3f}' for r in pair_ratios)})")
    recorded = [r for r in rows if r["record"]]
    result["recorder_cpu_s_median"] = statistics.median(r["recorder_cpu_s"] or 0.0 for r in recorded)
    result["mcap_bytes_median"] = statistics.median(r["mcap_bytes"] for r in recorded)
    print(f"recorder CPU median {result['recorder_cpu_s_median']:.2f} s, "
          f"mcap median {result['mcap_bytes_median'] / 1e6:.1f} MB")
    print(f"load after: {uptime_after}")
    write_results(args.json, result)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
