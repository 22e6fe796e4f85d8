"""Evaluation of a whole run (reference section 7): the paper's table for one sequence.

``evaluate(source, ...)`` replays ``source`` through the real node graph in lockstep
(:func:`memgs_ros.ros.pipeline.run_pipeline`), records the mapper's stats over time with an
observer of its own, and then scores what the run saved:

- rendering quality: the saved PLY rendered at the tracked pose of **every tracked frame**
  matched to a ground-truth image within 0.08 s, and separately at every keyframe's pose at
  insertion (``keyframes.txt``; MemGS's in-system number). Ground-truth images are undistorted
  (the map is trained on undistorted keyframes and renders with a pinhole camera) and resized
  with INTER_AREA to the **mapping resolution** (``mapping.resolution_scale`` of the run), the
  size the map was trained at; PSNR, SSIM and, when the ``lpips`` package and its cached
  weights are there, LPIPS;
- trajectory: ATE RMSE after SE(3) Umeyama alignment (Sim(3) for monocular) and rotation RMSE,
  association within 0.1 s;
- memory: on CUDA the mapper's peak ``torch.cuda.max_memory_allocated``; on CPU (no allocator
  statistic) the map's peak parameter + gradient + Adam bytes and the peak RSS of every node;
- points: the number of Gaussians in the saved PLY.

``ablation(...)`` runs the same data and seed three times: full MemGS, no merging, and no
Patch-Grid (keypoint seeds only, Photo-SLAM-like). Results are frozen dataclasses; JSON and
Markdown helpers are here, plots are the CLI's (``memgs eval``). No plotting imports here.
"""
from __future__ import annotations

import json
import logging
import math
import os
import random
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from memgs_ros.errors import ConfigError, DataError

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

__all__ = [
    "ABLATION_VARIANTS", "AblationResult", "EvalResult", "MapSample", "MemoryResult", "QualityResult",
    "TrajectoryResult", "ablation", "ablation_table", "evaluate", "markdown_row", "markdown_table",
    "mode_overrides", "result_from_dict", "score_map", "score_trajectory", "training_rate", "write_json",
]

FRAME_MATCH_MAX_DT_S = 0.08  # rendered frame <-> ground-truth image (reference section 7)
ATE_MAX_DT_S = 0.1  # estimate <-> ground-truth pose (reference section 7)
STRIP_FRAMES = 5  # rendered-vs-real frames kept for the strip plot

# Ablation variants: name -> parameter overrides on top of the run's own.
ABLATION_VARIANTS: dict[str, dict[str, Any]] = {
    "full": {},
    "no_merge": {"mapper.mapping.merge_enabled": False},
    "no_patch_grid": {"keyframe_sampler.patch_grid.enabled": False},
}
ABLATION_LABELS = {"full": "MemGS (full)", "no_merge": "w/o merging", "no_patch_grid": "w/o Patch-Grid"}


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class QualityResult:
    """Rendering quality over a set of frames (means; per-frame values in stamp order).

    stamps_ns / psnr_db_per_frame / ssim_per_frame: [F]; lpips is None unless every frame has it.
    """

    n: int
    psnr_db: float | None
    ssim: float | None
    lpips: float | None
    stamps_ns: tuple[int, ...] = ()
    psnr_db_per_frame: tuple[float, ...] = ()
    ssim_per_frame: tuple[float, ...] = ()
    # PSNR over the pixels that carry image content after undistortion (the black border of an
    # undistorted image is no observation and the mapper does not train on it); equals psnr_db
    # for cameras without distortion.
    psnr_db_valid: float | None = None
    psnr_db_valid_per_frame: tuple[float, ...] = ()


@dataclass(frozen=True)
class TrajectoryResult:
    """ATE of the tracked trajectory against ground truth (metres, degrees).

    est_xyz_aligned / gt_xyz: [n, 3] matched positions after alignment; keyframe_xyz_aligned:
    [K, 3]; stamps_ns / errors_m: [n].
    """

    sim3: bool
    rmse_m: float
    rotation_rmse_deg: float
    n_matched: int
    scale: float
    stamps_ns: tuple[int, ...] = ()
    errors_m: tuple[float, ...] = ()
    est_xyz_aligned: tuple[tuple[float, float, float], ...] = ()
    gt_xyz: tuple[tuple[float, float, float], ...] = ()
    keyframe_xyz_aligned: tuple[tuple[float, float, float], ...] = ()


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

    @property
    def headline_bytes(self) -> int:
        """The table's memory figure: CUDA peak when there is one, else the model's peak bytes."""
        return self.cuda_max_allocated_bytes if self.cuda_max_allocated_bytes is not None else self.model_bytes_peak

    @property
    def headline_kind(self) -> str:
        return "cuda_max_allocated" if self.cuda_max_allocated_bytes is not None else "model_bytes_peak (CPU)"


@dataclass(frozen=True)
class MapSample:
    """One mapper stats message: seconds since the run started, map size and memory then."""

    t_s: float
    iteration: int
    gaussians: int
    model_bytes: int
    cuda_max_allocated: int | None = None


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
        return {"variants": [r.as_dict() for r in self.results], "table": ablation_table(self.results)}


# ----------------------------------------------------------------------------- helpers


def write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as JSON atomically (temp file + rename); non-finite floats become null."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.tmp")
    tmp.write_text(json.dumps(_finite(obj), indent=2))
    os.replace(tmp, p)
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


def mode_overrides(mode: str) -> dict[str, Any]:
    """Parameter overrides that put tracker, sampler and mapper into ``mode`` (rgbd | mono)."""
    if mode not in ("rgbd", "mono"):
        raise ConfigError(f"mode must be 'rgbd' or 'mono', got {mode!r}")
    return {"tracker.tracker.mode": mode, "keyframe_sampler.mode": mode, "mapper.mode": mode}


def _run_params(out_dir: Path) -> dict[str, dict[str, Any]]:
    """The effective per-node parameters the run used (``params.yaml`` written by run_pipeline)."""
    import yaml

    path = out_dir / "params.yaml"
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise DataError(f"could not read the run's parameters {path}: {err}") from err
    return {key.rsplit("/", 1)[-1]: dict((v or {}).get("ros__parameters", {})) for key, v in raw.items()}


def _quality(stamps: list[int], scores: Sequence[Any], psnr_valid: Sequence[float]) -> QualityResult:
    from memgs_ros.core.metrics import summarize_scores

    s = summarize_scores(scores)
    pv = np.asarray(psnr_valid, dtype=np.float64)
    finite = np.isfinite(pv)
    return QualityResult(
        n=int(s["n"]), psnr_db=s["psnr_db"], ssim=s["ssim"], lpips=s["lpips"],
        stamps_ns=tuple(int(t) for t in stamps),
        psnr_db_per_frame=tuple(float(x.psnr_db) for x in scores),
        ssim_per_frame=tuple(float(x.ssim) for x in scores),
        psnr_db_valid=float(pv[finite].mean()) if finite.any() else None,
        psnr_db_valid_per_frame=tuple(float(v) for v in pv))


def _masked_psnr(render: Any, gt: Any, mask: Any) -> float:
    """PSNR over the pixels where ``mask`` [H, W] is true; render / gt: [3, H, W] in [0, 1]."""
    import torch

    if mask is None:
        mse = float(torch.mean((render.double() - gt.double()) ** 2))
    else:
        m = mask.to(render.device)
        n = int(m.sum())
        if n == 0:
            return math.nan
        mse = float(((render.double() - gt.double()) ** 2)[:, m].sum()) / (3 * n)
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def training_rate(samples: Sequence[MapSample]) -> float | None:
    """Mapping iterations per second while training ran: from the first sample with a positive
    iteration count to the first sample at the final count (None with fewer than 2 such samples)."""
    active = [m for m in samples if m.iteration > 0]
    if len(active) < 2:
        return None
    final = max(m.iteration for m in active)
    end = next(m for m in active if m.iteration == final)
    start = active[0]
    if end.t_s <= start.t_s:
        return None
    return (end.iteration - start.iteration) / (end.t_s - start.t_s)


# ----------------------------------------------------------------------------- scoring


def _ground_truth_images(source: str, max_frames: int, scale: float
                         ) -> tuple[np.ndarray, list[np.ndarray], Any, Any, np.ndarray | None]:
    """Undistorted ground-truth images at the mapping resolution.

    Returns (stamps_ns [G], images G x [h, w, 3] uint8, render camera (pinhole, scaled),
    the source (for its ground-truth trajectory), valid-pixel mask [h, w] bool or None when the
    camera has no distortion).
    """
    from memgs_ros.core.view import view_preparation
    from memgs_ros.io.sources import open_source

    src = open_source(source, with_depth=False, max_frames=max_frames or None)
    view = view_preparation(src.camera, scale)  # the mapper's own preparation of its keyframes
    stamps: list[int] = []
    images: list[np.ndarray] = []
    for frame in src:
        stamps.append(int(frame.stamp_ns))
        images.append(view(frame.rgb)[0])
    cam, mask = view.camera, view.valid_mask
    return np.asarray(stamps, dtype=np.int64), images, cam, src, mask


def score_map(ply_path: str | os.PathLike[str],
              pose_sets: Mapping[str, tuple[np.ndarray, np.ndarray]],  # name -> (stamps [M], T_wc [M, 4, 4])
              gt_stamps_ns: np.ndarray,  # [G]
              gt_images: Sequence[np.ndarray],  # G x [h, w, 3] uint8, undistorted, mapping resolution
              camera: Any,  # PinholeCamera of the renders (pinhole, mapping resolution)
              background: Sequence[float] = (0.0, 0.0, 0.0),
              device: str = "cpu", use_lpips: bool = True, progress: bool = True,
              strip_from: str | None = None, strip_frames: int = STRIP_FRAMES,
              valid_mask: np.ndarray | None = None,  # [h, w] bool: pixels with image content
              ) -> tuple[dict[str, QualityResult], list[tuple[int, np.ndarray, np.ndarray, float]], bool]:
    """Render the saved map at every pose of each pose set that matches a ground-truth image
    within 0.08 s and score it (PSNR, SSIM, LPIPS when available; PSNR also over ``valid_mask``).

    Renders are cached by stamp, so a keyframe that is also a tracked frame is rendered once.
    Returns ({name: QualityResult}, strip [(stamp_ns, render uint8 [h, w, 3], real uint8, psnr)]
    taken evenly from ``strip_from``'s scored frames, whether LPIPS was computed).
    """
    import torch

    from memgs_ros.core.gaussians import GaussianMap
    from memgs_ros.core.geometry import invert_pose
    from memgs_ros.core.metrics import make_lpips, match_frames, score_frame
    from memgs_ros.core.ply import load_ply
    from memgs_ros.core.raster import rasterize

    records = load_ply(ply_path)
    g = GaussianMap.from_records(records, max_sh_degree=3, device=device)
    bg = torch.tensor(list(background), dtype=torch.float32, device=device)
    lpips_fn = make_lpips(device) if use_lpips else None
    jobs: dict[str, list[tuple[int, np.ndarray, int]]] = {}
    for name, (stamps, poses) in pose_sets.items():
        stamps = np.asarray(stamps, dtype=np.int64)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        finite = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))  # lost frames carry no pose
        ir, ig = match_frames(stamps[finite], gt_stamps_ns, FRAME_MATCH_MAX_DT_S)
        jobs[name] = [(int(stamps[finite[a]]), poses[finite[a]], int(b)) for a, b in zip(ir, ig)]
    total = len({(s, gi) for js in jobs.values() for s, _, gi in js})
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc="rendering", unit="frame")
    mask_t = None if valid_mask is None else torch.from_numpy(np.asarray(valid_mask, dtype=bool))
    cache: dict[tuple[int, int], Any] = {}
    cache_valid: dict[tuple[int, int], float] = {}
    renders: dict[tuple[int, int], np.ndarray] = {}
    results: dict[str, QualityResult] = {}
    try:
        for name, js in jobs.items():
            stamps_out: list[int] = []
            scores = []
            for stamp, T_wc, gi in js:
                key = (stamp, gi)
                if key not in cache:
                    T_cw = torch.from_numpy(invert_pose(T_wc)).float().to(device)
                    if len(g):
                        with torch.no_grad():
                            out = rasterize(g.means, g.quats_wxyz, g.log_scales, g.opacity_logits, g.sh_dc,
                                            g.sh_rest, T_cw, camera, sh_degree=3, background=bg)
                        color = out.color.clamp(0.0, 1.0)
                    else:  # an empty map renders the background
                        color = bg.reshape(3, 1, 1).expand(3, camera.height, camera.width)
                    gt = torch.from_numpy(gt_images[gi]).to(device).permute(2, 0, 1).float() / 255.0
                    cache[key] = score_frame(stamp, color, gt, lpips_fn)
                    cache_valid[key] = _masked_psnr(color, gt, mask_t)
                    if name == strip_from:
                        renders[key] = (color * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
                    if bar is not None:
                        bar.update(1)
                stamps_out.append(stamp)
                scores.append(cache[key])
            results[name] = _quality(stamps_out, scores, [cache_valid[(t, gi)] for t, _, gi in js])
    finally:
        if bar is not None:
            bar.close()
    strip: list[tuple[int, np.ndarray, np.ndarray, float]] = []
    if strip_from is not None and jobs.get(strip_from):
        js = jobs[strip_from]
        picks = np.unique(np.linspace(0, len(js) - 1, min(strip_frames, len(js))).round().astype(int))
        for k in picks:
            stamp, _, gi = js[int(k)]
            key = (stamp, gi)
            if key in renders:
                strip.append((stamp, renders[key], gt_images[gi], float(cache[key].psnr_db)))
    return results, strip, lpips_fn is not None


def score_trajectory(trajectory_path: str | os.PathLike[str], gt_stamps_ns: np.ndarray,  # [K]
                     gt_T_wc: np.ndarray,  # [K, 4, 4]
                     sim3: bool, keyframes_path: str | os.PathLike[str] | None = None) -> TrajectoryResult:
    """ATE (SE(3), or Sim(3) when ``sim3``) of a TUM trajectory file against ground truth,
    association within 0.1 s. Raises DataError when fewer than 3 poses match."""
    from memgs_ros.core.trajectory import ate
    from memgs_ros.io.tum import read_trajectory

    stamps, poses = read_trajectory(trajectory_path)
    res = ate(stamps, poses, gt_stamps_ns, gt_T_wc, max_dt_s=ATE_MAX_DT_S, sim3=sim3)
    est = res.alignment.apply(poses[res.est_index, :3, 3])
    gt = np.asarray(gt_T_wc)[res.gt_index, :3, 3]
    kf_xyz: np.ndarray = np.zeros((0, 3))
    if keyframes_path is not None and Path(keyframes_path).is_file():
        try:
            _, kf_poses = read_trajectory(keyframes_path)
            kf_xyz = res.alignment.apply(kf_poses[:, :3, 3]) if len(kf_poses) else kf_xyz
        except DataError:
            pass

    def rows(a: np.ndarray) -> tuple[tuple[float, float, float], ...]:
        return tuple((float(x), float(y), float(z)) for x, y, z in np.asarray(a).reshape(-1, 3))

    return TrajectoryResult(
        sim3=sim3, rmse_m=res.rmse_m, rotation_rmse_deg=res.rotation_rmse_deg, n_matched=res.n_matched,
        scale=float(res.alignment.s), stamps_ns=tuple(int(s) for s in res.stamps_ns),
        errors_m=tuple(float(e) for e in res.errors_m), est_xyz_aligned=rows(est), gt_xyz=rows(gt),
        keyframe_xyz_aligned=rows(kf_xyz))


# ----------------------------------------------------------------------------- stats observer


def _child_node_peaks_mb() -> dict[str, float]:
    """Peak RSS (VmHWM, MB) of this process's node children, by node name (Linux /proc; {} elsewhere).

    VmHWM belongs to the address space made by execve, unlike ``ru_maxrss``, which Linux carries
    over from the parent across fork and execve (a node started by a process that once held
    500 MB reports at least 500 MB).
    """
    peaks: dict[str, float] = {}
    me = str(os.getpid())
    try:
        pids = [p for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return peaks
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                stat = f.read()
            if stat[stat.rindex(")") + 2:].split()[1] != me:  # field 4: ppid
                continue
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
            module = next((a.decode() for a in argv if a.startswith(b"memgs_ros.nodes.")), None)
            if module is None:
                continue
            with open(f"/proc/{pid}/status") as f:
                hwm = next((line.split()[1] for line in f if line.startswith("VmHWM:")), None)
        except (OSError, ValueError, IndexError):
            continue  # the process ended while we looked
        if hwm is not None:
            name = module.rsplit(".", 1)[-1]
            peaks[name] = max(peaks.get(name, 0.0), int(hwm) / 1024.0)
    return peaks


class _StatsRecorder:
    """Records ``memgs/mapper/stats`` over the run from an rclpy context of its own (the
    pipeline's observer keeps only the latest message). Use as a context manager.

    With ``domain_id`` None it picks a DDS domain nobody else is using: on a machine where
    other runs and tests start graphs on random domains, a shared domain mixes two graphs
    (seen: another run's camera_info reached this run's tracker). A candidate is taken when
    no other node shows up on it within ``probe_s``.
    """

    # Outside 100..199, where the tests' fixture and run_pipeline draw their random domains.
    CANDIDATE_DOMAINS = tuple(range(1, 100)) + tuple(range(200, 233))

    def __init__(self, domain_id: int | None, namespace: str = "", probe_s: float = 1.5,
                 max_probes: int = 8) -> None:
        self.requested_domain = domain_id
        self.domain_id = -1
        self.namespace = namespace
        self.probe_s = probe_s
        self.max_probes = max_probes
        self.samples: list[MapSample] = []
        self.last: dict[str, str] = {}
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._context: Any = None
        self._executor: Any = None
        self._thread: threading.Thread | None = None
        self.node_peak_rss_mb: dict[str, float] = {}
        self._rss_stop = threading.Event()
        self._rss_thread: threading.Thread | None = None

    def _sample_rss(self) -> None:
        while not self._rss_stop.wait(1.0):
            for name, mb in _child_node_peaks_mb().items():
                with self._lock:
                    self.node_peak_rss_mb[name] = max(self.node_peak_rss_mb.get(name, 0.0), round(mb, 1))

    def __enter__(self) -> _StatsRecorder:
        self._rss_thread = threading.Thread(target=self._sample_rss, name="eval-rss", daemon=True)
        self._rss_thread.start()
        if self.requested_domain is not None:
            self._start(self.requested_domain)
            return self
        rng = random.Random()
        candidates = rng.sample(self.CANDIDATE_DOMAINS, self.max_probes)
        for k, domain in enumerate(candidates):
            self._start(domain)
            time.sleep(self.probe_s)  # DDS discovery on one host takes well under a second
            others = [n for n, _ in self._node.get_node_names_and_namespaces() if n != self._node.get_name()]
            if not others or k == len(candidates) - 1:
                if others:
                    logger.warning("every probed DDS domain was busy; using %d (nodes seen: %s)", domain,
                                   ", ".join(sorted(set(others))[:5]))
                break
            logger.info("DDS domain %d is in use (%s); trying another", domain, ", ".join(sorted(set(others))[:3]))
            self._stop()
        self._t0 = time.monotonic()
        return self

    def _start(self, domain: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions

        from memgs_ros.ros import qos
        from memgs_ros.ros.diagnostics import stats_values

        self.domain_id = int(domain)
        self._t0 = time.monotonic()
        self._context = rclpy.Context()
        # The pipeline's own context handles signals; this one only listens.
        rclpy.init(args=None, context=self._context, domain_id=self.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        node = Node("memgs_eval_recorder", namespace=self.namespace or None, context=self._context)
        self._node = node

        def on_stats(msg: DiagnosticArray) -> None:
            v = stats_values(msg)
            if "gaussians" not in v:
                return  # before training starts the mapper has no map gauges

            def num(key: str) -> int:
                try:
                    return int(float(v.get(key, 0)))
                except ValueError:
                    return 0

            sample = MapSample(t_s=round(time.monotonic() - self._t0, 3), iteration=num("iteration"),
                               gaussians=num("gaussians"), model_bytes=num("model_bytes"),
                               cuda_max_allocated=num("cuda_max_allocated") if "cuda_max_allocated" in v else None)
            with self._lock:
                self.samples.append(sample)
                self.last = v

        node.create_subscription(DiagnosticArray, "memgs/mapper/stats", on_stats, qos.reliable(5))
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(node)
        self._thread = threading.Thread(target=self._executor.spin, name="eval-stats", daemon=True)
        self._thread.start()

    def _stop(self) -> None:
        import rclpy

        if self._executor is not None:
            self._executor.shutdown(timeout_sec=2.0)
            for node in list(self._executor.get_nodes()):
                node.destroy_node()
            self._executor = None
        if self._context is not None:
            rclpy.try_shutdown(context=self._context)
            self._context = None
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def __exit__(self, *exc: object) -> None:
        self._rss_stop.set()
        if self._rss_thread is not None:
            self._rss_thread.join(timeout=5.0)
        self._stop()


# ----------------------------------------------------------------------------- evaluate


def evaluate(source: str, config: str = "synthetic", mode: str = "rgbd",
             resolution_scale: float | None = None, seed: int = 0,
             out_dir: str | os.PathLike[str] = "memgs_eval",
             overrides: Mapping[str, Any] | None = None, *, max_frames: int = 0,
             domain_id: int | None = None, namespace: str = "", timeout_s: float = 3600.0,
             single_process: bool = False, variant: str = "full", use_lpips: bool = True,
             device: str | None = None, progress: bool = True) -> EvalResult:
    """Run the graph on ``source`` in lockstep and score the run (module docstring).

    resolution_scale: mapping resolution (``mapper.mapping.resolution_scale``); None keeps the
    config's. seed: seeds the mapper and the Patch-Grid sampler (and the tracker's RANSAC).
    overrides: "node.param" -> value, applied after mode/scale/seed. domain_id: DDS domain of
    the run; None probes for one no other node is using (outside 100..199). device: where the
    evaluation renders (default CUDA when available, else CPU; the mapper picks its own). On
    CPU, call :func:`memgs_ros.core.runtime.configure_cpu_runtime` first (the CLI does): with
    OpenMP threads on a shared machine each render is ~30x slower.
    Writes ``out_dir/eval.json`` and ``out_dir/strip.npz`` besides the run's own outputs.
    """
    import torch

    from memgs_ros.ros.pipeline import RunOptions, run_pipeline

    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_overrides: dict[str, Any] = dict(mode_overrides(mode))
    run_overrides.update({"mapper.mapping.seed": int(seed), "keyframe_sampler.patch_grid.seed": int(seed),
                          "tracker.tracker.seed": int(seed)})
    if resolution_scale is not None:
        if not (resolution_scale > 0):
            raise ConfigError(f"resolution_scale must be positive, got {resolution_scale}")
        run_overrides["mapper.mapping.resolution_scale"] = float(resolution_scale)
    run_overrides.update(dict(overrides or {}))
    with _StatsRecorder(domain_id, namespace) as recorder:
        options = RunOptions(source=str(source), config=config, out_dir=out, single_process=single_process,
                             lockstep=True, namespace=namespace, domain_id=recorder.domain_id,
                             max_frames=int(max_frames), overrides=run_overrides, timeout_s=timeout_s)
        summary = run_pipeline(options, progress=progress)
        time.sleep(0.2)
    with recorder._lock:
        samples = tuple(recorder.samples)
        last = dict(recorder.last)
        node_rss = dict(recorder.node_peak_rss_mb)

    t_eval = time.monotonic()
    params = _run_params(out)
    mapper_params = params.get("mapper", {})
    scale = float(mapper_params.get("mapping.resolution_scale", 1.0))
    background = tuple(float(v) for v in mapper_params.get("mapping.background", (0.0, 0.0, 0.0)))
    notes: list[str] = []
    if not summary.ply_path or not Path(summary.ply_path).is_file():
        raise DataError(f"the run saved no map (ply path {summary.ply_path!r}); see {out / 'logs'}")
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    gt_stamps, gt_images, camera, src, valid_mask = _ground_truth_images(str(source), int(max_frames), scale)
    from memgs_ros.io.tum import read_trajectory

    traj_stamps, traj_poses = read_trajectory(summary.trajectory_path)
    kf_path = out / "keyframes.txt"
    kf_stamps, kf_poses = (read_trajectory(kf_path) if kf_path.is_file()
                           else (np.zeros(0, np.int64), np.zeros((0, 4, 4))))
    quality, strip, lpips_ok = score_map(
        summary.ply_path, {"frames": (traj_stamps, traj_poses), "keyframes": (kf_stamps, kf_poses)},
        gt_stamps, gt_images, camera, background=background, device=device, use_lpips=use_lpips,
        progress=progress, strip_from="frames", valid_mask=valid_mask)
    strip_path = ""
    if strip:
        strip_path = str(out / "strip.npz")
        np.savez_compressed(strip_path, stamps_ns=np.array([s[0] for s in strip], dtype=np.int64),
                            renders=np.stack([s[1] for s in strip]), reals=np.stack([s[2] for s in strip]),
                            psnr_db=np.array([s[3] for s in strip]))
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
    from memgs_ros.core.ply import load_ply

    n_ply = len(load_ply(summary.ply_path).ids)
    cuda_peak = None
    if "cuda_max_allocated" in last:
        cuda_peak = int(float(last["cuda_max_allocated"]))
    mapper_device = "cuda" if cuda_peak is not None else "cpu"
    if cuda_peak is None:
        notes.append("memory: the mapper ran on CPU, where torch has no allocator peak; the table's "
                     "memory is the map's peak parameters + gradients + Adam bytes (model_bytes_peak)")
    if node_rss:
        rss, rss_source = node_rss, "VmHWM of each node process, sampled at 1 Hz by memgs eval"
    else:
        rss = {k: float(v) for k, v in summary.peak_rss_mb.items()}
        rss_source = "node stats (ru_maxrss: on Linux it includes the parent's peak at spawn)"
    memory = MemoryResult(mapper_device=mapper_device, cuda_max_allocated_bytes=cuda_peak,
                          model_bytes_peak=int(summary.model_bytes_peak), peak_rss_mb=rss,
                          peak_rss_source=rss_source,
                          peak_rss_mb_node_stats={k: float(v) for k, v in summary.peak_rss_mb.items()})
    if not samples:
        notes.append("no mapper stats were recorded during the run (map size over time unavailable)")
    result = EvalResult(
        variant=variant, source=str(source), config=config, mode=mode, seed=int(seed),
        resolution_scale=scale, render_size=(int(camera.width), int(camera.height)),
        overrides={k: v for k, v in run_overrides.items()}, max_frames=int(max_frames),
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


def ablation(source: str, config: str = "synthetic", mode: str = "rgbd",
             resolution_scale: float | None = None, seed: int = 0,
             out_dir: str | os.PathLike[str] = "memgs_eval",
             overrides: Mapping[str, Any] | None = None,
             variants: Sequence[str] = tuple(ABLATION_VARIANTS), **kwargs: Any) -> AblationResult:
    """``evaluate`` once per variant (same data, seed and settings), each in ``out_dir/<variant>``;
    writes ``out_dir/ablation.json``."""
    results = []
    for name in variants:
        if name not in ABLATION_VARIANTS:
            raise ConfigError(f"unknown ablation variant {name!r}; known: {', '.join(ABLATION_VARIANTS)}")
        merged = {**dict(overrides or {}), **ABLATION_VARIANTS[name]}
        logger.info("ablation variant %s (%s)", name, ", ".join(f"{k}={v}" for k, v in merged.items()) or "defaults")
        results.append(evaluate(source, config, mode, resolution_scale, seed, Path(out_dir) / name, merged,
                                variant=name, **kwargs))
    res = AblationResult(tuple(results))
    write_json(Path(out_dir) / "ablation.json", res.as_dict())
    return res


# ----------------------------------------------------------------------------- tables


def _fmt(v: float | None, spec: str) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


TABLE_HEADER = ("| method | PSNR dB / Mem GB / Points k | PSNR valid px dB | PSNR kf dB | SSIM | LPIPS | ATE cm | rot deg "
                "| track FPS | map it/s | frames | KF |\n"
                "|---|---|---|---|---|---|---|---|---|---|---|---|")
TABLE_FOOTNOTE_SPEED = ("track FPS: 1 / mean tracker time per frame; map it/s: mapping iterations per second "
                        "while training (mapper stats), whole-run rate in eval.json.")


def markdown_row(r: EvalResult, label: str | None = None) -> str:
    """One row in the paper's layout (PSNR / Mem / Points) plus SSIM, ATE and speeds. Memory is
    the CUDA peak when the mapper had a GPU, else the CPU model peak (marked ``*``)."""
    mem = r.memory.headline_bytes / 1e9
    star = "" if r.memory.cuda_max_allocated_bytes is not None else "*"
    q, k = r.frames_quality, r.keyframes_quality
    ate_cm = None if r.trajectory is None else r.trajectory.rmse_m * 100.0
    rot = None if r.trajectory is None else r.trajectory.rotation_rmse_deg
    return (f"| {label or ABLATION_LABELS.get(r.variant, r.variant)} | {_fmt(q.psnr_db, '.2f')} / {mem:.3g}{star} / "
            f"{r.gaussians / 1000:.1f} | {_fmt(q.psnr_db_valid, '.2f')} | {_fmt(k.psnr_db, '.2f')} | {_fmt(q.ssim, '.3f')} | {_fmt(q.lpips, '.3f')} "
            f"| {_fmt(ate_cm, '.2f')} | {_fmt(rot, '.2f')} | {r.tracking_fps:.1f} "
            f"| {_fmt(r.mapping_iters_per_s_training, '.2f')} "
            f"| {q.n} | {k.n} |")


def markdown_table(results: Sequence[EvalResult], labels: Sequence[str] | None = None) -> str:
    """Header plus one row per result; a footnote says what the memory column is."""
    rows = [markdown_row(r, None if labels is None else labels[i]) for i, r in enumerate(results)]
    r0 = results[0] if results else None
    foot = ""
    if r0 is not None:
        foot = (f"\nPSNR/SSIM over every tracked frame matched to ground truth within {FRAME_MATCH_MAX_DT_S} s, "
                f"rendered at the mapping resolution {r0.render_size[0]}x{r0.render_size[1]} "
                f"(scale {r0.resolution_scale:g}); 'PSNR valid px': only pixels with image content after "
                "undistortion (same as the whole image without distortion); 'PSNR kf' on keyframes only. ATE: "
                f"{'Sim(3)' if r0.mode == 'mono' else 'SE(3)'} alignment. "
                "Mem*: CPU run, map parameters + gradients + Adam state at peak (no CUDA allocator). "
                + TABLE_FOOTNOTE_SPEED)
    return TABLE_HEADER + "\n" + "\n".join(rows) + "\n" + foot + "\n"


def _pct(a: float, b: float) -> float | None:
    return None if b == 0 else 100.0 * (a - b) / b


def ablation_table(results: Sequence[EvalResult]) -> str:
    """Variants side by side with differences against the first (full MemGS): Gaussians %,
    memory %, PSNR dB (every frame and keyframes), ATE cm."""
    if not results:
        return ""
    base = results[0]
    lines = [markdown_table(results).rstrip("\n"), "",
             f"| variant | Gaussians vs {base.variant} | memory vs {base.variant} | PSNR dB | PSNR kf dB | ATE cm |",
             "|---|---|---|---|---|---|"]

    def diff(a: float | None, b: float | None, scale: float = 1.0) -> str:
        return "n/a" if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) else f"{(a - b) * scale:+.2f}"

    def ate(r: EvalResult) -> float | None:
        return None if r.trajectory is None else r.trajectory.rmse_m

    for r in results[1:]:
        g = _pct(r.gaussians, base.gaussians)
        m = _pct(r.memory.headline_bytes, base.memory.headline_bytes)
        lines.append(f"| {ABLATION_LABELS.get(r.variant, r.variant)} | {_fmt(g, '+.1f')} % | {_fmt(m, '+.1f')} % "
                     f"| {diff(r.frames_quality.psnr_db, base.frames_quality.psnr_db)} "
                     f"| {diff(r.keyframes_quality.psnr_db, base.keyframes_quality.psnr_db)} "
                     f"| {diff(ate(r), ate(base), 100.0)} |")
    return "\n".join(lines) + "\n"


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
