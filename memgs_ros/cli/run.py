"""``memgs run``: replay a bag or TUM folder through the four nodes and save the map."""
from __future__ import annotations

import argparse
import difflib
import json
import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import yaml

from memgs_ros.cli.rerun_options import add_rerun_arguments, rerun_target
from memgs_ros.core.geometry.camera import PinholeCamera, calibration_differences, describe_camera
from memgs_ros.core.runtime.replay import Pacing
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.orchestration.run_files import (
    GRAPH_NODE_NAMES,
    LOGS_DIR,
    ConfiguredCamera,
    RunOptions,
    RunSummary,
    build_params,
    check_parameters,
    check_record_path,
    configured_camera,
    node_params,
)

logger = logging.getLogger(__name__)

RUN_LOG = "memgs.log"  # the command's own log, beside the nodes' logs in OUT/logs

HELP = "replay a bag, TUM folder or synthetic spec through tracker, sampler, mapper and merger"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bag", required=True, metavar="SOURCE",
                   help="ROS 2 bag (folder, .mcap, .db3), TUM ROS 1 .bag, TUM folder or 'synthetic:...' spec")
    add_graph_arguments(p)


def add_graph_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by ``run`` and ``demo``."""
    p.add_argument("--config", default=None, help="config name in config/ (tum_fr1, synthetic, ...) or a YAML path")
    p.add_argument("--out", type=Path, default=Path("memgs_out"),
                   help="output folder: map.ply, trajectory.txt, keyframes.txt, summary.json, logs/ "
                        "(README, 'Outputs'; default: %(default)s)")
    p.add_argument("--composed", "--single-process", dest="composed", action="store_true",
                   help="the nodes as components of one process (this one), on one executor: the libraries load "
                        "once (a Jetson's CPU and GPU share its memory); default: one process per node")
    p.add_argument("--realtime", action="store_true",
                   help="replay at the recorded rate (frames may be dropped) instead of lockstep")
    p.add_argument("--rate", type=float, default=1.0, help="real-time factor with --realtime")
    p.add_argument("--namespace", default="", help="ROS namespace for every node (e.g. /uav1)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: a random free-ish one)")
    p.add_argument("--max-frames", type=int, default=0, help="stop after this many frames (0 = all)")
    p.add_argument("--repeat", type=int, default=1, metavar="N",
                   help="play the source N times, every other pass backward, on one clock with its ground truth: "
                        "a long flight over the same room (default: %(default)s)")
    p.add_argument("--repeat-forward", action="store_true",
                   help="with --repeat: every pass forward, the camera jumping back to the start between them "
                        "(a rolling-shutter recording played backward reads its rows bottom to top)")
    p.add_argument("--topics", default="", metavar="color=/T,depth=/T,camera_info=/T",
                   help="a bag's colour, depth and camera_info topics (any of them); default: TUM's names, else "
                        "found by type and encoding (a realsense-ros bag: colour, depth aligned to it, raw or "
                        "compressed), said in the log; a bag with several candidates is refused with their list")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first bad frame (unreadable or mis-sized image, stamp going backwards, "
                        "camera changing) instead of skipping it and counting it in the summary")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                   help="override a node parameter, e.g. mapper.mapping.resolution_scale=0.25 (repeatable)")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds")
    p.add_argument("--json", type=Path, default=None, help="also write the summary as JSON here")
    p.add_argument("--kill", action="append", default=[], metavar="NODE@SECONDS",
                   help="fault injection: SIGKILL NODE (mapper, merger, ...) this many seconds after the "
                        "player starts, once it has state to lose (the mapper a checkpoint with Gaussians, "
                        "the merger a delta), and restart it at once (repeatable; separate processes only)")
    add_map_arguments(p)
    add_record_argument(p)
    add_rerun_arguments(p)


def add_map_arguments(p: argparse.ArgumentParser, mode_flags: tuple[str, ...] = ("--mode", "--map-mode")) -> None:
    """``--map`` and ``--mode`` (``eval``, whose ``--mode`` is the camera's: ``--map-mode``)."""
    p.add_argument("--map", type=Path, default=None, metavar="BUNDLE",
                   help="start from a saved map bundle (a folder of OUT/maps/, or OUT/maps for its latest): "
                        "no pose until a frame relocalises in it, then its world frame")
    p.add_argument(*mode_flags, dest="map_mode", choices=("mapping", "localize"), default="mapping",
                   help="with --map: mapping continues the map (and saves a new bundle); localize tracks in "
                        "it and changes nothing")


def add_record_argument(p: argparse.ArgumentParser) -> None:
    """``--record``, shared by ``run``, ``demo`` and ``eval``."""
    p.add_argument("--record", type=Path, default=None, metavar="FILE.mcap",
                   help="also record every output topic (poses, path, map, renders, stats) into this ROS 2 "
                        "mcap file, for Foxglove, RViz via ros2 bag play, or rosbags; replaced when complete")


def guess_config(source: str) -> str:
    s = source.lower()
    for fr in ("freiburg1", "freiburg2", "freiburg3"):
        if fr in s:
            return f"tum_fr{fr[-1]}"
    return "synthetic"


def options_from_args(args: argparse.Namespace, source: str) -> RunOptions:
    kills = {}
    for item in getattr(args, "kill", []):
        node, sep, after = item.partition("@")
        node = node.strip()
        try:
            kills[node] = float(after)
        except ValueError:
            sep = ""
        if not sep or not kills[node] >= 0:
            raise ConfigError(f"--kill needs NODE@SECONDS (seconds >= 0), got '{item}'")
        if node not in GRAPH_NODE_NAMES:
            close = difflib.get_close_matches(node, GRAPH_NODE_NAMES, 1)
            raise ConfigError(f"--kill {item}: no node '{node}'{f' (did you mean {close[0]}?)' if close else ''}; "
                              f"nodes: {', '.join(GRAPH_NODE_NAMES)}")
    if kills and args.composed:
        raise ConfigError("--kill needs separate processes: drop --composed")
    if not args.rate > 0 or not args.timeout > 0 or args.max_frames < 0:
        raise ConfigError(f"--rate and --timeout must be positive and --max-frames >= 0, got {args.rate}, "
                          f"{args.timeout}, {args.max_frames}")
    check_repeat(args.repeat)
    check_topics(args.topics)
    overrides = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--set needs NODE.PARAM=VALUE, got '{item}'")
        overrides[key.strip()] = yaml.safe_load(value)
    return RunOptions(
        source=source, config=args.config or guess_config(source), out_dir=args.out,
        composed=args.composed, pacing=Pacing.LIVE if args.realtime else Pacing.LOCKSTEP, rate=args.rate,
        namespace=args.namespace, domain_id=args.domain_id, max_frames=args.max_frames, repeat=args.repeat,
        repeat_forward=args.repeat_forward, bag_topics=args.topics,
        overrides=overrides, timeout_s=args.timeout, kill_after_s=kills, strict=args.strict,
        record=check_record_path(args.record) if getattr(args, "record", None) is not None else None,
        rerun=rerun_target(args), map_bundle=getattr(args, "map", None), map_mode=getattr(args, "map_mode", "mapping"))


def check_repeat(repeat: int) -> None:
    """ConfigError unless ``--repeat`` is a pass count the player takes."""
    from memgs_ros.io.repeat import MAX_PASSES

    if not 1 <= repeat <= MAX_PASSES:
        raise ConfigError(f"--repeat must be in [1, {MAX_PASSES}], got {repeat}")


def check_topics(text: str) -> None:
    """ConfigError unless ``--topics`` parses (``BagTopics.parse``)."""
    from memgs_ros.io.bag_reader import BagTopics

    BagTopics.parse(text)


def check_config(config: str, overrides: dict | None = None, source: str = "") -> dict[str, dict]:
    """The run's per-node parameters from ``config``, ``overrides`` and ``source`` (whose depth units
    the tracker is given, as the run gives them); ConfigError (before any node starts) when the
    config does not load, names a parameter no node declares or gives one a value its node would
    refuse (type, range, choices)."""
    params = node_params(build_params(RunOptions(source=source, config=config, overrides=overrides or {}),
                                      Path("map.ply")))
    check_parameters(params)
    return params


def check_out_dir(out_dir: Path) -> None:
    """DataError unless ``out_dir`` is (or can be created as) a folder."""
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise DataError(f"output folder {out_dir}: exists and is not a folder")
    try:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise DataError(f"output folder {out_dir}: {err.strerror or err}") from err


def check_inputs(source: str, config: str, max_frames: int = 0, overrides: dict | None = None,
                 out_dir: Path | None = None, repeat: int = 1, repeat_forward: bool = False,
                 bag_topics: str = "", map_bundle: Path | None = None, map_mode: str = "mapping") -> list[str]:
    """Fail before any node starts, with one line naming the file: the config must load, the
    overrides name real nodes, the source must open (a bag is scanned whole, so a truncated or
    corrupt one is found here rather than by the player in the middle of the run), a TUM folder's
    camera must be known and the output folder must be creatable (:func:`check_config`: every
    parameter named must exist); a map bundle must be whole and made with this camera, depth unit
    and tracker mode (:func:`check_map_bundle`).

    Returns the warnings to show before the run: the source's camera_info against the config's
    calibration (:func:`calibration_warning`)."""
    from memgs_ros.io.bag_reader import BagTopics
    from memgs_ros.io.repeat import RepeatedSource
    from memgs_ros.io.sources import open_source  # opening a source loads the bag readers
    from memgs_ros.io.tum import CAMERA_JSON, TumFolder

    params = check_config(config, overrides, source)  # the tracker's depth_scale as the run sets it
    configured = configured_camera(params)
    src = open_source(source, max_frames=(max_frames or None) if repeat == 1 else None,
                      default_camera=configured.camera, repeat=repeat, repeat_forward=repeat_forward,
                      topics=BagTopics.parse(bag_topics))  # a source that cannot repeat fails here
    if isinstance(src, RepeatedSource):
        src = src.source
    if isinstance(src, TumFolder) and not src.camera_origin:
        raise ConfigError(f"{src.name}: cannot tell the camera: no {CAMERA_JSON}, folder name has no "
                          f"freiburg1/2/3 and the config ({config}) gives no calibration; pass --config tum_fr1 "
                          f"(tum_fr2, tum_fr3) or write {CAMERA_JSON} (see README)")
    warning = calibration_warning(str(source), src.camera, configured, config)
    check_map_bundle(map_bundle, map_mode, params, src.camera if configured.camera is None or not configured.override
                     else configured.camera.fitted(src.camera.width, src.camera.height))
    if out_dir is not None:
        check_out_dir(out_dir)
    return [warning] if warning else []


def check_map_bundle(bundle: Path | None, mode: str, params: dict[str, dict], camera: PinholeCamera) -> None:
    """ConfigError for ``--mode localize`` without a map; BundleError (one line naming the field or
    file) for a bundle that is damaged or made with another camera, depth unit or tracker mode."""
    from memgs_ros.core.map_io.bundle import check_bundle

    if bundle is None:
        if mode == "localize":
            raise ConfigError("--mode localize needs --map BUNDLE: a map to localise in")
        return
    tracker = params.get("tracker", {})
    check_bundle(bundle, camera.as_dict(), float(tracker.get("depth_scale", 1000.0)),
                 str(tracker.get("tracker.mode", "rgbd")))


def calibration_warning(source: str, source_camera: PinholeCamera, configured: ConfiguredCamera,
                        config: str) -> str | None:
    """One line when the source's camera_info departs from the config's calibration by more than
    1 % (fx, fy, cx, cy) or in having distortion; None when they agree or the config has none.
    ConfigError when the calibration replaces camera_info but cannot fit the source's images."""
    calib = configured.camera
    if calib is None:
        return None
    try:
        fitted = calib.fitted(source_camera.width, source_camera.height)
    except DataError as err:
        if configured.override:
            raise ConfigError(f"config {config}: its calibration cannot be used for {source}: {err}") from err
        fitted = calib  # unused by the nodes; the comparison below names the size mismatch
    diffs = calibration_differences(source_camera, calib)
    if not diffs:
        return None
    rescaled = f" rescaled from {calib.width}x{calib.height}" if fitted is not calib else ""
    action = ("the nodes use the config's (camera_info_override)" if configured.override else
              "the nodes use the source's camera_info; --set tracker.camera_info_override=true uses the config's")
    return (f"{source}: camera_info ({describe_camera(source_camera)}) differs from the calibration in config "
            f"{config} ({describe_camera(fitted)}{rescaled}) by more than 1 %: {'; '.join(diffs)}; {action}")


@contextmanager
def run_log(out_dir: Path) -> Iterator[Path]:
    """Copy this process's log records into ``OUT/logs/memgs.log`` while a run lasts, so what the
    console said (warnings included) stays beside the nodes' logs."""
    path = Path(out_dir) / LOGS_DIR / RUN_LOG
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield path
    finally:
        root.removeHandler(handler)
        handler.close()


def player_error(out_dir: Path) -> str:
    """The last error the bag player logged (its log's ERROR/FATAL line without the prefix), or ''."""
    path = Path(out_dir) / LOGS_DIR / "bag_player.log"
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    errors = [line for line in lines if line.startswith(("[ERROR]", "[FATAL]"))]
    return errors[-1].split("]: ", 1)[-1].strip() if errors else ""


def print_summary(summary: RunSummary, json_path: Path | None, record: Path | None = None) -> None:
    s = summary
    print(f"source        {s.source}")
    played = f"{s.frames_played} played, " if s.frames_played else ""
    print(f"frames        {played}{s.frames} in, {s.poses} poses, {s.lost_frames} lost")
    if any(s.tracker_skipped.values()):
        print("not tracked   " + ", ".join(f"{n} {why}" for why, n in s.tracker_skipped.items() if n)
              + " (warming: came before the tracker's kernels were in; stale: dropped to catch up with the "
                "camera; busy: never delivered while the tracker worked; unpaired: colour that found no depth "
                "within max_sync_dt_s, the tracker's log says why)")
    if s.tracker_frame_cpu_ms:
        print(f"tracker CPU   {s.tracker_frame_cpu_ms:.1f} ms a frame (median, message in to pose out)")
    print(f"keyframes     {s.keyframes}")
    print(f"mapping       {s.mapping_iterations} iterations: {s.mapping_iterations_replay} while frames came, "
          f"{s.mapping_iterations_final} final; {s.keyframes_trained} of {s.keyframes} keyframes trained")
    if s.keyframe_intake_ms or s.keyframe_latency_ms:
        i, lat = s.keyframe_intake_ms, s.keyframe_latency_ms
        print(f"keyframe      intake {i.get('median', 0):.1f} ms CPU (p95 {i.get('p95', 0):.1f}); decision to first "
              f"training step {lat.get('median', 0):.0f} ms (p95 {lat.get('p95', 0):.0f})")
    if s.frame_ms:
        t = s.frame_ms
        print(f"lockstep      a frame {t['frame']:.0f} ms (median): tracker {t['tracker']:.0f} ms, mapper's "
              f"acknowledgement {t['mapper']:.0f} ms after it (training {t['training']:.0f} ms a frame); the rest "
              "is messages and handshakes")
    print(f"memory        {s.graph_memory_mb:.0f} MB for the graph: peak RSS "
          + ", ".join(f"{n} {v:.0f}" for n, v in s.peak_rss_mb.items())
          + ("" if s.cuda_peak_mb is None else f", CUDA peak {s.cuda_peak_mb:.0f}"))
    if s.cuda_peak_by_work_mb:
        by = sorted(s.cuda_peak_by_work_mb.items(), key=lambda kv: -kv[1])
        print(f"CUDA peak     set during {by[0][0]}; the highest during each kind of work (MB): "
              + ", ".join(f"{w} {v:.0f}" for w, v in by))
    print(f"Gaussians     {s.gaussians}")
    print(f"tracking      {s.tracking_fps:.1f} FPS")
    print(f"map deltas    {s.delta_messages} messages, {s.delta_bytes / 1e6:.2f} MB, "
          f"{s.delta_bytes_per_s / 1e3:.1f} kB/s")
    if s.restarts:
        print(f"faults        restarted {s.restarts}; merger resyncs {s.merger_resyncs}; "
              f"merger == mapper: {s.replica_identical}")
    if s.skipped_frames:
        print("skipped       " + ", ".join(f"{n} {kind}" for kind, n in sorted(s.skipped_frames.items()))
              + " (bad frames; --strict stops at the first)")
    print(f"wall time     {s.wall_s:.1f} s")
    if s.cpu_s:
        print("CPU time      " + ", ".join(f"{n} {v:.1f} s" for n, v in s.cpu_s.items()))
    print(f"map           {s.ply_path}")
    if s.bundle_path:
        print(f"map bundle    {s.bundle_path}")
    if s.map_bundle:
        print(f"started from  {s.map_bundle} ({s.relocalizing} frames before the first relocalised pose)")
    print(f"trajectory    {s.trajectory_path}")
    if record is not None:
        print(f"recording     {record} ({record.stat().st_size / 1e6:.1f} MB)")
    if json_path is not None:
        json_path.write_text(json.dumps(s.as_dict(), indent=2))


def print_trajectory_error(source: str, trajectory_path: str, repeat: int = 1, repeat_forward: bool = False,
                           bag_topics: str = "") -> None:
    """When the source has ground truth (TUM folders and bags, the synthetic room), print the
    tracked trajectory's ATE after an SE(3) alignment; print nothing when it has none."""
    from memgs_ros.core.metrics.trajectory import ate
    from memgs_ros.io.bag_reader import BagTopics
    from memgs_ros.io.sources import open_source
    from memgs_ros.io.tum import read_trajectory

    gt_stamps, gt_poses = open_source(source, repeat=repeat, repeat_forward=repeat_forward,
                                      topics=BagTopics.parse(bag_topics)).ground_truth()
    if not len(gt_stamps):
        return
    est_stamps, est_poses = read_trajectory(trajectory_path)
    try:
        err = ate(est_stamps, est_poses, gt_stamps, gt_poses)
    except DataError as why:  # too few poses matched in time: say so rather than fail the run
        print(f"ATE           n/a ({why})")
        return
    print(f"ATE           {err.rmse_m * 100:.2f} cm RMSE over {err.n_matched} frames "
          "(SE(3)-aligned to the ground truth)")


def run(args: argparse.Namespace) -> int:
    # The runner imports every node (rclpy, torch): only when a run starts, not for `memgs --help`.
    from memgs_ros.orchestration.pipeline import run_pipeline

    options = options_from_args(args, args.bag)
    warnings = check_inputs(options.source, options.config, options.max_frames, dict(options.overrides),
                            options.out_dir, options.repeat, options.repeat_forward, options.bag_topics,
                            options.map_bundle, options.map_mode)
    with run_log(options.out_dir):
        for warning in warnings:
            logger.warning(warning)
        summary = run_pipeline(options)
    print_summary(summary, args.json, options.record)
    if summary.poses:
        print_trajectory_error(options.source, summary.trajectory_path, options.repeat, options.repeat_forward,
                               options.bag_topics)
    if not summary.source_complete:
        cause = player_error(options.out_dir)
        print(f"memgs run: error: {options.source} failed part-way{f': {cause}' if cause else ''} (see "
              f"{Path(options.out_dir) / LOGS_DIR / 'bag_player.log'}); the map and trajectory above hold "
              "the frames played", file=sys.stderr)
        return 1
    return 0
