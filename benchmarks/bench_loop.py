"""Benchmark loop closure on the synthetic loop sequence: trajectory and map, with and without.

    python benchmarks/bench_loop.py [--runs 3] [--spec SPEC] [--n-features 300] [--iterations 600]
        [--rate 0] [--out results/bench_loop.json]

Sequence: ``synthetic:w=320,h=240,n=240,path=loop,noise=0.01,holes=0.05`` (once round the room,
11 m, then back over the start views), tracked with a low feature budget (300 ORB features) so
the uncorrected tracker drifts. Each run tracks the sequence twice, ``loop_closure`` on and off
(threads as in the live system, so runs differ: medians over ``--runs``). Frames go in back to
back (``--rate 0``: the back-end lags furthest behind) or at ``--rate`` times the camera's rate
(1: as a live camera delivers them).

Trajectory numbers use the corrected trajectory (every frame re-expressed relative to its
reference keyframe after BA and loop corrections: what ``memgs/path`` and ``trajectory.txt``
hold): ATE RMSE (SE(3)-aligned), drift at the revisit = median position error of the frames that
return to the start views (the tracker's world is the first camera's, so no alignment),
loops detected (consistent candidates) / accepted (verified and committed), pose-graph time, and
the CPU time of ``track()`` (median / p95, thread time).

Map: a Gaussian map trained offline (GaussianMapper, ``--iterations`` steps at half resolution)
on the tracker's keyframes at their final poses, seeded from their depth; PSNR of renders at the
tracked poses of the revisit frames against the ground-truth images. Without loop closure the
revisit keyframes sit where the drift put them, so the start region is mapped twice, offset.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

from _common import write_results

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

from memgs_ros.core.metrics.trajectory import ate, path_length_m
from memgs_ros.core.tracking import TrackerConfig, make_tracker
from memgs_ros.core.tracking.anchored_path import AnchoredPath
from memgs_ros.io.synthetic import generate_frames, loop_revisit_frames, parse_spec

DEFAULT_SPEC = "synthetic:w=320,h=240,n=240,path=loop,noise=0.01,holes=0.05"


def track(frames: list, camera: object, cfg: TrackerConfig, rate: float = 0.0) -> dict:
    """Track every frame (``rate`` > 0: not before its stamp, replayed at that rate); the corrected
    trajectory, keyframe poses and the loop counters."""
    tracker = make_tracker(cfg, camera)
    path = AnchoredPath()
    cpu, kf_stamps = [], {}
    t_start = time.perf_counter()
    for f in frames:
        if rate > 0:
            time.sleep(max(0.0, t_start + (f.stamp_ns - frames[0].stamp_ns) * 1e-9 / rate - time.perf_counter()))
        c0 = time.thread_time()
        res = tracker.track(f)
        cpu.append(time.thread_time() - c0)
        path.update(res, tracker.poll_loop_corrections())
        if res.keyframe is not None:
            kf_stamps[res.keyframe.keyframe_id] = f.stamp_ns
    tracker.wait_for_ba()
    tracker.wait_for_loop_closing()
    for c in tracker.poll_loop_corrections():
        path.correct(c)
    kf_T = {kf_stamps[k]: tracker.map.keyframes[k].T_wc for k in kf_stamps if k in tracker.map.keyframes}
    st = tracker.loop_stats
    tracker.close()
    stamps, T_wc = path.poses()
    return {"stamps": stamps, "T_wc": T_wc, "kf_poses": kf_T, "cpu": np.array(cpu),
            "loops_detected": st.loops_detected, "loops_accepted": st.loops_accepted,
            "loops_rejected": st.loops_rejected, "pose_graph_time_s": st.pose_graph_time_s,
            "global_ba_runs": st.global_ba_runs, "global_ba_time_s": st.global_ba_time_s}


def map_psnr(frames: list, kf_poses: dict, T_first: np.ndarray, eval_idx: np.ndarray, eval_T: np.ndarray,
             iterations: int) -> float:
    """Mean PSNR (dB) at frames ``eval_idx`` rendered at ``eval_T`` [K, 4, 4] (tracker world) from a
    map trained on the keyframes at ``kf_poses`` ({stamp: T_wc in the tracker world})."""
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_mapping import PRESETS, grid_seeds, psnr_of

    from memgs_ros.core.mapping.mapper import GaussianMapper, MappingConfig

    cfg = MappingConfig(min_keyframes=1, resolution_scale=0.5, densify_start_iter=iterations // 4,
                        densify_stop_iter=int(0.7 * iterations), merge_enabled=False,
                        sh_up_interval=max(1, iterations // 4), pyramid_uses_per_level=2, seed=0,
                        **PRESETS["cpu"])
    mapper = GaussianMapper(cfg, device="cpu")
    by_stamp = {f.stamp_ns: f for f in frames}
    for i, (stamp, T) in enumerate(sorted(kf_poses.items())):
        f = replace(by_stamp[stamp], T_wc_gt=T)
        p, c = grid_seeds(f, 6, 0.5)
        mapper.add_keyframe(i, f.stamp_ns, T, f.rgb, f.depth_m, f.camera, p, c)
    mapper.train(iterations, progress=False)
    return float(np.mean([psnr_of(mapper, replace(frames[k], T_wc_gt=T), 0.5)[0]
                          for k, T in zip(eval_idx.tolist(), eval_T)]))


def evaluate(frames: list, spec: object, out: dict, with_map: bool, iterations: int) -> dict:
    gt_st = np.array([f.stamp_ns for f in frames])
    gt_T = np.array([f.T_wc_gt for f in frames])
    T0 = gt_T[0]  # the tracker's world is the first camera's frame
    r = ate(out["stamps"], out["T_wc"], gt_st, gt_T)
    rev = loop_revisit_frames(spec)
    index = {s: i for i, s in enumerate(out["stamps"].tolist())}
    have = [k for k in rev.tolist() if int(gt_st[k]) in index]
    T_rev = out["T_wc"][[index[int(gt_st[k])] for k in have]]
    err = np.linalg.norm((T0 @ T_rev)[:, :3, 3] - gt_T[have, :3, 3], axis=1)
    res = {"ate_cm": 100 * r.rmse_m, "revisit_drift_cm": 100 * float(np.median(err)) if len(err) else None,
           "tracked": len(out["stamps"]), "loops_detected": out["loops_detected"],
           "loops_accepted": out["loops_accepted"], "loops_rejected": out["loops_rejected"],
           "pose_graph_s": out["pose_graph_time_s"], "global_ba_runs": out["global_ba_runs"],
           "global_ba_s": out["global_ba_time_s"],
           "track_cpu_ms_median": 1e3 * float(np.median(out["cpu"])),
           "track_cpu_ms_p95": 1e3 * float(np.percentile(out["cpu"], 95))}
    if with_map:
        res["psnr_revisit_db"] = map_psnr(frames, out["kf_poses"], T0, np.array(have), T_rev, iterations)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spec", default=DEFAULT_SPEC)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--n-features", type=int, default=300)
    ap.add_argument("--iterations", type=int, default=600, help="mapping steps per map (0: no map)")
    ap.add_argument("--rate", type=float, default=0.0,
                    help="replay rate as a multiple of the camera's (0: back to back)")
    ap.add_argument("--out", default="results/bench_loop.json")
    args = ap.parse_args(argv)
    if not (args.rate >= 0 and np.isfinite(args.rate)):
        ap.error(f"--rate must be >= 0, got {args.rate}")
    spec = parse_spec(args.spec)
    t0 = time.perf_counter()
    frames = list(generate_frames(spec))
    print(f"{spec.to_string()}: {len(frames)} frames, path {path_length_m(np.array([f.T_wc_gt for f in frames])):.1f} m, "
          f"{len(loop_revisit_frames(spec))} revisit frames, generated in {time.perf_counter() - t0:.1f} s", flush=True)
    rows: dict[str, list[dict]] = {"with": [], "without": []}
    for run in range(args.runs):
        for name, on in (("with", True), ("without", False)):
            cfg = TrackerConfig(n_features=args.n_features, loop_closure=on)
            res = evaluate(frames, spec, track(frames, spec.camera, cfg, args.rate), args.iterations > 0 and run == 0,
                           args.iterations)
            rows[name].append(res)
            print(f"run {run} {name:>7} loop closure: " + ", ".join(
                f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in res.items()), flush=True)
    keys = [k for k in rows["with"][0] if isinstance(rows["with"][0][k], (int, float))]
    med = {n: {k: float(np.median([r[k] for r in rs if r.get(k) is not None]))
               for k in keys if any(r.get(k) is not None for r in rs)} for n, rs in rows.items()}
    feed = "back to back" if args.rate == 0 else f"at {args.rate:g}x the camera rate"
    print(f"\nmedians over {args.runs} runs ({args.spec}, n_features={args.n_features}, frames {feed}):")
    print(f"{'':>22} | {'with':>9} | {'without':>9}")
    for k in med["with"]:
        print(f"{k:>22} | {med['with'][k]:9.2f} | {med['without'].get(k, float('nan')):9.2f}")
    w, wo = med["with"], med["without"]
    print(f"ATE ratio {w['ate_cm'] / wo['ate_cm']:.2f}, revisit drift ratio "
          f"{w['revisit_drift_cm'] / wo['revisit_drift_cm']:.2f} (target <= 0.33)")
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} on {os.cpu_count()} cores")
    write_results(args.out, {"benchmark": "loop", "spec": args.spec, "n_features": args.n_features,
                             "rate": args.rate, "runs": rows, "medians": med, "loadavg": load})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
