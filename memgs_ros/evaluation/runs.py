"""Evaluation of a run (reference section 7): the paper's table for one sequence.

The tools tier between the pure scorers (:mod:`memgs_ros.core.metrics.scoring`) and the CLI
(``memgs eval``; the tables and plots are this package's ``tables`` and ``figures``):

- :func:`evaluate_run` reads a **finished** run's files (``summary.json``, ``params.yaml``,
  ``stats_timeline.jsonl``, ``map.ply``, ``trajectory.txt``, ``keyframes.txt``; see
  :mod:`memgs_ros.orchestration.run_files`) and the source's ground truth, and scores them. It
  opens no ROS context: map size over time, the CUDA peak and each node's peak RSS come from
  the stats timeline the run recorded;
- :func:`evaluate` runs the graph on a source, every frame acknowledged (:func:`run_pipeline`) and then
  :func:`evaluate_run` on its output; :func:`ablation` does so once per variant.

What is measured:

- rendering quality: the saved PLY rendered at the tracked pose of **every tracked frame**
  matched to a ground-truth image within 0.08 s, and separately at every keyframe's pose at
  insertion (``keyframes.txt``; MemGS's in-system number). Ground-truth images go through the
  mapper's own view preparation (:func:`memgs_ros.core.geometry.view.view_preparation`: undistorted,
  resized to the **mapping resolution**); PSNR, SSIM and, when the ``lpips`` package and its
  cached weights are there, LPIPS;
- trajectory: ATE RMSE after SE(3) Umeyama alignment (Sim(3) for monocular) and rotation RMSE,
  association within 0.1 s;
- memory ("Mem", the mapper's peak working memory): on CUDA the mapper's peak
  ``torch.cuda.max_memory_allocated`` (what the paper reports); on CPU the mapper's peak
  resident memory (VmHWM, read 10 times a second) above its baseline right after start-up
  (imports, node, session and the rasterizer's compiled kernels, loaded at start-up). The map's
  peak parameter + gradient + Adam bytes ("model") and every node's peak RSS stay beside it;
- points: the number of Gaussians in the saved PLY.
"""
from __future__ import annotations

import itertools
import json
import logging
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from memgs_ros.core.gaussians.gaussian_map import GaussianMap
from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.view import view_preparation
from memgs_ros.core.map_io.ply import load_ply
from memgs_ros.core.mapping.config import MappingConfig
from memgs_ros.core.metrics import scoring
from memgs_ros.core.metrics.image import make_lpips
from memgs_ros.core.metrics.scoring import (
    ATE_MAX_DT_S,
    FRAME_MATCH_MAX_DT_S,
    STRIP_FRAMES,
    QualityResult,
    StripFrame,
    TrajectoryResult,
)
from memgs_ros.core.runtime.atomic import atomic_write
from memgs_ros.core.runtime.replay import Pacing
from memgs_ros.core.sampling import PatchGridConfig
from memgs_ros.core.tracking.config import TrackerConfig
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.evaluation.timeline import MapSample, map_samples, mapper_gauge_max, node_peak_rss_mb, training_rate
from memgs_ros.io.bag_reader import BagTopics
from memgs_ros.io.sources import open_source
from memgs_ros.io.tum import read_trajectory
from memgs_ros.nodes.params import KeyframeSamplerParams, MapperParams
from memgs_ros.orchestration.run_files import (
    KEYFRAMES_FILE,
    LOGS_DIR,
    ConfigEdit,
    ConfiguredCamera,
    RunOptions,
    RunSummary,
    configured_camera,
    edited_parameters,
    read_params,
    read_stats_timeline,
    read_summary,
)
from memgs_ros.viz import RerunTarget

logger = logging.getLogger(__name__)

__all__ = [
    "ABLATION_LABELS",
    "ABLATION_VARIANTS",
    "ATE_MAX_DT_S",
    "FRAME_MATCH_MAX_DT_S",
    "AblationResult",
    "EvalResult",
    "MemoryResult",
    "QualityResult",
    "TrajectoryResult",
    "ablation",
    "evaluate",
    "evaluate_run",
    "mode_edits",
    "result_from_dict",
    "run_edits",
    "score_map",
    "score_trajectory",
    "write_json",
]

# Ablation variants: name -> typed config changes on top of the run's own.
ABLATION_VARIANTS: dict[str, tuple[ConfigEdit[Any], ...]] = {
    "full": (),
    "no_merge": (ConfigEdit("mapper", "mapping", MappingConfig, lambda c: replace(c, merge_enabled=False)),),
    "no_patch_grid": (ConfigEdit("keyframe_sampler", "patch_grid", PatchGridConfig,
                                 lambda c: replace(c, enabled=False)),),
}
ABLATION_LABELS = {"full": "MemGS (full)", "no_merge": "w/o merging", "no_patch_grid": "w/o Patch-Grid"}
# Stats-timeline node name -> the node's name elsewhere (the player publishes as "player").
PEAK_RSS_SOURCE = "VmHWM of each node process: the peak of its 1 Hz stats (peak_rss_mb in stats_timeline.jsonl)"


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class MemoryResult:
    """Memory of the run. ``cuda_max_allocated_bytes`` is None when the mapper ran on CPU (no
    allocator statistic there); ``model_bytes_peak`` is the map's parameters + gradients + Adam
    state at its peak; ``peak_rss_mb``: per node process (``peak_rss_source`` says how measured)."""

    mapper_device: str
    cuda_max_allocated_bytes: int | None
    model_bytes_peak: int
    peak_rss_mb: dict[str, float]
    peak_rss_source: str = ""
    peak_rss_mb_node_stats: dict[str, float] = field(default_factory=dict)  # as the nodes report it
    mapper_working_peak_bytes: int | None = None  # peak RSS above the start-up baseline (CPU)
    mapper_rss_baseline_mb: float | None = None
    accounted_bytes_peak: int | None = None  # model + keyframes + step buffers (max_mapper_mbytes)
    # the whole graph as a Jetson's one memory counts it: each node process's peak RSS (the one
    # process's when composed) plus the CUDA peak
    graph_mb: float | None = None

    @property
    def headline_bytes(self) -> int:
        """The table's memory figure: the CUDA peak when there is one, else the mapper's peak
        working memory (RSS above its start-up baseline), else (older runs) the model's peak."""
        if self.cuda_max_allocated_bytes is not None:
            return self.cuda_max_allocated_bytes
        if self.mapper_working_peak_bytes is not None:
            return self.mapper_working_peak_bytes
        return self.model_bytes_peak

    @property
    def headline_kind(self) -> str:
        if self.cuda_max_allocated_bytes is not None:
            return "cuda_max_allocated"
        if self.mapper_working_peak_bytes is not None:
            return "mapper_working_peak_rss (CPU)"
        return "model_bytes_peak (CPU)"


@dataclass(frozen=True)
class EvalResult:
    """Everything ``evaluate`` measured on one run (see the module docstring)."""

    variant: str
    source: str
    config: str
    mode: str
    seed: int
    resolution_scale: float
    render_size: tuple[int, int]  # (width, height) of renders and ground truth: the mapping resolution
    overrides: dict[str, Any]
    max_frames: int
    frames: int
    poses: int
    keyframes: int
    lost_frames: int
    tracking_fps: float
    mapping_iterations: int
    mapping_iters_per_s: float  # iterations / wall time of the whole run (start-up included)
    mapping_iters_per_s_training: float | None  # from the 1 Hz mapper stats, while the count grew
    wall_s: float
    eval_s: float  # scoring time (rendering every frame)
    gaussians: int  # in the saved PLY
    gaussians_peak: int
    frames_quality: QualityResult
    keyframes_quality: QualityResult
    trajectory: TrajectoryResult | None
    memory: MemoryResult
    map_samples: tuple[MapSample, ...]
    out_dir: str
    ply_path: str
    strip_path: str  # npz with rendered and real frames for the strip plot ("" if none)
    lpips_available: bool
    notes: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["memory"]["headline_bytes"] = self.memory.headline_bytes
        d["memory"]["headline_kind"] = self.memory.headline_kind
        return d


@dataclass(frozen=True)
class AblationResult:
    """The ablation variants in order (``full`` first)."""

    results: tuple[EvalResult, ...]

    def as_dict(self) -> dict[str, Any]:
        return {"variants": [r.as_dict() for r in self.results]}


def write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as JSON atomically (the project's temp file + fsync + rename); non-finite
    floats become null."""
    p = Path(path)
    text = json.dumps(_finite(obj), indent=2)
    atomic_write(p, lambda f: f.write(text.encode("utf-8")))
    return p


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def mode_edits(mode: str) -> tuple[ConfigEdit[Any], ...]:
    """The config changes that put tracker, sampler and mapper into ``mode`` (rgbd | mono)."""
    if mode not in ("rgbd", "mono"):
        raise ConfigError(f"mode must be 'rgbd' or 'mono', got {mode!r}")
    return (ConfigEdit("tracker", "tracker", TrackerConfig, lambda c: replace(c, mode=mode)),
            ConfigEdit("keyframe_sampler", "", KeyframeSamplerParams, lambda c: replace(c, mode=mode)),
            ConfigEdit("mapper", "", MapperParams, lambda c: replace(c, mode=mode)))


def run_edits(mode: str, seed: int, resolution_scale: float | None) -> tuple[ConfigEdit[Any], ...]:
    """An evaluation's changes to the run's config: the mode, the seed of the mapper and the
    Patch-Grid sampler, and the mapping resolution (None: the config's)."""
    if resolution_scale is not None and not (resolution_scale > 0):
        raise ConfigError(f"resolution_scale must be positive, got {resolution_scale}")

    def mapping(c: MappingConfig) -> MappingConfig:
        c = replace(c, seed=int(seed))
        return c if resolution_scale is None else replace(c, resolution_scale=float(resolution_scale))

    return (*mode_edits(mode), ConfigEdit("mapper", "mapping", MappingConfig, mapping),
            ConfigEdit("keyframe_sampler", "patch_grid", PatchGridConfig, lambda c: replace(c, seed=int(seed))))


# ----------------------------------------------------------------------------- scoring


_UNCONFIGURED = ConfiguredCamera(None, False)


def _ground_truth_images(source: str, max_frames: int, scale: float,
                         configured: ConfiguredCamera = _UNCONFIGURED, repeat: int = 1, repeat_forward: bool = False,
                         bag_topics: str = "",
                         ) -> tuple[np.ndarray, list[np.ndarray], PinholeCamera, Any, np.ndarray | None]:
    """Ground-truth images prepared as the mapper prepares its keyframes, with the camera the
    run's tracker used: the configured calibration when it overrode camera_info, else the source's.

    Returns (stamps_ns [G], images G x [h, w, 3] uint8, render camera (pinhole, scaled),
    the source (for its ground-truth trajectory), valid-pixel mask [h, w] bool or None when the
    camera has no distortion).
    """
    # ``max_frames`` caps the frames played: under ``repeat`` those of all passes together.
    src = open_source(source, with_depth=False, max_frames=(max_frames or None) if repeat == 1 else None,
                      default_camera=configured.camera, repeat=repeat, repeat_forward=repeat_forward,
                      topics=BagTopics.parse(bag_topics))
    camera = src.camera
    if configured.override and configured.camera is not None:
        camera = configured.camera.fitted(camera.width, camera.height)
    view = view_preparation(camera, scale)
    stamps: list[int] = []
    images: list[np.ndarray] = []
    for frame in itertools.islice(src, max_frames or None):
        stamps.append(int(frame.stamp_ns))
        images.append(view(frame.rgb)[0])
    return np.asarray(stamps, dtype=np.int64), images, view.camera, src, view.valid_mask


def score_map(ply_path: str | os.PathLike[str],
              pose_sets: Mapping[str, tuple[np.ndarray, np.ndarray]],  # name -> (stamps [M], T_wc [M, 4, 4])
              gt_stamps_ns: np.ndarray,  # [G]
              gt_images: Sequence[np.ndarray],  # G x [h, w, 3] uint8, prepared, mapping resolution
              camera: PinholeCamera,  # of the renders (pinhole, mapping resolution)
              background: Sequence[float] = (0.0, 0.0, 0.0),
              device: str = "cpu", use_lpips: bool = True, progress: bool = True,
              strip_from: str | None = None, strip_frames: int = STRIP_FRAMES,
              valid_mask: np.ndarray | None = None,  # [h, w] bool: pixels with image content
              ) -> tuple[dict[str, QualityResult], list[StripFrame], bool]:
    """:func:`memgs_ros.core.metrics.scoring.score_map` on the map saved at ``ply_path`` (DataError
    naming the file when it cannot be read), with a progress bar and LPIPS when available.
    Returns ({name: QualityResult}, strip frames, whether LPIPS was computed)."""
    gmap = GaussianMap.from_records(load_ply(ply_path), max_sh_degree=3, device=device)
    lpips_fn = make_lpips(device) if use_lpips else None
    bar: tqdm | None = None

    def on_frame(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc="rendering", unit="frame", disable=None)  # quiet off a terminal
        bar.update(done - bar.n)

    try:
        quality, strip = scoring.score_map(
            gmap, pose_sets, gt_stamps_ns, gt_images, camera, background=background, lpips_fn=lpips_fn,
            valid_mask=valid_mask, strip_from=strip_from, strip_frames=strip_frames,
            progress=on_frame if progress else None)
    finally:
        if bar is not None:
            bar.close()
    return quality, strip, lpips_fn is not None


def score_trajectory(trajectory_path: str | os.PathLike[str], gt_stamps_ns: np.ndarray,  # [K]
                     gt_T_wc: np.ndarray,  # [K, 4, 4]
                     sim3: bool, keyframes_path: str | os.PathLike[str] | None = None) -> TrajectoryResult:
    """:func:`memgs_ros.core.metrics.scoring.score_trajectory` of a TUM trajectory file (and, for the
    plot, the keyframe poses in ``keyframes_path`` when it is readable). Raises DataError when
    fewer than 3 poses match."""
    stamps, poses = read_trajectory(trajectory_path)
    kf_poses = None
    if keyframes_path is not None and Path(keyframes_path).is_file():
        try:
            kf_poses = read_trajectory(keyframes_path)[1]
        except DataError:
            kf_poses = None  # the keyframe markers are a plot detail; the ATE stands without them
    return scoring.score_trajectory(stamps, poses, gt_stamps_ns, gt_T_wc, sim3, kf_poses)


# ----------------------------------------------------------------------------- a finished run


def evaluate_run(out_dir: str | os.PathLike[str], source: str | None = None, mode: str = "rgbd", *,
                 variant: str = "full", config: str = "", seed: int = 0,
                 overrides: Mapping[str, Any] | None = None, max_frames: int = 0,
                 use_lpips: bool = True, device: str | None = None, progress: bool = True) -> EvalResult:
    """Score the finished run in ``out_dir`` against ``source``'s ground truth (module docstring).

    source: None takes the one the run played (its summary). mode: "mono" aligns the trajectory
    in Sim(3). config / seed / overrides / max_frames are recorded in the result as given (the
    run's effective parameters are in its ``params.yaml``). device: where the renders run
    (default CUDA when available). Opens no ROS context. Writes ``out_dir/eval.json`` and
    ``out_dir/strip.npz``.
    """
    t_eval = time.monotonic()
    out = Path(out_dir).resolve()
    summary: RunSummary = read_summary(out)
    source = summary.source if source is None else str(source)
    run_params = read_params(out)
    mapper_params = run_params.get("mapper", {})
    scale = float(mapper_params.get("mapping.resolution_scale", 1.0))
    background = tuple(float(v) for v in mapper_params.get("mapping.background", (0.0, 0.0, 0.0)))
    timeline = read_stats_timeline(out)
    notes: list[str] = []
    if not summary.ply_path or not Path(summary.ply_path).is_file():
        raise DataError(f"the run saved no map (ply path {summary.ply_path!r}); see {out / LOGS_DIR}")
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    gt_stamps, gt_images, camera, src, valid_mask = _ground_truth_images(
        source, int(max_frames), scale, configured_camera(run_params), summary.repeat, summary.repeat_forward,
        summary.bag_topics)
    traj_stamps, traj_poses = read_trajectory(summary.trajectory_path)
    kf_path = out / KEYFRAMES_FILE
    kf_stamps, kf_poses = (read_trajectory(kf_path) if kf_path.is_file()
                           else (np.zeros(0, np.int64), np.zeros((0, 4, 4))))
    quality, strip, lpips_ok = score_map(
        summary.ply_path, {"frames": (traj_stamps, traj_poses), "keyframes": (kf_stamps, kf_poses)},
        gt_stamps, gt_images, camera, background=background, device=device, use_lpips=use_lpips,
        progress=progress, strip_from="frames", valid_mask=valid_mask)
    strip_path = _save_strip(out, strip)
    trajectory: TrajectoryResult | None = None
    gt_s, gt_T = src.ground_truth()
    if len(gt_s):
        try:
            trajectory = score_trajectory(summary.trajectory_path, gt_s, gt_T, sim3=(mode == "mono"),
                                          keyframes_path=kf_path)
        except DataError as err:
            notes.append(f"no ATE: {err}")
    else:
        notes.append("no ATE: the source has no ground-truth trajectory")
    n_ply = len(load_ply(summary.ply_path).ids)
    samples = map_samples(timeline)
    memory = _memory_result(summary, timeline, samples, notes)
    if not samples:
        notes.append("no mapper stats were recorded during the run (map size over time unavailable)")
    result = EvalResult(
        variant=variant, source=source, config=config, mode=mode, seed=int(seed),
        resolution_scale=scale, render_size=(int(camera.width), int(camera.height)),
        overrides=dict(overrides or {}), max_frames=int(max_frames),
        frames=int(summary.frames), poses=int(summary.poses), keyframes=int(summary.keyframes),
        lost_frames=int(summary.lost_frames), tracking_fps=float(summary.tracking_fps),
        mapping_iterations=int(summary.mapping_iterations),
        mapping_iters_per_s=summary.mapping_iterations / summary.wall_s if summary.wall_s > 0 else 0.0,
        mapping_iters_per_s_training=training_rate(samples),
        wall_s=float(summary.wall_s), eval_s=time.monotonic() - t_eval, gaussians=n_ply,
        gaussians_peak=int(summary.gaussians_peak), frames_quality=quality["frames"],
        keyframes_quality=quality["keyframes"], trajectory=trajectory, memory=memory, map_samples=samples,
        out_dir=str(out), ply_path=str(summary.ply_path), strip_path=strip_path, lpips_available=lpips_ok,
        notes=tuple(notes))
    write_json(out / "eval.json", result.as_dict())
    return result


def _save_strip(out: Path, strip: Sequence[tuple[int, np.ndarray, np.ndarray, float]]) -> str:
    """strip.npz: the frame strip's stamps, renders, real images and PSNR ("" when empty)."""
    if not strip:
        return ""
    path = str(out / "strip.npz")
    np.savez_compressed(path, stamps_ns=np.array([s[0] for s in strip], dtype=np.int64),
                        renders=np.stack([s[1] for s in strip]), reals=np.stack([s[2] for s in strip]),
                        psnr_db=np.array([s[3] for s in strip]))
    return path


def _memory_result(summary: RunSummary, timeline: Sequence[Mapping[str, Any]], samples: Sequence[MapSample],
                   notes: list[str]) -> MemoryResult:
    """The memory figures of a run: the CUDA peak or, on CPU, the mapper's working peak; every node's
    peak RSS from the timeline (the summary's last stats where the timeline has none)."""
    cuda_peak = next((m.cuda_max_allocated for m in reversed(samples) if m.cuda_max_allocated is not None), None)
    working = mapper_gauge_max(timeline, "working_peak_mb")
    baseline = mapper_gauge_max(timeline, "rss_baseline_mb")
    accounted = mapper_gauge_max(timeline, "accounted_bytes_peak")
    if cuda_peak is None:
        notes.append("memory: the mapper ran on CPU, where torch has no allocator peak; the table's "
                     + ("memory is the mapper's peak RSS above its start-up baseline" if working is not None
                        else "memory is the map's peak parameters + gradients + Adam bytes (model_bytes_peak)"))
    node_stats_rss = {k: float(v) for k, v in summary.peak_rss_mb.items()}
    rss = node_peak_rss_mb(timeline)
    rss_source = PEAK_RSS_SOURCE
    if not rss:
        rss, rss_source = node_stats_rss, "VmHWM of each node process: its last stats message (run summary)"
    return MemoryResult(mapper_device="cpu" if cuda_peak is None else "cuda", cuda_max_allocated_bytes=cuda_peak,
                        model_bytes_peak=int(summary.model_bytes_peak), peak_rss_mb=rss,
                        peak_rss_source=rss_source, peak_rss_mb_node_stats=node_stats_rss,
                        mapper_working_peak_bytes=None if working is None else int(working * 2**20),
                        mapper_rss_baseline_mb=baseline,
                        accounted_bytes_peak=None if accounted is None else int(accounted),
                        graph_mb=summary.graph_memory_mb or None)


# ----------------------------------------------------------------------------- run, then score


def evaluate(source: str, config: str = "synthetic", mode: str = "rgbd",
             resolution_scale: float | None = None, seed: int = 0,
             out_dir: str | os.PathLike[str] = "memgs_eval",
             overrides: Mapping[str, Any] | None = None, *, max_frames: int = 0, repeat: int = 1,
             repeat_forward: bool = False,
             domain_id: int | None = None, namespace: str = "", timeout_s: float = 3600.0,
             composed: bool = False, variant: str = "full", use_lpips: bool = True,
             device: str | None = None, progress: bool = True, record: Path | None = None,
             rerun: RerunTarget | None = None, map_bundle: Path | None = None,
             map_mode: str = "mapping", edits: Sequence[ConfigEdit[Any]] = ()) -> EvalResult:
    """Run the graph on ``source``, every frame acknowledged (from ``map_bundle`` in ``map_mode`` when given),
    then :func:`evaluate_run` on its output.

    resolution_scale: mapping resolution (``mapper.mapping.resolution_scale``); None keeps the
    config's. seed: seeds the mapper and the Patch-Grid sampler (and the tracker's RANSAC).
    repeat: the source played this many times, every other pass backward (``open_source``).
    edits: typed config changes (``ConfigEdit``), applied after mode/scale/seed; overrides:
    "node.param" -> value (a user's ``--set``), applied last. domain_id: DDS domain of
    the run; None lets the run pick a free one. record: also record the run's output topics into
    this .mcap file. rerun: stream the run to Rerun (see RunOptions). device: where the evaluation
    renders. On CPU,
    call :func:`memgs_ros.core.runtime.cpu.configure_cpu_runtime` first (the CLI does): with OpenMP
    threads on a shared machine each render is ~30x slower.
    """
    # Only running needs rclpy and the nodes; scoring a finished run (evaluate_run) does not.
    from memgs_ros.orchestration.pipeline import run_pipeline

    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    all_edits = (*run_edits(mode, seed, resolution_scale), *edits)
    options = RunOptions(source=str(source), config=config, out_dir=out, composed=composed,
                         pacing=Pacing.LOCKSTEP, namespace=namespace, domain_id=domain_id,
                         max_frames=int(max_frames), repeat=int(repeat), repeat_forward=bool(repeat_forward),
                         edits=all_edits, overrides=dict(overrides or {}), timeout_s=timeout_s,
                         record=record, rerun=rerun, map_bundle=map_bundle, map_mode=map_mode)
    run_pipeline(options, progress=progress)
    changed = {**edited_parameters(config, all_edits), **dict(overrides or {})}  # what the run changed, as parameters
    return evaluate_run(out, str(source), mode, variant=variant, config=config, seed=seed,
                        overrides=changed, max_frames=max_frames, use_lpips=use_lpips,
                        device=device, progress=progress)


def ablation(source: str, config: str = "synthetic", mode: str = "rgbd",
             resolution_scale: float | None = None, seed: int = 0,
             out_dir: str | os.PathLike[str] = "memgs_eval",
             overrides: Mapping[str, Any] | None = None,
             variants: Sequence[str] = tuple(ABLATION_VARIANTS), **kwargs: Any) -> AblationResult:
    """``evaluate`` once per variant (same data, seed and settings), each in ``out_dir/<variant>``."""
    results = []
    for name in variants:
        if name not in ABLATION_VARIANTS:
            raise ConfigError(f"unknown ablation variant {name!r}; known: {', '.join(ABLATION_VARIANTS)}")
        variant_edits = ABLATION_VARIANTS[name]
        changed = edited_parameters(config, variant_edits)
        logger.info("ablation variant %s (%s)", name, ", ".join(f"{k}={v}" for k, v in changed.items()) or "defaults")
        rerun = kwargs.get("rerun")
        per_variant = {**kwargs, "rerun": rerun.for_variant(name)} if rerun is not None else kwargs
        results.append(evaluate(source, config, mode, resolution_scale, seed, Path(out_dir) / name, overrides,
                                variant=name, edits=variant_edits, **per_variant))
    return AblationResult(tuple(results))


def result_from_dict(d: Mapping[str, Any]) -> EvalResult:
    """Rebuild an EvalResult from ``as_dict()`` / eval.json (for re-plotting a saved run)."""
    d = dict(d)
    mem = dict(d["memory"])
    mem.pop("headline_bytes", None)
    mem.pop("headline_kind", None)

    def quality(q: Mapping[str, Any]) -> QualityResult:
        return QualityResult(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in q.items()})

    traj = d.get("trajectory")
    if traj is not None:
        traj = TrajectoryResult(**{k: (tuple(tuple(x) if isinstance(x, list) else x for x in v)
                                       if isinstance(v, list) else v) for k, v in traj.items()})
    d.update(frames_quality=quality(d["frames_quality"]), keyframes_quality=quality(d["keyframes_quality"]),
             trajectory=traj, memory=MemoryResult(**mem),
             map_samples=tuple(MapSample(**s) for s in d.get("map_samples", [])),
             render_size=tuple(d["render_size"]), notes=tuple(d.get("notes", ())))
    return EvalResult(**d)
