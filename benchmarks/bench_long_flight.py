"""Benchmark: a long flight over one room, live and in lockstep: does the map grow with the room or the flight?

    python benchmarks/bench_long_flight.py [--tum DIR] [--repeat 5] [--modes live lockstep] [--runs 3]
    python benchmarks/bench_long_flight.py --source synthetic:w=320,h=240,path=orbit,n=450,laps=40 \\
        --config synthetic --modes live --flat-window-s 480 --no-psnr      # the 10-minute orbit
    python benchmarks/bench_long_flight.py --table results/bench_long_flight.json   # the README's table

Each run is a real ``memgs run`` (node processes over DDS) of the source played ``--repeat`` times,
forward then backward (``--repeat``; ground truth carried), or of a source that is long already
(``--passes P`` names how many passes it holds, for the per-pass figures): ``live`` plays it on its
own clock at ``--rate`` (nobody waits; the player preloads the frames, as a camera driver hands
over decoded images), ``lockstep`` waits for every node at every frame. ``--checkout DIR`` runs
another tree's ``memgs_ros`` (a worktree of an earlier commit: an A/B in one session; a tree
without ``--repeat`` is given a source that holds its passes, with ``--passes``).

Per run, from the run's own files (summary.json, stats_timeline.jsonl, trajectory.txt):

- frames played, tracked (poses), lost; tracker keyframes (inserted, kept after culling);
- Gaussians at the end and at their peak; the mapper's and merger's peak RSS, every node's;
- the timeline (1 Hz): Gaussians, model MB, tracker keyframes and map points, mapper keyframes,
  every node's RSS, CUDA memory where present, tracker ms a frame, mapper iterations/s, merges;
- the growth of Gaussians and of every node's RSS over the flight's last ``--flat-window-s``;
- the keyframe latency (tracker's decision to the mapper's first training step: median, p95);
- ATE after one SE(3) alignment over the whole flight, and per pass;
- PSNR of the final map at the tracked poses (``evaluate_run``; ``--no-psnr`` skips it).

Writes the JSON (``--out``), a PNG of the timelines beside it, and prints the table. Run nothing
else on the machine meanwhile (one benchmark at a time: CPU time rises with contention).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ (not a package): _common
from _common import ROOT, TUM_HELP, run_memgs, tum_path_or_exit, uptime, write_results  # noqa: E402

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from memgs_ros.evaluation.timeline import finite_number  # noqa: E402 - no torch: the table reads JSON only

NODES = ("tracker", "keyframe_sampler", "mapper", "merger", "player")


def _log(msg: str) -> None:
    print(f"[bench_long_flight {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def timeline_series(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, list[float]]]:
    """{node: {"t_s": [...], key: [...]}} of the numeric stats each node sent (1 Hz), in order."""
    out: dict[str, dict[str, list[float]]] = {}
    for row in rows:
        node = str(row["node"])
        series = out.setdefault(node, {"t_s": []})
        n = len(series["t_s"])
        series["t_s"].append(float(row["t_s"]))
        for key, value in row.items():
            if key in ("t_s", "node"):
                continue
            v = finite_number(value)
            if v is None:
                continue
            col = series.setdefault(key, [float("nan")] * n)
            col.extend([float("nan")] * (n - len(col)))
            col.append(v)
    for series in out.values():  # pad keys a later row did not carry
        n = len(series["t_s"])
        for col in series.values():
            col.extend([float("nan")] * (n - len(col)))
    return out


def _at(series: Mapping[str, list[float]], key: str, t: float) -> float | None:
    """The last value of ``key`` at or before ``t`` (s), None when there is none."""
    ts, vs = series.get("t_s", []), series.get(key, [])
    best = None
    for ti, vi in zip(ts, vs):
        if ti <= t and np.isfinite(vi):
            best = vi
    return best


def _max(series: Mapping[str, list[float]], key: str, t0: float = -np.inf, t1: float = np.inf) -> float | None:
    vals = [v for t, v in zip(series.get("t_s", []), series.get(key, [])) if t0 <= t <= t1 and np.isfinite(v)]
    return max(vals) if vals else None


def flight_window(series: Mapping[str, Mapping[str, list[float]]]) -> tuple[float, float]:
    """(start, end) in run seconds of the flight: the player's first to its last published frame."""
    player = series.get("player", {})
    pub = [(t, v) for t, v in zip(player.get("t_s", []), player.get("frames_published", [])) if np.isfinite(v)]
    moving = [t for t, v in pub if v > 0]
    if not moving:
        return 0.0, max((max(s["t_s"]) for s in series.values() if s["t_s"]), default=0.0)
    final = max(v for _, v in pub)
    end = min(t for t, v in pub if v >= final)
    return min(moving), end


def growth(series: Mapping[str, list[float]], key: str, t_from: float, t_to: float) -> float | None:
    """Relative change of ``key`` between two run times (None without values there)."""
    a, b = _at(series, key, t_from), _at(series, key, t_to)
    if a is None or b is None or a <= 0:
        return None
    return (b - a) / a


def pass_ate(out: Path, source: str, repeat: int, passes: int, forward_only: bool = False) -> dict[str, Any]:
    """ATE of trajectory.txt after one SE(3) alignment over the whole flight, and per pass (a
    source played with ``repeat``, or one that holds ``passes`` back-and-forth passes itself)."""
    from memgs_ros.core.metrics.trajectory import ate
    from memgs_ros.io.repeat import RepeatClock, RepeatedSource
    from memgs_ros.io.sources import open_source
    from memgs_ros.io.tum import read_trajectory

    src = open_source(source, repeat=repeat, repeat_forward=forward_only)
    gt_s, gt_T = src.ground_truth()
    est_s, est_T = read_trajectory(out / "trajectory.txt")
    res = ate(est_s, est_T, gt_s, gt_T)
    if isinstance(src, RepeatedSource):
        clock = src.clock
    else:
        stamps = np.asarray(src.frame_stamps(), np.int64)  # type: ignore[attr-defined]
        clock = RepeatClock(int(stamps[0]), int(stamps[0]) + int(stamps[-1] - stamps[0]) // max(passes, 1), passes)
    which = clock.pass_of(res.stamps_ns)
    per_pass = []
    for p in range(passes):
        e = res.errors_m[which == p]
        per_pass.append(float(np.sqrt(np.mean(e ** 2))) * 100 if len(e) else None)
    return {"ate_cm": res.rmse_m * 100, "ate_pass_cm": per_pass, "rotation_deg": res.rotation_rmse_deg,
            "matched": res.n_matched}


def analyse(out: Path, source: str, repeat: int, passes: int, flat_window_s: float, psnr: bool,
            forward_only: bool = False) -> dict[str, Any]:
    """Every figure of one finished run (module docstring)."""
    from memgs_ros.orchestration.run_files import read_stats_timeline, read_summary

    s = read_summary(out)
    series = timeline_series(read_stats_timeline(out))
    t0, t1 = flight_window(series)
    tracker, mapper = series.get("tracker", {}), series.get("mapper", {})
    row: dict[str, Any] = {
        "frames_played": s.frames_played, "frames_in": s.frames, "poses": s.poses, "lost": s.lost_frames,
        "tracked_fraction": s.poses / s.frames_played if s.frames_played else None,
        "tracker_skipped": s.tracker_skipped,
        "keyframes": s.keyframes, "map_keyframes_end": _at(tracker, "map_keyframes", t1),
        "map_keyframes_removed": _max(tracker, "map_keyframes_removed"),
        "gaussians": s.gaussians, "gaussians_peak": s.gaussians_peak,
        "gaussians_flight_end": _at(mapper, "gaussians", t1),
        "gaussians_flight_peak": _max(mapper, "gaussians", t0, t1),
        "peak_rss_mb": dict(s.peak_rss_mb),
        "flight_peak_rss_mb": {n: _max(series.get(n, {}), "peak_rss_mb", t0, t1) for n in NODES},
        "keyframe_latency_ms": dict(s.keyframe_latency_ms), "keyframe_intake_ms": dict(s.keyframe_intake_ms),
        "iterations_flight": s.mapping_iterations_replay, "iterations_final": s.mapping_iterations_final,
        "merged_removed_flight": _at(mapper, "merged_removed", t1),
        "merge_passes_flight": _at(mapper, "merge_passes", t1),
        "seeded_gaussians": _at(mapper, "seeded_gaussians", t1),
        "seeds_skipped": _at(mapper, "seeds_covered", t1),
        "cuda_peak_mb": s.cuda_peak_mb, "wall_s": s.wall_s, "flight_s": t1 - t0, "cpu_s": dict(s.cpu_s),
        "tracker_frame_cpu_ms": s.tracker_frame_cpu_ms,
    }
    if flat_window_s > 0 and t1 - t0 > flat_window_s:
        t_from = t1 - flat_window_s
        row["flat_window_s"] = flat_window_s
        row["growth_gaussians"] = growth(mapper, "gaussians", t_from, t1)
        row["growth_rss"] = {n: growth(series.get(n, {}), "rss_mb", t_from, t1) for n in NODES}
        row["growth_map_keyframes"] = growth(tracker, "map_keyframes", t_from, t1)
    try:
        row.update(pass_ate(out, source, repeat, passes, forward_only))
    except Exception as err:  # noqa: BLE001 - a run without a trajectory still has its other figures
        row["ate_error"] = str(err)
    if psnr:
        from memgs_ros.evaluation.runs import evaluate_run

        r = evaluate_run(out, use_lpips=False, progress=False)
        row["psnr_db"] = r.frames_quality.psnr_db
        row["psnr_kf_db"] = r.keyframes_quality.psnr_db
    row["timeline"] = {n: {k: v for k, v in series.get(n, {}).items() if k in _PLOTTED or k == "t_s"}
                       for n in NODES}
    row["flight_window_s"] = [t0, t1]
    return row


_PLOTTED = {"gaussians", "model_bytes", "keyframes", "map_keyframes", "map_points", "keyframes_trained",
            "rss_mb", "cuda_max_allocated", "track_ms", "frame_cpu_ms_median", "iterations_per_s", "iteration",
            "merged_removed", "merge_passes", "frames_published"}


def _label(result: Mapping[str, Any], mode: str) -> str:
    return f"{result['label']} {mode}" if result.get("label") else mode


def plot(results: Sequence[Mapping[str, Any]], path: Path, metadata: Mapping[str, str] | None = None) -> Path:
    """The timelines of every run of ``results`` (one colour per result and mode; time since the
    flight's first frame) and the median ATE per pass, as a PNG (``metadata``: its text chunks)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    panels = [
        (axes[0, 0], "mapper", "gaussians", 1e-3, "Gaussians (thousands)"),
        (axes[0, 1], "tracker", "map_keyframes", 1.0, "tracker keyframes kept"),
        (axes[0, 2], "mapper", "iteration", 1.0, "mapper iterations"),
        (axes[1, 0], "mapper", "rss_mb", 1.0, "mapper RSS (MB)"),
        (axes[1, 1], "merger", "rss_mb", 1.0, "merger RSS (MB)"),
    ]
    series = [(_label(r, mode), runs) for r in results for mode, runs in r["modes"].items()]
    for c, (name, runs) in enumerate(series):
        for i, run in enumerate(runs):
            for ax, node, key, scale, label in panels:
                tl = run["timeline"].get(node, {})
                t, v = np.asarray(tl.get("t_s", [])), np.asarray(tl.get(key, []), float)
                if len(t) and len(v) == len(t):
                    ax.plot(t - run["flight_window_s"][0], v * scale, label=name if i == 0 else None,
                            color=f"C{c}", alpha=0.8)
                ax.set_xlabel("time since the first frame (s)")
                ax.set_ylabel(label)
    ax = axes[1, 2]
    width = 0.8 / max(len(series), 1)
    for c, (name, runs) in enumerate(series):
        passes = [r.get("ate_pass_cm") or [] for r in runs]
        if passes and passes[0]:
            med = [statistics.median([p[j] for p in passes if p[j] is not None] or [np.nan])
                   for j in range(len(passes[0]))]
            ax.bar(np.arange(1, len(med) + 1) + (c - (len(series) - 1) / 2) * width, med, width=width,
                   label=name, color=f"C{c}")
    ax.set_xlabel("pass")
    ax.set_ylabel("ATE (cm), one alignment over the flight")
    for a in axes.flat:
        a.grid(alpha=0.3)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=8)
    first = results[0]
    fig.suptitle(f"{Path(first['source']).name} x{first['passes']} ({first['config']})")
    fig.tight_layout()
    fig.savefig(path, dpi=80, metadata=dict(metadata or {}))
    plt.close(fig)
    return path


def _med(runs: Sequence[Mapping[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in runs if isinstance(r.get(key), (int, float))]
    return statistics.median(vals) if vals else None


def summary_row(runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The medians over a mode's runs of the figures the table shows."""
    row = {k: _med(runs, k) for k in ("tracked_fraction", "keyframes", "map_keyframes_end", "gaussians",
                                      "gaussians_flight_peak", "gaussians_peak", "ate_cm", "psnr_db",
                                      "iterations_flight", "growth_gaussians", "lost")}
    for node in ("mapper", "merger", "tracker", "keyframe_sampler", "player"):  # over the flight
        vals = [r["flight_peak_rss_mb"].get(node) for r in runs if r["flight_peak_rss_mb"].get(node) is not None]
        row[f"rss_{node}"] = statistics.median(vals) if vals else None
    lat = [r["keyframe_latency_ms"].get("median") for r in runs if r["keyframe_latency_ms"].get("median") is not None]
    row["latency_ms"] = statistics.median(lat) if lat else None
    passes = [r.get("ate_pass_cm") or [] for r in runs]
    if passes and passes[0]:
        row["ate_pass_cm"] = [statistics.median([p[j] for p in passes if p[j] is not None] or [float("nan")])
                              for j in range(len(passes[0]))]
    return row


def table(results: Sequence[Mapping[str, Any]]) -> str:
    def f(v: Any, fmt: str = "{:.2f}") -> str:
        return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else fmt.format(v)

    lines = ["| mode | runs | tracked | tracker KF (kept) | Gaussians end (flight peak) | ATE cm | ATE per pass cm | "
             "PSNR dB | KF latency s | mapper / merger RSS MB, flight peak | iterations in flight |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for mode, runs in ((_label(res, m), runs) for res in results for m, runs in res["modes"].items()):
        r = summary_row(runs)
        per = " / ".join(f(v, "{:.1f}") for v in r.get("ate_pass_cm", []))
        lines.append(
            f"| {mode} | {len(runs)} | {f(r['tracked_fraction'] and 100 * r['tracked_fraction'], '{:.1f} %')} | "
            f"{f(r['keyframes'], '{:.0f}')} ({f(r['map_keyframes_end'], '{:.0f}')}) | "
            f"{f(r['gaussians'] and r['gaussians'] / 1e3, '{:.1f}k')} "
            f"({f(r['gaussians_flight_peak'] and r['gaussians_flight_peak'] / 1e3, '{:.1f}k')}) | "
            f"{f(r['ate_cm'])} | {per} | {f(r['psnr_db'])} | "
            f"{f(r['latency_ms'] and r['latency_ms'] / 1e3, '{:.1f}')} | "
            f"{f(r['rss_mapper'], '{:.0f}')} / {f(r['rss_merger'], '{:.0f}')} | "
            f"{f(r['iterations_flight'], '{:.0f}')} |")
    return "\n".join(lines)


def run_mode(mode: str, args: argparse.Namespace, source: str, out: Path) -> dict[str, Any]:
    words = ["run", "--bag", source, "--config", args.config]
    if args.repeat > 1:
        words += ["--repeat", str(args.repeat)] + (["--repeat-forward"] if args.repeat_forward else [])
    if mode == "live":
        words += ["--realtime", "--rate", str(args.rate), "--set", f"bag_player.preload_mb={args.preload_mb}"]
    for item in args.set:
        words += ["--set", item]
    _log(f"{mode}: memgs {' '.join(words)} -> {out}")
    out.parent.mkdir(parents=True, exist_ok=True)
    run = run_memgs(words, out, log=out.parent / f"{out.name}.log", timeout_s=args.timeout, checkout=args.checkout)
    if not run.ok:
        raise SystemExit(f"{mode} run failed (exit {run.returncode}); see {out.parent / (out.name + '.log')}")
    _log(f"{mode}: done in {run.wall_s:.0f} s; analysing")
    row = analyse(out, source, args.repeat, args.passes or args.repeat, args.flat_window_s, not args.no_psnr,
                  args.repeat_forward)
    row["uptime_before"] = args.uptime_before
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tum", type=Path, default=None, help=TUM_HELP)
    ap.add_argument("--source", default=None, help="any source instead of the TUM folder (a bag, 'synthetic:...')")
    ap.add_argument("--config", default="tum_fr1")
    ap.add_argument("--repeat", type=int, default=5, help="passes, forward and back (memgs run --repeat)")
    ap.add_argument("--repeat-forward", action="store_true",
                    help="every pass forward, jumping back between them (memgs run --repeat-forward)")
    ap.add_argument("--passes", type=int, default=0, help="passes the source already holds (with --repeat 1)")
    ap.add_argument("--modes", nargs="+", default=["live", "lockstep"], choices=["live", "lockstep"])
    ap.add_argument("--runs", type=int, default=1, help="runs per mode (the table shows medians)")
    ap.add_argument("--rate", type=float, default=1.0, help="live: real-time factor")
    ap.add_argument("--preload-mb", type=int, default=4096, help="live: the player's preload_mb")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", help="passed to memgs run")
    ap.add_argument("--flat-window-s", type=float, default=0.0,
                    help="report the growth of Gaussians and RSS over the flight's last this many seconds")
    ap.add_argument("--no-psnr", action="store_true", help="skip rendering the final map at the tracked poses")
    ap.add_argument("--checkout", type=Path, default=ROOT, help="the tree whose memgs_ros runs (A/B)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="per run (s)")
    ap.add_argument("--work", type=Path, default=ROOT / "results/long_flight", help="run folders go here")
    ap.add_argument("--out", type=Path, default=ROOT / "results/bench_long_flight.json")
    ap.add_argument("--table", type=Path, nargs="+", default=None, metavar="JSON",
                    help="print the table of saved runs (several: a row each, by their labels) and exit")
    ap.add_argument("--figure", type=Path, default=None, metavar="PNG",
                    help="with --table: also draw the saved runs' timelines into this PNG")
    ap.add_argument("--label", default="", help="the runs' name in tables and figures (e.g. the commit)")
    args = ap.parse_args(argv)
    if args.table is not None:
        import json

        saved = [json.loads(p.read_text()) for p in args.table]
        print(table(saved))
        if args.figure is not None:
            print(plot(saved, args.figure))
        return 0
    source = args.source if args.source else str(tum_path_or_exit(ap, args.tum))
    result: dict[str, Any] = {"label": args.label, "source": source, "repeat": args.repeat,
                              "repeat_forward": args.repeat_forward,
                              "passes": args.passes or args.repeat,
                              "config": args.config, "checkout": str(args.checkout), "sets": args.set,
                              "rate": args.rate, "modes": {}}
    for mode in args.modes:
        runs = []
        for i in range(args.runs):
            args.uptime_before = uptime()
            out = args.work / f"{mode}{i}"
            if out.exists():
                import shutil

                shutil.rmtree(out)
            runs.append(run_mode(mode, args, source, out))
            result["modes"][mode] = runs
            write_results(args.out, result)  # what finished so far survives a later failure
    png = plot([result], args.out.with_suffix(".png"))
    write_results(args.out, result)
    print(table([result]))
    print(f"\n{args.out}\n{png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
