"""Benchmark: sustained load. A 30 Hz 640x480 RGB-D stream for minutes through the whole graph.

A synthetic sequence (``--unique`` frames, default 150 = 5 s) is written to an mcap bag and
the bag player loops it in real time (stamps keep increasing) for ``--seconds`` into the four
nodes, as separate processes over DDS (``memgs run --realtime`` with ``bag_player.loop``).
Camera input is best effort with a depth-5 queue, so a tracker slower than the camera drops
frames instead of queueing them. The run's 1 Hz node statistics (``stats_timeline.jsonl``)
give frames in/out/dropped and each node's resident memory over time. Memory is judged over
the streaming window after the warm-up (``--warmup-s``) up to the player's last frame (the
finish and final flush after it are not load): the median and peak RSS of its first and of its
last minute, and the least-squares slope in MB/min over the whole window. Nodes hand free heap
pages back every 30 s (``release_free_memory``), so the mapper's RSS is a sawtooth between its
working set (the floor just after a trim) and its training temporaries (the peaks); the floor
of each 30 s window and its slope say whether live memory grows.

Prints a table, writes JSON (default results/bench_load.json) and a PNG of memory and map
size over time next to it.

    python benchmarks/harness/bench_load.py                      # 300 s at 30 Hz, 640x480
    python benchmarks/harness/bench_load.py --seconds 60 --unique 60
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ (not a package): _common
from _common import write_results  # noqa: E402

NODES = ("tracker", "keyframe_sampler", "mapper", "merger")


def _num(row: dict, key: str) -> float:
    try:
        return float(row.get(key, "nan"))
    except ValueError:
        return float("nan")


def _stream_end_s(timeline: list[dict]) -> float:
    """When the player published its last frame (the first stats row showing the final count)."""
    rows = [r for r in timeline if r["node"] == "player" and _num(r, "frames_published") >= 0]
    if not rows:  # NaN (a row without the counter) fails the comparison and is left out
        return max(r["t_s"] for r in timeline)
    final = max(_num(r, "frames_published") for r in rows)
    return min(r["t_s"] for r in rows if _num(r, "frames_published") == final)


def memory_trend(rows: list[dict], t0: float, t1: float, window_s: float = 60.0) -> dict:
    """RSS over [t0, t1]: median and peak of its first and last ``window_s``, slope in MB/min."""
    import numpy as np

    pts = [(r["t_s"], _num(r, "rss_mb")) for r in rows if t0 <= r["t_s"] <= t1]
    if len(pts) < 3:
        return {}
    t, m = np.array(pts).T
    first, last = m[t <= t0 + window_s], m[t >= t1 - window_s]
    slope = float(np.polyfit(t / 60.0, m, 1)[0])
    # Floors: the lowest sample of each 30 s (trim period) window.
    edges = np.arange(t0, t1 - 30.0 + 1e-9, 30.0)  # whole windows only: each holds one trim
    floors = [(a + 15.0, m[(t >= a) & (t < a + 30.0)].min()) for a in edges if ((t >= a) & (t < a + 30.0)).any()]
    if not floors:  # a window shorter than one trim period: its lowest sample stands in
        floors = [(float(t[np.argmin(m)]), float(m.min()))]
    ft, fm = np.array(floors).T
    floor_slope = float(np.polyfit(ft / 60.0, fm, 1)[0]) if len(floors) >= 2 else 0.0
    return {"first_min_median": float(np.median(first)), "first_min_peak": float(first.max()),
            "last_min_median": float(np.median(last)), "last_min_peak": float(last.max()),
            "slope_mb_per_min": slope, "floors_mb": [round(float(x), 1) for x in fm],
            "floor_slope_mb_per_min": floor_slope, "window_s": [float(t0), float(t1)]}


def summarise(timeline: list[dict], warmup_s: float) -> dict:
    """Per node: RSS at start / end of warm-up / end / peak, the post-warm-up trend while
    streaming (``memory_trend``), and the counters' last values."""
    out: dict = {}
    stream_end = _stream_end_s(timeline) if timeline else 0.0
    for node in (*NODES, "player"):
        rows = [r for r in timeline if r["node"] == node]
        if not rows:
            continue
        after = [r for r in rows if r["t_s"] >= rows[0]["t_s"] + warmup_s] or rows[-1:]
        rss = [_num(r, "rss_mb") for r in rows]
        out[node] = {
            "samples": len(rows), "t_first_s": rows[0]["t_s"], "t_last_s": rows[-1]["t_s"],
            "rss_mb_start": _num(rows[0], "rss_mb"), "rss_mb_after_warmup": _num(after[0], "rss_mb"),
            "rss_mb_end": _num(rows[-1], "rss_mb"), "rss_mb_max": max(rss),
            "trend": memory_trend(rows, rows[0]["t_s"] + warmup_s, stream_end),
            "last": {k: v for k, v in rows[-1].items() if k not in ("node",)},
            "after_warmup": {k: v for k, v in after[0].items() if k not in ("node",)},
        }
    return out


def _orphans(domain_id: int) -> list[int]:
    """Pids of memgs node processes still running with this run's ROS_DOMAIN_ID (Linux /proc)."""
    left = []
    for pid in (int(d) for d in os.listdir("/proc") if d.isdigit()):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
            env = Path(f"/proc/{pid}/environ").read_bytes()
        except OSError:
            continue
        if b"memgs_ros.nodes." in cmd and f"ROS_DOMAIN_ID={domain_id}\0".encode() in env + b"\0":
            left.append(pid)
    return left


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=300.0, help="stream length (s of camera time)")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--unique", type=int, default=150, help="distinct frames in the looped bag")
    p.add_argument("--warmup-s", type=float, default=120.0,
                   help="memory growth is measured after this (the map fills its budget first)")
    p.add_argument("--config", default="synthetic")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE")
    p.add_argument("--out", type=Path, default=Path("results/bench_load.json"))
    p.add_argument("--keep", type=Path, default=None, help="keep the run folder here (default: temporary)")
    args = p.parse_args(argv)

    import yaml

    from memgs_ros.core.runtime.replay import Pacing
    from memgs_ros.io.bag_writer import write_bag
    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.orchestration.pipeline import RunOptions, run_pipeline
    from memgs_ros.orchestration.run_files import read_stats_timeline

    tmp = tempfile.TemporaryDirectory(prefix="memgs_load_")
    work = args.keep or Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    bag = Path(tmp.name) / "loop.mcap"
    spec = f"synthetic:w={args.width},h={args.height},n={args.unique},fps={args.fps:g},seed=0"
    t0 = time.perf_counter()
    write_bag(generate_frames(parse_spec(spec)), bag)
    print(f"bag {spec}: {bag.stat().st_size / 1e6:.0f} MB in {time.perf_counter() - t0:.0f} s", flush=True)
    n_frames = int(round(args.seconds * args.fps))
    overrides = {"bag_player.loop": True}
    for item in args.set:
        key, _, value = item.partition("=")
        overrides[key.strip()] = yaml.safe_load(value)
    load0 = os.getloadavg()[0]
    t1 = time.perf_counter()
    s = run_pipeline(RunOptions(source=str(bag), config=args.config, out_dir=work / "run", pacing=Pacing.LIVE,
                                max_frames=n_frames, overrides=overrides,
                                timeout_s=args.seconds * 4 + 900), progress=True)
    wall = time.perf_counter() - t1
    timeline = read_stats_timeline(work / "run")
    nodes = summarise(timeline, args.warmup_s)
    tr = nodes.get("tracker", {}).get("last", {})
    player = nodes.get("player", {}).get("last", {})
    published = int(_num(player, "frames_published")) if player else n_frames
    frames_in = s.frames
    result = {
        "spec": spec, "seconds": args.seconds, "fps": args.fps, "frames_published": published,
        "frames_tracked": frames_in, "frames_dropped_before_tracker": published - frames_in,
        "dropped_fraction": (published - frames_in) / max(published, 1),
        "tracker_stamp_drops": {k: v for k, v in tr.items() if k.startswith("problem.")},
        "poses": s.poses, "lost": s.lost_frames, "keyframes": s.keyframes, "gaussians": s.gaussians,
        "gaussians_peak": s.gaussians_peak, "mapping_iterations": s.mapping_iterations, "wall_s": wall,
        "delta_kbytes_per_s": s.delta_bytes_per_s / 1e3, "replica_identical": s.replica_identical,
        "nodes": nodes, "loadavg_before": load0, "loadavg_after": os.getloadavg()[0],
    }
    print(f"\nframes published {published}, tracked {frames_in}, dropped before the tracker "
          f"{published - frames_in} ({100 * result['dropped_fraction']:.1f} %), poses {s.poses}, lost {s.lost_frames}")
    mp = nodes.get("mapper", {}).get("last", {})
    result["mapper_keyframes"] = {k: mp.get(k) for k in ("keyframes", "problem.keyframe_overload", "keyframes_missed",
                                                         "dropped_keyframe_bundles", "keyframes_trained",
                                                         "keyframes_dropped")}
    print(f"tracker keyframes {s.keyframes}: mapper inserted {mp.get('keyframes')}, dropped from its full insert "
          f"queue {mp.get('problem.keyframe_overload', 0)}, missed {mp.get('keyframes_missed', 0)}, incomplete "
          f"bundles dropped {mp.get('dropped_keyframe_bundles')}")
    acc = [_num(r, "accounted_bytes") for r in timeline if r["node"] == "mapper" and "accounted_bytes" in r]
    cap = next((float(v.split("=", 1)[1]) for v in args.set if v.startswith("mapper.mapping.max_mapper_mbytes=")), 0.0)
    result["mapper_accounted_mb_max"] = max(acc) / 2**20 if acc else None
    result["mapper_max_mapper_mbytes"] = cap
    if acc:
        print(f"mapper accounted memory (model + keyframes + step buffers + delta): max {max(acc) / 2**20:.1f} MiB, "
              f"end {acc[-1] / 2**20:.1f} MiB (cap {cap:g} MiB; 0 = none), keyframes trained at the end "
              f"{mp.get('keyframes_trained')}, dropped {mp.get('keyframes_dropped')}")
    result["tracker_map"] = {k: tr.get(k) for k in ("map_keyframes", "map_points", "map_keyframes_removed")}
    print(f"tracker sparse map at the end: {tr.get('map_keyframes')} keyframes, {tr.get('map_points')} points, "
          f"{tr.get('map_keyframes_removed')} keyframes removed by its cap")
    print(f"keyframes {s.keyframes}, Gaussians {s.gaussians} (peak {s.gaussians_peak}), "
          f"deltas {result['delta_kbytes_per_s']:.0f} kB/s, merger == mapper: {s.replica_identical}")
    print(f"RSS MB; first / last minute of streaming after the {args.warmup_s:.0f} s warm-up: median (peak)")
    print(f"{'node':18s} {'start':>6s} {'first minute':>14s} {'last minute':>14s} {'slope MB/min':>13s} "
          f"{'30 s floors first/last':>23s} {'floor slope':>12s}")
    for node in NODES:
        n = nodes.get(node)
        tr_ = n.get("trend") if n else None
        if tr_:
            print(f"{node:18s} {n['rss_mb_start']:6.0f} {tr_['first_min_median']:7.0f} ({tr_['first_min_peak']:4.0f}) "
                  f"{tr_['last_min_median']:7.0f} ({tr_['last_min_peak']:4.0f}) {tr_['slope_mb_per_min']:+13.1f} "
                  f"{tr_['floors_mb'][0]:11.0f} / {tr_['floors_mb'][-1]:<9.0f} {tr_['floor_slope_mb_per_min']:+12.1f}")
    print(f"wall {wall:.0f} s, load {load0:.1f} -> {result['loadavg_after']:.1f}")
    # The three sustained-load checks: keyframes the tracker made that the mapper never trained,
    # the mapper's live memory trend, and node processes of this run still alive after it.
    made = max(int(s.keyframes), 1)
    lost_kf = sum(int(_num(mp, k)) if k in mp else 0 for k in ("problem.keyframe_overload", "keyframes_missed",
                                                                  "dropped_keyframe_bundles"))
    floor_slope = (nodes.get("mapper", {}).get("trend") or {}).get("floor_slope_mb_per_min")
    orphans = _orphans(s.domain_id)
    result["checks"] = {"keyframes_dropped": lost_kf, "keyframes_dropped_fraction": lost_kf / made,
                        "mapper_floor_slope_mb_per_min": floor_slope, "orphans": orphans}
    slope_txt = "n/a" if floor_slope is None else f"{floor_slope:+.2f}"
    print(f"checks: keyframes dropped {lost_kf} of {made} ({100 * lost_kf / made:.2f} %, <= 1 %); mapper RSS floor "
          f"slope {slope_txt} MB/min (<= 1); node processes left behind {len(orphans)} (0)")
    # The figure and its table are made together from this JSON (tools/make_figures.py load):
    # keep the per-node RSS and the mapper's size over time, and the command.
    argv_used = argv if argv is not None else sys.argv[1:]
    result["command"] = " ".join(["python benchmarks/harness/bench_load.py", *argv_used])
    result["timeline"] = [{k: r[k] for k in ("t_s", "node", "rss_mb", "gaussians", "keyframes") if k in r}
                          for r in timeline]
    write_results(args.out, result)
    print(f"wrote {args.out}; figure and table: python tools/make_figures.py load {args.out} "
          "--name load_30hz_640x480 --readme docs/results.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
