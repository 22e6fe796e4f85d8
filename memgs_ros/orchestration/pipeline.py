"""Run the whole graph on a recorded source: player -> tracker -> sampler -> mapper -> merger.

``run_pipeline(options)`` starts the five nodes either as separate processes over real DDS
(the default, as on a robot) or composed in this process on one executor, watches them
through an observer node, and at the end of the source finishes the mapper (final flush),
waits for the merger to hold the mapper's last delta, saves the map and returns a summary.
It is what ``memgs run`` / ``memgs demo`` and the end-to-end tests call.
"""
from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
import yaml
from rclpy.executors import Executor, SingleThreadedExecutor
from tqdm import tqdm

from memgs_ros.core.geometry.poses import pose_to_tq
from memgs_ros.core.map_io.answers import MapAnswer
from memgs_ros.core.runtime.atomic import atomic_write
from memgs_ros.core.runtime.cpu import MALLOC_ARENAS
from memgs_ros.errors import ConfigError, PipelineError
from memgs_ros.io.image_decoding import image_to_numpy
from memgs_ros.orchestration.bring_up import AUTOSTART_OFF, bring_up
from memgs_ros.orchestration.graph_watch import STATS_NODES, GraphObserver, compare_maps, end_flight, wait_for_graph
from memgs_ros.orchestration.processes import (
    NODE_FACTORIES,
    NODE_MODULES,
    VIEW_NODE,
    NodeProcesses,
    open_context,
    spin_in_background,
    stop_spinning,
)
from memgs_ros.orchestration.run_files import (
    CHECKPOINT_FILE,
    GRAPH_NODE_NAMES,
    KEYFRAMES_FILE,
    LOGS_DIR,
    MAP_FILE,
    PARAMS_FILE,
    STATS_TIMELINE_FILE,
    SUMMARY_FILE,
    TRAJECTORY_FILE,
    RunOptions,
    RunSummary,
    build_params,
    config_path,
    node_params,
)
from memgs_ros.orchestration.signals import stop_on_signals
from memgs_ros.ros.codecs import matrix_to_pose_stamped

logger = logging.getLogger(__name__)

__all__ = ["GRAPH_NODES", "NODE_MODULES", "PipelineError", "RunOptions", "RunSummary", "run_pipeline"]

GRAPH_NODES = GRAPH_NODE_NAMES
_STATS_ROUND_S = 1.5  # every node publishes its stats once a second: one round, with margin
_FINAL_RENDER_TIMEOUT_S = 30.0  # a render of the final map takes < 1 s on CPU at 640x480
_DESTROY_TIMEOUT_S = 10.0  # how long the runner waits for each of its own teardown calls in rclpy


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def run_pipeline(options: RunOptions, progress: bool = True) -> RunSummary:
    """Replay ``options.source`` through the graph and return what it produced.

    SIGTERM and SIGHUP stop it as Ctrl-C does (``orchestration/signals.py``): the nodes are
    stopped in order and the merger saves its map; then ``StopRequested`` propagates.
    """
    with stop_on_signals():
        return _run_pipeline(options, progress)


def _run_pipeline(options: RunOptions, progress: bool) -> RunSummary:

    if options.rerun is not None:
        options.rerun.check()  # rerun-sdk missing or no display: one line, before any node starts
    if options.composed and options.kill_after_s:
        raise ConfigError("fault injection (kill_after_s) needs separate processes")
    out, params, params_file = _write_run_files(options)
    earlier_record = _file_identity(options.record)  # an earlier run's file is replaced, never taken for this one's

    # A 50 ms heartbeat repairs lost fragments of big messages fast (see config/fastdds.xml);
    # a profile the user chose is kept.
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(config_path("fastdds.xml")))
    ns = options.namespace
    ros_args = ["--ros-args", "--params-file", str(params_file)] + (["-r", f"__ns:={ns}"] if ns else [])
    context, domain = open_context(options.domain_id, ros_args, namespace=ns)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    # One thread: the observer's callbacks only store what arrives, and composed nodes' callbacks
    # never wait (their work runs on their own threads). rclpy's multi-threaded executor spent CPU
    # on every wake-up (11 s over a 156 s run) and took ~30 ms to pick up a message.
    executor: Executor = SingleThreadedExecutor(context=context)
    procs: NodeProcesses | None = None
    in_process: list[Any] = []
    observer: GraphObserver | None = None
    spin: threading.Thread | None = None
    t0 = time.monotonic()
    try:
        observer = GraphObserver(context)
        executor.add_node(observer.node)
        if options.composed:
            spin = _start_composed(options, observer, executor, context, in_process, t0)
        else:
            spin = spin_in_background(executor)
            procs = _start_processes(options, observer, params, params_file, domain, out, t0)
        try:
            summary = _drive(observer, options, procs, out, t0, progress)
        except BaseException as err:
            _write_ended_summary(out, options, observer, err, time.monotonic() - t0)
            raise
    finally:
        _stop_graph(procs, in_process, executor, spin, observer, context)
    # The recorder stopped with the graph (its shutdown closes the file): in parallel, not after it.
    if options.record is not None and _file_identity(options.record) in (None, earlier_record):
        raise PipelineError(f"the recorder did not write {options.record} (see {out / LOGS_DIR / 'recorder.log'})")
    return summary


def _write_run_files(options: RunOptions) -> tuple[Path, dict[str, Any], Path]:
    """The output folder with its logs/ and params.yaml (an earlier run's checkpoint set aside)."""
    out = Path(options.out_dir).resolve()
    (out / LOGS_DIR).mkdir(parents=True, exist_ok=True)
    params_file = out / PARAMS_FILE
    params = build_params(options, out / MAP_FILE)
    _write_text(params_file, yaml.safe_dump(params, sort_keys=False))
    if "mapper.checkpoint_path" not in options.overrides:
        _set_aside_previous_checkpoint(out / CHECKPOINT_FILE)
    return out, params, params_file


def _graph_names(options: RunOptions) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The graph's nodes (with the Rerun view when asked for) and the recorder when recording."""
    graph = (*GRAPH_NODES, VIEW_NODE) if options.rerun is not None else GRAPH_NODES
    return graph, (("recorder",) if options.record is not None else ())


def _start_composed(options: RunOptions, observer: GraphObserver, executor: Executor, context: Any,
                    in_process: list[Any], t0: float) -> threading.Thread:
    """The nodes as components on this process's executor; the player once the graph is warm."""
    graph, recording = _graph_names(options)
    for name in (*graph, *recording):  # the recorder sees the graph's publishers
        in_process.append(NODE_FACTORIES[name](context=context))
        executor.add_node(in_process[-1])
    spin = spin_in_background(executor)
    _wait_for_warm_graph(observer, None, GRAPH_NODES, t0 + options.timeout_s)
    in_process.append(NODE_FACTORIES["bag_player"](context=context))
    executor.add_node(in_process[-1])
    return spin


def _node_env(domain: int) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
    # Threaded BLAS/OpenMP pools fight over a few shared cores (a 1 ms product took
    # 460 ms under load): one thread per node unless the user asked otherwise.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "1")
    # Two malloc arenas per node process: with one per thread (DDS, executor, session,
    # compositor threads) freed blocks sit in arenas that other threads never reuse, and the
    # mapper's peak RSS on the fr1/rpy head was 26 MB higher (723 instead of 697 MB).
    env.setdefault("MALLOC_ARENA_MAX", str(MALLOC_ARENAS))
    return env


def _start_processes(options: RunOptions, observer: GraphObserver, params: dict[str, Any], params_file: Path,
                     domain: int, out: Path, t0: float) -> NodeProcesses:
    """One process per node; the player once every node listens and has its kernels in. Nodes
    with a start delay are started by _drive's loop, counted from the start of the replay."""
    graph, recording = _graph_names(options)
    deadline = t0 + options.timeout_s
    procs = NodeProcesses(params_file, options.namespace, _node_env(domain), out / LOGS_DIR)
    delayed = {n: float(d) for n, d in options.start_delays_s.items() if float(d) > 0}
    managed = [n for n in GRAPH_NODES if n in graph and n not in delayed]  # brought up by the runner
    for name in graph:
        if name not in delayed:
            procs.start(name, AUTOSTART_OFF if name in managed else ())
    for name in recording:  # beside the graph; it subscribes as it discovers their publishers
        procs.start(name)
    observer.bring_up_s = bring_up(observer.node, managed, procs.check, deadline)
    wait_for_graph(observer, procs, [n for n in graph if n not in delayed], deadline)
    if recording:
        topics = node_params(params).get("recorder", {}).get("topics", NODE_MODULES["recorder"].DEFAULT_TOPICS)
        _wait_for_recorder(observer, procs, topics, deadline)
    _wait_for_warm_graph(observer, procs, [n for n in GRAPH_NODES if n not in delayed], deadline)
    procs.start("bag_player")
    procs.due = {name: time.monotonic() + delay for name, delay in delayed.items()}
    return procs


def _stop_graph(procs: NodeProcesses | None, in_process: Sequence[Any], executor: Executor,
                spin: threading.Thread | None, observer: GraphObserver | None, context: Any) -> None:
    """Stop the node processes (each saves what it holds) or the composed nodes, then the runner's
    executor (also after a second Ctrl-C: its thread left in rclpy crashed the runner, SIGSEGV) and context."""
    try:
        if procs is not None:
            procs.stop()
        for node in in_process:
            hook = getattr(node, "close", None)
            if hook is not None:
                hook()
    finally:
        stop_spinning(executor, spin)  # before the context ends, or rclpy may abort at exit
    for node in in_process:
        node.destroy_node()
    if observer is not None:
        # Bounded: with another graph's publishers on the same topics, destroying the observer's
        # publishers once hung in rclpy for over 5 minutes (and SIGTERM could not end the runner).
        _bounded(observer.node.destroy_node, _DESTROY_TIMEOUT_S, "destroying the runner's node")
    _bounded(lambda: rclpy.try_shutdown(context=context), _DESTROY_TIMEOUT_S, "shutting down the runner's context")


def _bounded(fn: Any, timeout_s: float, what: str) -> None:
    """Run ``fn`` on a daemon thread and wait at most ``timeout_s``: a call stuck in native code
    is left behind (logged) rather than holding the runner, whose process then exits."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            fn()
        except BaseException as err:  # noqa: BLE001 - reported in the caller's thread below
            errors.append(err)

    t = threading.Thread(target=run, name="memgs-run-stop", daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        logger.warning("%s took over %.0f s; going on without it", what, timeout_s)
    elif errors:
        raise errors[0]


def _wait_for_fresh_stats(obs: GraphObserver, names: Sequence[str], timeout_s: float = _STATS_ROUND_S) -> None:
    """Wait for one more stats message from each of ``names`` (1 Hz each), at most ``timeout_s``
    (a node that is gone sends none)."""
    with obs._lock:
        start = len(obs.timeline)
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        with obs._lock:
            if {row["node"] for row in obs.timeline[start:]} >= set(names):
                return
        time.sleep(0.05)


def _write_ended_summary(out: Path, options: RunOptions, obs: GraphObserver, err: BaseException, wall_s: float) -> None:
    """A run that ends early still says what happened in ``summary.json``: how it ended (the one
    line the CLI prints) and what the graph had done by then. Best effort: the disk may be full,
    and nothing here may replace the error that ended the run."""
    interrupted = isinstance(err, KeyboardInterrupt)  # StopRequested (SIGTERM, SIGHUP) is one
    line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    try:
        tracker = obs.telemetry("tracker")
        ended = {
            "source": str(options.source), "outcome": "interrupted" if interrupted else "failed",
            "error": line if not interrupted else f"interrupted ({line})", "wall_s": round(wall_s, 1),
            "frames_played": obs.telemetry("player").frames_published,
            "frames": tracker.frames_in, "poses": len(obs.trajectory),
            "lost_frames": tracker.state.get("LOST", 0), "keyframes": tracker.keyframes,
            "gaussians": obs.telemetry("mapper").gaussians, "merger_seq": obs.telemetry("merger").seq,
            "source_complete": False, "map_path": str(out / MAP_FILE),  # the merger saves its map as it stops
        }
        _write_text(out / SUMMARY_FILE, json.dumps(ended, indent=2) + "\n")
    except Exception as write_err:  # noqa: BLE001 - the run's own error is the one to report
        logger.warning("could not write %s: %s", out / SUMMARY_FILE, write_err)


def _file_identity(path: Path | None) -> tuple[int, int] | None:
    """(inode, mtime ns) of a file, None when there is none: a file moved into place is a new inode."""
    try:
        st = Path(path).stat() if path is not None else None
    except OSError:
        return None
    return (st.st_ino, st.st_mtime_ns) if st is not None else None


def _set_aside_previous_checkpoint(path: Path) -> None:
    """A checkpoint in the output folder from an earlier run would make this run's mapper resume
    that run's map (resuming is for a mapper restarted within one run): rename it to
    ``*.previous.npz``, kept rather than deleted."""
    if not path.is_file():
        return
    aside = path.with_name(f"{path.stem}.previous{path.suffix}")
    os.replace(path, aside)
    logger.warning("%s holds a checkpoint of an earlier run: moved it to %s so this run starts a new map",
                   path.parent, aside.name)


# A topic each node publishes: once the observer sees it, DDS discovery reached that node.
def _wait_for_recorder(obs: GraphObserver, procs: NodeProcesses, topics: Sequence[str], deadline: float) -> None:
    """Block until the recorder subscribes to every output topic whose publisher is up, so the
    first frame's pose is in the file (topics of nodes that start later it subscribes to later)."""
    ns = "/" + obs.node.get_namespace().strip("/")
    topics = [obs.node.resolve_topic_name(t) for t in topics]
    while True:
        procs.check()
        waiting = [t for t in topics if obs.node.count_publishers(t) > 0 and not any(
            i.node_name == "recorder" and i.node_namespace == ns for i in obs.node.get_subscriptions_info_by_topic(t))]
        if not waiting:
            break
        if time.monotonic() > deadline:
            raise PipelineError(f"the recorder did not subscribe to {', '.join(waiting)}")
        time.sleep(0.1)
    time.sleep(0.3)  # endpoint matching settles just after discovery, as for the graph


_SLOW_WARM_UP_S = 5.0  # warm-ups from the kernel cache take ~1 s; longer means compiling


def _wait_for_warm_graph(obs: GraphObserver, procs: NodeProcesses | None, nodes: Sequence[str],
                         deadline: float) -> None:
    """The player starts once every node has its compiled kernels in (stats ``kernels_warm``):
    from the kernel cache in about a second; on a fresh install they compile first (a minute on 2
    cores, which ``memgs doctor --warm`` does ahead). A frame played before that would be dropped
    by a live tracker (skipped.warming) or wait for their acknowledgement, and cost the track the next dozen."""
    start, told = time.monotonic(), False
    while missing := [n for n in nodes if obs.telemetry(n).kernels_warm < 1]:
        if procs is not None:
            procs.check()
        now = time.monotonic()
        if now > deadline:
            raise PipelineError(f"{', '.join(missing)} did not load their kernels in time")
        if not told and now - start > _SLOW_WARM_UP_S:
            told = True
            logger.warning("waiting for %s to compile their kernels (the first run after an install; "
                           "`memgs doctor --warm` does it ahead, once)", ", ".join(missing))
        time.sleep(0.05)


def _has_state_to_lose(obs: GraphObserver, name: str) -> bool:
    """Whether killing ``name`` now tests its recovery: the mapper has written a checkpoint
    holding Gaussians (or never checkpoints, and has Gaussians), the merger has applied a delta.
    (A kill counted in seconds alone once hit a mapper that had not started mapping on a loaded
    machine, and its second life resumed an empty checkpoint.)"""
    if name == "mapper":
        if not obs.heard("mapper"):
            return False
        mapper = obs.telemetry("mapper")
        return (mapper.checkpoint_gaussians > 0 if mapper.checkpoint_period_s > 0 else mapper.gaussians > 0)
    if name == "merger":
        return obs.telemetry("merger").seq > 0
    return True


def _drive(obs: GraphObserver, options: RunOptions, procs: NodeProcesses | None, out: Path, t0: float,
           progress: bool) -> RunSummary:
    """Wait for the end of the source, finish the mapper, sync the merger, save, summarise."""
    end = t0 + options.timeout_s
    restarts = _replay(obs, options, procs, end, progress)
    if not obs.source_ok:
        # What was played is still mapped and saved; the caller reports the failure.
        logger.error("the source failed part-way (see the bag_player log): finishing and saving the map "
                     "of the frames played")
    if not options.pacing.acknowledged:
        time.sleep(2.0)  # let the last frames drain through the graph
    logger.info("source finished after %.1f s; finishing the mapper", time.monotonic() - t0)
    end_flight(obs)
    final = MapAnswer.parse(obs.call(obs.finish_client, max(60.0, end - time.monotonic())))
    final_seq, gaussians, epoch = final.seq, final.gaussians, final.epoch or 0
    _wait_for_merger(obs, procs, final_seq, epoch, end)
    identical, max_diff = compare_maps(obs, final_seq, epoch, end)
    if options.rerun is not None:
        _wait_for_view(obs, procs, final_seq, epoch, end)
        if gaussians:  # an empty map has no view to show
            _wait_for_final_render(obs, procs, end)
    extra = (("recorder",) if options.record is not None else ()) + ((VIEW_NODE,) if options.rerun is not None else ())
    _wait_for_fresh_stats(obs, (*GRAPH_NODES, *extra))  # so the summary sees the final counts
    saved = obs.call(obs.save_client, 300.0) if gaussians or final_seq else ""  # a map bundle too: ~100 MB
    saved_map = MapAnswer.parse(saved) if saved else MapAnswer(0, 0)
    wall = time.monotonic() - t0
    poses = _write_trajectories(obs, out)
    tracker, mapper, merger = obs.telemetry("tracker"), obs.telemetry("mapper"), obs.telemetry("merger")
    track_s = tracker.track_us_total * 1e-6
    summary = RunSummary(
        source=str(options.source), repeat=int(options.repeat), repeat_forward=bool(options.repeat_forward),
        bag_topics=str(options.bag_topics), frames=tracker.frames_in, poses=poses,
        keyframes=tracker.keyframes, gaussians=gaussians,
        tracking_fps=(tracker.frames_in / track_s) if track_s > 0 else 0.0, wall_s=wall,
        ply_path=saved_map.ply or "", trajectory_path=str(out / TRAJECTORY_FILE),
        bundle_path=saved_map.bundle or "", map_bundle=str(options.map_bundle or ""),
        relocalizing=int(tracker.relocalizing), delta_messages=merger.deltas,
        delta_bytes=merger.delta_bytes, delta_bytes_per_s=merger.delta_bytes / wall if wall > 0 else 0.0,
        lost_frames=tracker.state.get("LOST", 0), merger_seq=merger.seq,
        namespace=options.namespace, domain_id=int(os.environ["ROS_DOMAIN_ID"]),
        mapping_iterations=mapper.iteration, model_bytes_peak=mapper.model_bytes_peak,
        gaussians_peak=mapper.gaussians_peak,
        peak_rss_mb={n: obs.telemetry(n).peak_rss_mb for n in GRAPH_NODES},
        cpu_s=_cpu_times(obs, procs), merger_resyncs=sum(merger.resync.values()), restarts=restarts,
        replica_identical=identical, replica_max_abs_diff=max_diff, **_render_info(obs.render),
        source_complete=obs.source_ok, frames_played=obs.telemetry("player").frames_published,
        tracker_skipped={k: tracker.skipped.get(k, 0) for k in ("warming", "stale", "busy", "unpaired",
                                                                 "inactive")},
        tracker_frame_cpu_ms=tracker.frame_cpu_ms_median, skipped_frames=dict(obs.telemetry("player").skipped),
        bring_up_s=None if obs.bring_up_s is None else round(obs.bring_up_s, 2),
        **_mapper_figures(obs, options.composed))
    # The summary is a file of the run, so evaluation reads a finished run instead of watching it.
    _write_text(out / SUMMARY_FILE, json.dumps(summary.as_dict(), indent=2) + "\n")
    return summary


def _replay(obs: GraphObserver, options: RunOptions, procs: NodeProcesses | None, end: float,
            progress: bool) -> dict[str, int]:
    """Until the player is done: the fault injection's kills and delayed starts, the nodes'
    health, the progress bar. Returns the restarts per node."""
    # frames / total, frames/s and ETA on a terminal; nothing when stderr is a file or pipe
    # (stats_timeline.jsonl keeps the same figures).
    bar = tqdm(desc="replay", unit="frame", disable=None, dynamic_ncols=True) if progress else None
    play_start = time.monotonic()
    kills = dict(options.kill_after_s)
    restarts: dict[str, int] = {}
    if procs is not None:
        unknown = set(kills) - set(GRAPH_NODES)
        if unknown:
            raise ConfigError(f"cannot kill {sorted(unknown)}: nodes are {list(GRAPH_NODES)}")
    while not obs.done.is_set():
        if procs is not None:
            for name, after in list(kills.items()):
                if time.monotonic() - play_start >= after and _has_state_to_lose(obs, name):
                    logger.warning("fault injection: killing %s (SIGKILL) and restarting it", name)
                    procs.kill_and_restart(name)
                    restarts[name] = restarts.get(name, 0) + 1
                    del kills[name]
            procs.start_due()
            procs.check()
            if _player_ended_unheard(procs):
                _note_unfinished_source(obs)
                break
        if time.monotonic() > end:
            raise PipelineError(f"the source did not finish within {options.timeout_s:.0f} s")
        if bar is not None:
            _show_progress(bar, obs)
        time.sleep(0.1)
    if bar is not None:
        _show_progress(bar, obs)
        bar.close()
    for name in kills:
        logger.warning("fault injection: %s was not killed: the source ended before it had state to lose", name)
    if procs is not None:
        procs.player_reported = True
    return restarts


def _note_unfinished_source(obs: GraphObserver) -> None:
    """The player exited 0 unheard: a source it stopped part-way (Ctrl-C exits 0 too) is not done."""
    player = obs.telemetry("player")
    total, played = player.frames_total, player.frames_published
    if total and played < total:
        logger.error("the bag player stopped after %d of %d frames: the map holds those", played, total)
        obs.source_ok = False


def _wait_for_merger(obs: GraphObserver, procs: NodeProcesses | None, final_seq: int, epoch: int, end: float) -> None:
    """Until the merger holds the mapper's final delta of ``epoch``, resynchronised."""
    while (not obs.heard("merger") or (merger := obs.telemetry("merger")).seq < final_seq
           or merger.resyncing > 0 or merger.epoch != epoch):
        if procs is not None:
            procs.check()
        if time.monotonic() > end:
            raise PipelineError(f"the merger did not reach delta {final_seq} in time")
        time.sleep(0.1)


def _write_trajectories(obs: GraphObserver, out: Path) -> int:
    """trajectory.txt, keyframes.txt and stats_timeline.jsonl; the number of poses."""
    corrected = obs.corrected_poses()
    with obs._lock:
        # Corrected poses (memgs/path) where the path has them, the per-frame odometry elsewhere.
        traj = sorted(((s, corrected.get(s, T)) for s, T in obs.trajectory), key=lambda p: p[0])
        kfs = sorted(obs.keyframes, key=lambda p: p[0])
        timeline = "".join(json.dumps(row) + "\n" for row in obs.timeline)
    _write_text(out / TRAJECTORY_FILE, _tum_trajectory(traj))
    _write_text(out / KEYFRAMES_FILE, _tum_trajectory(kfs))  # poses at insertion
    _write_text(out / STATS_TIMELINE_FILE, timeline)
    if (sent := obs.telemetry("tracker").poses_out) > len(traj):  # DDS dropped some on the way: say so
        logger.warning(f"trajectory.txt holds {len(traj)} of the {sent} poses the tracker published")
    return len(traj)


def _mapper_figures(obs: GraphObserver, composed: bool) -> dict[str, Any]:
    """The mapper's keyframe and iteration figures and the graph's memory, for RunSummary."""
    mapper = obs.telemetry("mapper")

    def pair(name: str) -> dict[str, float]:
        quantiles = {q: getattr(mapper, f"keyframe_{name}_{q}") for q in ("median", "p95")}
        return {q: v for q, v in quantiles.items() if v is not None}

    cuda_mb = round(mapper.cuda_max_allocated / 2**20, 1) if mapper.cuda_max_allocated is not None else None
    rss = [obs.telemetry(n).peak_rss_mb for n in GRAPH_NODES]
    host = max(rss, default=0.0) if composed else sum(rss)
    per_frame = {} if mapper.train_commands <= 0 else {
        "frame": obs.telemetry("player").ack_wait_ms_median, "tracker": obs.telemetry("tracker").frame_ms_median,
        "mapper": mapper.frame_ack_ms_median, "training": round(mapper.train_ms_total / mapper.train_commands, 2)}
    return {"frame_ms": per_frame, "mapping_iterations_final": mapper.iterations_final,
            "keyframes_mapped": mapper.keyframes, "keyframes_trained": mapper.keyframes_used,
            "keyframe_intake_ms": pair("intake_ms"), "keyframe_latency_ms": pair("latency_ms"),
            "cuda_peak_mb": cuda_mb, "graph_memory_mb": round(host + (cuda_mb or 0.0), 1),
            "cuda_peak_by_work_mb": dict(mapper.cuda_peak_mb)}


def _cpu_times(obs: GraphObserver, procs: NodeProcesses | None) -> dict[str, float]:
    """CPU seconds of each node process so far (from its last stats) and of this runner; in one
    process (``--composed``) the process's total."""
    if procs is None:
        return {"all nodes": round(time.process_time(), 2)}
    cpu = {n: obs.telemetry(n).cpu_s for n in STATS_NODES}
    return {**{n: s for n, s in cpu.items() if s > 0}, "runner": round(time.process_time(), 2)}


_DONE_GRACE_S = 3.0  # after the player's exit, how long its latched "done" may still be in flight


def _player_ended_unheard(procs: NodeProcesses) -> bool:
    """True when the player process ended cleanly (exit 0: the whole source played) but its
    latched ``memgs/player/done`` has not arrived within a grace time: under heavy load the
    message can be lost when the player exits right after publishing it. Its exit code says the
    same, so the run goes on rather than waiting for ``--timeout``."""
    p = procs.procs.get("bag_player")
    if p is None or p.poll() != 0:
        return False
    if procs.player_exit_seen is None:
        procs.player_exit_seen = time.monotonic()
    if time.monotonic() - procs.player_exit_seen < _DONE_GRACE_S:
        return False
    logger.warning("the bag player finished (exit 0) but its done message did not arrive; going on")
    return True


def _show_progress(bar: tqdm, obs: GraphObserver) -> None:
    """Frames the player published out of its total, with keyframes and Gaussians beside them."""
    player = obs.telemetry("player")
    if player.frames_total and bar.total != player.frames_total:
        bar.total = player.frames_total
    if player.frames_published > bar.n:
        bar.update(player.frames_published - bar.n)
    bar.set_postfix(keyframes=obs.telemetry("tracker").keyframes, gaussians=obs.telemetry("mapper").gaussians,
                    refresh=False)


def _wait_for_view(obs: GraphObserver, procs: NodeProcesses | None, final_seq: int, epoch: int, end: float) -> None:
    """Wait until the rerun_bridge has logged the final map (the one _compare_maps had the merger
    publish), so the recording ends with the saved map before the nodes are stopped."""
    while (view := obs.telemetry(VIEW_NODE)).map_seq < final_seq or view.map_epoch != epoch:
        if procs is not None:
            procs.check()
        if time.monotonic() > end:
            raise PipelineError(f"the Rerun view did not log the final map (delta {final_seq}) in time")
        time.sleep(0.1)


def _wait_for_final_render(obs: GraphObserver, procs: NodeProcesses | None, end: float) -> None:
    """Have the mapper render the final map at the last pose and wait until the Rerun view has
    logged it, so the recording ends with a view of the saved map: the live render's next tick may
    come after the nodes are stopped (a recording ended on a view 100 iterations old). A view that
    does not come in time is a warning: the final map itself is logged."""
    with obs._lock:
        last, frame_id = (obs.trajectory[-1] if obs.trajectory else None), obs.pose_frame
    if last is None:
        return
    _wait_for_fresh_stats(obs, (VIEW_NODE,))  # a count from after the finish, not a stale one
    before = obs.telemetry(VIEW_NODE).logged.get("views", 0)
    stamp_ns, T_wc = last
    obs.view_request.publish(matrix_to_pose_stamped(T_wc, stamp_ns, frame_id))
    deadline = min(end, time.monotonic() + _FINAL_RENDER_TIMEOUT_S)
    while obs.telemetry(VIEW_NODE).logged.get("views", 0) <= before:
        if procs is not None:
            procs.check()
        if time.monotonic() > deadline:
            logger.warning("the Rerun view did not log a render of the final map within %.0f s; the recording "
                           "ends with the final map and an earlier render", _FINAL_RENDER_TIMEOUT_S)
            return
        time.sleep(0.1)


def _render_info(msg: Any) -> dict[str, Any]:
    if msg is None:
        return {"render_size": (0, 0), "render_std": 0.0}

    img = image_to_numpy(msg)
    return {"render_size": (int(msg.width), int(msg.height)), "render_std": float(img.std())}


def _tum_trajectory(traj: list[tuple[int, np.ndarray]]) -> str:

    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, memgs_ros tracker)"]
    for stamp, T in traj:
        t, q = pose_to_tq(T)
        sec, nsec = divmod(int(stamp), 1_000_000_000)  # exact ns: the stamps key frames downstream
        lines.append(f"{sec}.{nsec:09d} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
    return "\n".join(lines) + "\n"
