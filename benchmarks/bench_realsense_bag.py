"""Benchmark: a robot's own bag. A TUM folder rewritten in realsense-ros 4.x's layout (raw, and with
colour and depth compressed as image_transport writes them), each mapped with ``memgs run --bag``
and no topic flags, against the folder itself.

    python benchmarks/bench_realsense_bag.py [--tum DIR] [--config tum_fr1] [--out results/bench_realsense_bag.json]

Per source: its size on disk, the topics the reader chose, and the run (lockstep: the same work
for every source) scored by ``evaluate_run`` against the *folder's* images and ground truth: ATE
after one SE(3) alignment and PSNR of the final map at the tracked poses. A bag's depth is
millimetres (RealSense's 16UC1), the folder's 0.2 mm; compressed colour is JPEG at quality 95
(image_transport's default), depth PNG (lossless). Run nothing else on the machine meanwhile.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ (not a package): _common
from _common import ROOT, TUM_HELP, run_memgs, tum_path_or_exit, uptime, write_results  # noqa: E402

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _log(msg: str) -> None:
    print(f"[bench_realsense_bag {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
    return sum(f.stat().st_size for f in files) / 1e6


def make_bags(tum: Path, work: Path) -> dict[str, Path]:
    """The folder's frames as realsense-layout bags (raw and compressed), made once."""
    from memgs_ros.io.bag_writer import write_realsense_bag
    from memgs_ros.io.sources import open_source

    bags = {}
    for kind in ("raw", "compressed"):
        path = work / f"{tum.name}_realsense_{kind}"
        if not path.exists():
            _log(f"writing {path}")
            write_realsense_bag(open_source(tum), path, compressed=kind == "compressed")
        bags[kind] = path
    return bags


def run_one(label: str, source: Path, tum: Path, config: str, work: Path, timeout_s: float) -> dict[str, Any]:
    from memgs_ros.evaluation.runs import evaluate_run
    from memgs_ros.io.sources import open_source

    src = open_source(source)
    slug = "".join(c if c.isalnum() else "_" for c in label)
    out, log = work / slug, work / f"{slug}.log"
    _log(f"{label}: memgs run --bag {source} --config {config} -> {out}")
    run = run_memgs(["run", "--bag", source, "--config", config], out, log=log, timeout_s=timeout_s)
    if not run.ok or run.summary is None:
        raise SystemExit(f"{label}: memgs run failed (exit {run.returncode}); see {log}")
    r = evaluate_run(out, source=str(tum), use_lpips=False, progress=False)  # the folder's images and poses
    return {"label": label, "source": str(source), "size_mb": round(_size_mb(source), 1),
            "topics": getattr(src, "topic_choice", "") or "TUM layout", "frames": run.summary.frames,
            "poses": run.summary.poses, "gaussians": run.summary.gaussians, "wall_s": round(run.wall_s, 1),
            "ate_cm": round(100 * r.trajectory.rmse_m, 3) if r.trajectory else None,
            "psnr_db": round(r.frames_quality.psnr_db or 0.0, 2), "uptime_before": uptime()}


def table(rows: list[dict[str, Any]]) -> str:
    base = rows[0]
    lines = ["| source | size MB | topics chosen | poses | Gaussians | ATE cm | PSNR dB | vs folder: ATE cm / dB |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        topics = r["topics"].split(": ", 1)[-1]
        lines.append(f"| {r['label']} | {r['size_mb']:.1f} | {topics} | {r['poses']}/{r['frames']} "
                     f"| {r['gaussians']} | {r['ate_cm']:.2f} | {r['psnr_db']:.2f} "
                     f"| {r['ate_cm'] - base['ate_cm']:+.2f} / {r['psnr_db'] - base['psnr_db']:+.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tum", type=Path, default=None, help=TUM_HELP)
    ap.add_argument("--config", default="tum_fr1")
    ap.add_argument("--work", type=Path, default=ROOT / "results/realsense_bag", help="bags and run folders")
    ap.add_argument("--out", type=Path, default=ROOT / "results/bench_realsense_bag.json")
    ap.add_argument("--timeout", type=float, default=3600.0, help="per run (s)")
    args = ap.parse_args(argv)
    tum = tum_path_or_exit(ap, args.tum)
    args.work.mkdir(parents=True, exist_ok=True)
    bags = make_bags(tum, args.work)
    rows = [run_one("TUM folder", tum, tum, args.config, args.work, args.timeout)]
    for kind, path in bags.items():
        rows.append(run_one(f"realsense bag, {kind}", path, tum, args.config, args.work, args.timeout))
    ratio = rows[2]["size_mb"] / rows[1]["size_mb"]
    print(table(rows))
    print(f"\ncompressed / raw bag size: {ratio:.2f}")
    write_results(args.out, {"config": args.config, "tum": str(tum), "rows": rows, "compressed_size_ratio": ratio})
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
