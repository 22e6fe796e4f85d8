"""Benchmark: pausing the graph through the node lifecycle. The head played live (``memgs run
--realtime``) twice: once untouched, once with the tracker and the mapper deactivated by
``lifecycle_msgs/srv/ChangeState`` after ``--pause-after`` frames and activated again
``--pause-frames`` frames later (a drone hovering over a landing pad), driven from this script over DDS.

    python benchmarks/bench_lifecycle_pause.py [--tum DIR] [--pause-after 70] [--pause-frames 60]

Prints, per run: frames the tracker answered while inactive and how many of them it tracked (0
expected), the run's poses and keyframes, the mapper's iterations, and PSNR of the final map at
the tracked poses (``evaluate_run``); for the comparison the untouched run is also scored over
the frames the paused one tracked only. Also the time from each ``activate`` request to its
answer. Run nothing else on the machine meanwhile.
"""
from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ (not a package): _common
from _common import ROOT, TUM_HELP, run_memgs, tum_path_or_exit, uptime, write_results  # noqa: E402

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

NAMESPACE = "/pause_bench"
PAUSED = ("tracker", "mapper")


def _log(msg: str) -> None:
    print(f"[bench_lifecycle_pause {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


class Pauser:
    """Counts the tracker's answers (``memgs/tracker/processed``) and deactivates, then activates,
    the tracker and mapper at the given counts, on its own DDS context and thread."""

    def __init__(self, domain_id: int, pause_after: int, pause_frames: int) -> None:
        import rclpy
        from lifecycle_msgs.srv import ChangeState
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import Header

        from memgs_ros.ros import qos

        self.pause_after, self.resume_at = pause_after, pause_after + pause_frames
        self.answered, self.last_stamp = 0, 0
        self.window: list[int] = []  # stamps: the last answered when both nodes were inactive, when activating
        self.events: list[dict[str, Any]] = []
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("pause_bench", namespace=NAMESPACE, context=self.ctx)
        self.clients = {n: self.node.create_client(ChangeState, f"{n}/change_state") for n in PAUSED}
        self.node.create_subscription(Header, "memgs/tracker/processed", self._on_processed, qos.reliable(100))
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self._stop = threading.Event()
        self._phase = "before"
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.ex.spin_once(timeout_sec=0.05)

    def _on_processed(self, msg: Any) -> None:
        from memgs_ros.ros.codecs import stamp_to_ns

        self.answered += 1
        self.last_stamp = stamp_to_ns(msg.stamp)
        if self._phase == "before" and self.answered >= self.pause_after:
            self._phase = "paused"
            self._change("deactivate")
        elif self._phase == "paused" and self.answered >= self.resume_at:
            self._phase = "after"
            self._change("activate")

    def _change(self, label: str) -> None:
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        tid = Transition.TRANSITION_DEACTIVATE if label == "deactivate" else Transition.TRANSITION_ACTIVATE
        if label == "activate":
            self.window.append(self.last_stamp)
        for name, client in self.clients.items():
            t0 = time.perf_counter()
            future = client.call_async(ChangeState.Request(transition=Transition(id=tid)))

            def done(f: Any, name: str = name, t0: float = t0, at: int = self.answered) -> None:
                ok = f.exception() is None and f.result().success
                self.events.append({"node": name, "transition": label, "at_frame": at, "ok": ok,
                                    "answer_ms": round((time.perf_counter() - t0) * 1e3, 1)})
                _log(f"{name} {label} at frame {at}: {'ok' if ok else 'FAILED'}")
                if label == "deactivate" and name == "tracker":
                    self.window.insert(0, self.last_stamp)  # frames after this one came to an inactive tracker

            future.add_done_callback(done)

    def close(self) -> None:
        import rclpy

        self._stop.set()
        self.thread.join(5.0)
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _score(out: Path, tum: Path, only: Path | None = None) -> dict[str, Any]:
    """PSNR and ATE of a finished run; with ``only`` (another run), over the frames that run tracked."""
    from memgs_ros.evaluation.runs import evaluate_run
    from memgs_ros.io.tum import parse_stamp_ns, read_trajectory
    from memgs_ros.orchestration.run_files import SUMMARY_FILE, TRAJECTORY_FILE

    if only is not None:  # a copy whose trajectory keeps the other run's frames only
        copy = out.parent / f"{out.name}_over_{only.name}"
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(out, copy)
        keep = set(read_trajectory(only / TRAJECTORY_FILE)[0].tolist())
        lines = (copy / TRAJECTORY_FILE).read_text().splitlines(keepends=True)
        (copy / TRAJECTORY_FILE).write_text("".join(
            ln for ln in lines if ln.startswith("#") or not ln.strip() or parse_stamp_ns(ln.split()[0]) in keep))
        summary = json.loads((copy / SUMMARY_FILE).read_text())  # it names its files by absolute path
        summary["trajectory_path"] = str(copy / TRAJECTORY_FILE)
        (copy / SUMMARY_FILE).write_text(json.dumps(summary))
        out = copy
    r = evaluate_run(out, source=str(tum), use_lpips=False, progress=False)
    return {"psnr_db": round(r.frames_quality.psnr_db or 0.0, 2),
            "ate_cm": round(100 * r.trajectory.rmse_m, 3) if r.trajectory else None}


def _tf_counts(mcap_path: Path) -> dict[str, int]:
    """Messages on the run's tf, tf_static and odometry topics in its recording."""
    from mcap.reader import make_reader

    counts = {"tf": 0, "tf_static": 0, "odom": 0, "tracked_state_ok": 0}
    names = {f"{NAMESPACE}/tf": "tf", f"{NAMESPACE}/tf_static": "tf_static", f"{NAMESPACE}/memgs/odom": "odom"}
    with open(mcap_path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            if channel.topic in names:
                counts[names[channel.topic]] += 1
            elif channel.topic == f"{NAMESPACE}/memgs/tracking_state" and b"OK" in message.data:
                counts["tracked_state_ok"] += 1
    return counts


def run_one(label: str, tum: Path, config: str, work: Path, pause: tuple[int, int] | None) -> dict[str, Any]:
    out, log = work / label, work / f"{label}.log"
    domain = random.Random(time.time_ns()).randrange(120, 220)
    args = ["run", "--bag", tum, "--config", config, "--realtime", "--domain-id", str(domain),
            "--namespace", NAMESPACE, "--record", out / "run.mcap"]
    _log(f"{label}: memgs {' '.join(map(str, args))} -> {out}")
    pauser = Pauser(domain, *pause) if pause is not None else None
    try:
        run = run_memgs(args, out, log=log, timeout_s=1800)
    finally:
        if pauser is not None:
            pauser.close()
    if not run.ok or run.summary is None:
        raise SystemExit(f"{label}: memgs run failed (exit {run.returncode}); see {log}")
    s = run.summary
    row: dict[str, Any] = {"label": label, "frames": s.frames, "poses": s.poses, "keyframes": s.keyframes,
                           "gaussians": s.gaussians, "iterations": s.mapping_iterations,
                           "skipped": dict(s.tracker_skipped), "wall_s": round(run.wall_s, 1), "uptime": uptime()}
    row["bring_up_s"] = s.bring_up_s
    row.update(_tf_counts(out / "run.mcap"))
    if pauser is not None:
        from memgs_ros.io.tum import read_trajectory

        row["events"], row["answered"], row["window_ns"] = pauser.events, pauser.answered, pauser.window
        stamps = read_trajectory(Path(s.trajectory_path))[0]
        if len(pauser.window) == 2:  # poses of frames that came while the tracker was inactive
            row["posed_while_inactive"] = int(((stamps > pauser.window[0]) & (stamps <= pauser.window[1])).sum())
    row.update(_score(out, tum))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tum", type=Path, default=None, help=TUM_HELP)
    ap.add_argument("--config", default="tum_fr1")
    ap.add_argument("--pause-after", type=int, default=70, help="frames answered before the pause")
    ap.add_argument("--pause-frames", type=int, default=60, help="frames the pause lasts")
    ap.add_argument("--work", type=Path, default=ROOT / "results/lifecycle_pause", help="run folders")
    ap.add_argument("--out", type=Path, default=ROOT / "results/bench_lifecycle_pause.json")
    args = ap.parse_args(argv)
    tum = tum_path_or_exit(ap, args.tum)
    args.work.mkdir(parents=True, exist_ok=True)
    plain = run_one("unpaused", tum, args.config, args.work, None)
    paused = run_one("paused", tum, args.config, args.work, (args.pause_after, args.pause_frames))
    plain_over_paused = _score(args.work / "unpaused", tum, only=args.work / "paused")
    inactive = paused["skipped"].get("inactive", 0)
    print("| run | frames | poses | skipped.inactive | keyframes | Gaussians | iterations | PSNR dB | ATE cm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in (plain, paused):
        print(f"| {r['label']} | {r['frames']} | {r['poses']} | {r['skipped'].get('inactive', 0)} | {r['keyframes']} "
              f"| {r['gaussians']} | {r['iterations']} | {r['psnr_db']:.2f} | {r['ate_cm']} |")
    print(f"| unpaused, over the paused run's frames | | | | | | | {plain_over_paused['psnr_db']:.2f} "
          f"| {plain_over_paused['ate_cm']} |")
    print(f"\nframes answered while inactive (skipped.inactive): {inactive}; poses of frames that came while "
          f"the tracker was inactive: {paused.get('posed_while_inactive')}; PSNR paused - unpaused over the "
          f"same frames: {paused['psnr_db'] - plain_over_paused['psnr_db']:+.2f} dB")
    for r in (plain, paused):
        print(f"{r['label']}: bring-up (configure -> active, all four) {r['bring_up_s']} s; tf {r['tf']} for "
              f"{r['tracked_state_ok']} frames tracked OK ({100 * r['tf'] / max(r['tracked_state_ok'], 1):.1f} %), "
              f"tf_static {r['tf_static']}, odometry {r['odom']}")
    for e in paused.get("events", []):
        print(f"  {e['node']} {e['transition']} at frame {e['at_frame']}: {'ok' if e['ok'] else 'FAILED'}, "
              f"answered in {e['answer_ms']} ms")
    write_results(args.out, {"config": args.config, "tum": str(tum), "pause_after": args.pause_after,
                             "pause_frames": args.pause_frames, "unpaused": plain, "paused": paused,
                             "unpaused_over_paused_frames": plain_over_paused})
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
