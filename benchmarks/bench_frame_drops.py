"""Benchmark: the tracker node's frame path when frames are dropped, as a live tracker drops stale ones.

    python benchmarks/bench_frame_drops.py [--tum DIR] [--drop 0.5] [--seeds 1 2]

Feeds a TUM folder to the real ``TrackerNode`` (the tracker parameters ``memgs run --realtime``
gives it: local BA on the back-end's thread) at the folder's frame rate, in this process, leaving
out each frame with probability ``--drop`` (seeded; the first 5 frames always go in). Per seed:
the frame path's CPU per frame (median, p90, max; thread time, message in to pose out), tracking
states, and the ATE of the frames that went in against the ground truth (SE(3)-aligned). With
``--drop 0`` every frame goes in.

Run nothing else on the machine meanwhile: CPU time rises with contention.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import ROOT, TUM_HELP, tum_path_or_exit, write_results


def _recording(tracker: Any) -> dict[int, np.ndarray]:
    """Wrap ``tracker.track`` so that every tracked pose (T_wc, state OK) lands in the returned dict."""
    poses: dict[int, np.ndarray] = {}
    track = tracker.track

    def recorded(frame: Any) -> Any:
        result = track(frame)
        if result.T_wc is not None and result.state.name == "OK":
            poses[frame.stamp_ns] = result.T_wc
        return result

    tracker.track = recorded
    return poses


def run(tum: Path, drop: float, seed: int, frames: int, config: str) -> dict[str, Any]:
    import rclpy
    from rclpy.parameter import Parameter

    from memgs_ros.core.metrics.trajectory import ate
    from memgs_ros.core.runtime.replay import Pacing
    from memgs_ros.core.tracking import warm_up
    from memgs_ros.io.tum import TumFolder
    from memgs_ros.nodes.tracker.node import TrackerNode
    from memgs_ros.orchestration.run_files import RunOptions, build_params, node_params
    from memgs_ros.ros import images

    work = ROOT / "results" / "bench_frame_drops"
    work.mkdir(parents=True, exist_ok=True)
    params = node_params(build_params(RunOptions(source=str(tum), config=config, out_dir=work, pacing=Pacing.LIVE),
                                      work / "map.ply"))["tracker"]
    every = list(TumFolder(tum, max_frames=frames))
    rng = np.random.default_rng(seed)
    fed = [f for i, f in enumerate(every) if i < 5 or rng.random() >= drop]
    msgs = [(f.stamp_ns, images.numpy_to_image(f.rgb, "rgb8", f.stamp_ns, "camera"),
             images.depth_to_image(f.depth_m, "32FC1", f.stamp_ns, "camera")) for f in fed]
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get("ROS_DOMAIN_ID", "78")))
    try:
        node = TrackerNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()
                                                             if not k.startswith("qos_overrides")])
        warm_up()  # the node's own warm-up posts to an executor this process does not spin: do it here
        poses: dict[int, np.ndarray] = {}
        cpu_ms: list[float] = []
        t0 = time.perf_counter()
        stamp0 = msgs[0][0]
        for i, (stamp, color, depth) in enumerate(msgs):  # paced by the stamps, as a camera delivers them
            wait = t0 + (stamp - stamp0) * 1e-9 - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            c0 = time.thread_time()
            node._handle(color, depth)  # noqa: SLF001 - the frame path itself
            cpu_ms.append((time.thread_time() - c0) * 1e3)
            if i == 0:  # the node made its tracker on the first frame: record what it tracks
                poses = _recording(node.tracker)
        states = {k.split(".", 1)[1]: v for k, v in node.stats.counters.items() if k.startswith("state.")}
        node.close()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    est_s = np.array(sorted(poses))
    a = ate(est_s, np.array([poses[s] for s in est_s]), np.array([f.stamp_ns for f in every]),
            np.array([f.T_wc_gt for f in every]))
    ms = np.array(cpu_ms[5:])
    return {"seed": seed, "drop": drop, "frames_in": len(fed), "of": len(every),
            "cpu_ms_median": round(float(np.median(ms)), 2), "cpu_ms_p90": round(float(np.percentile(ms, 90)), 2),
            "cpu_ms_max": round(float(ms.max()), 2), "states": states, "ate_cm": round(a.rmse_m * 100, 2)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tum", type=Path, default=None, help=TUM_HELP)
    ap.add_argument("--config", default="tum_fr1")
    ap.add_argument("--drop", type=float, default=0.5, help="probability that a frame is left out")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--out", type=Path, default=ROOT / "results/bench_frame_drops.json")
    args = ap.parse_args(argv)
    if not 0.0 <= args.drop < 1.0:
        ap.error("--drop must be in [0, 1)")
    args.tum = tum_path_or_exit(ap, args.tum)
    rows = []
    for seed in args.seeds:
        row = run(args.tum, args.drop, seed, args.frames, args.config)
        print(f"seed {seed}: {row['frames_in']}/{row['of']} frames in, CPU ms/frame median {row['cpu_ms_median']} "
              f"p90 {row['cpu_ms_p90']} max {row['cpu_ms_max']}, states {row['states']}, ATE {row['ate_cm']} cm",
              flush=True)
        rows.append(row)
    write_results(args.out, {"date": time.strftime("%Y-%m-%d"), "source": args.tum.name, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
