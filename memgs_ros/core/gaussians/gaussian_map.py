"""The Gaussian map: leaf parameters, per-Gaussian side arrays and the Adam optimiser, in step.

Two types live here:

- ``GaussianRecords`` (defined in ``core/gaussians/records.py``, which imports no torch, re-exported here):
  a frozen plain-numpy record of N Gaussians whose fields are named as the INRIA 3DGS PLY
  (reference section 10). PLY files, map deltas and the merger's replica all use it.
- ``GaussianMap``: the trainable map. Parameters are stored pre-activation (log scales, opacity
  logits, unnormalised w-first quaternions, SH coefficients). Every grow/shrink of the map goes
  through one private helper, ``_resize``, that edits parameters, Adam moments and side arrays
  together, so the optimiser is never rebuilt and no row can fall out of step.

Row order and ids: ``ids`` are unique and never reused (a monotonic ``next_id``). New rows are
appended and removal keeps the order of the survivors, so ``ids`` is always strictly increasing;
``index_of`` relies on that.

Side arrays (all ``[N]`` tensors on the map's device, stable names for other modules):

- ``ids`` int64: the Gaussian's id.
- ``keyframe_ids`` int64: id of the keyframe that created it (-1 when unknown, e.g. loaded maps).
- ``created_iter`` int64: mapper iteration at creation.
- ``densify_grad_sum`` float32 / ``densify_count`` int64: sum of the view-space (NDC-scaled) 2D
  positional gradient norm and the number of renders it was visible in (3DGS densification).
- ``merge_grad_sum`` float32 / ``merge_count`` int64: sum of the 3D positional gradient norm and
  the number of renders it was visible in (MemGS merge candidates, reference section 4). Use
  ``merge_grad_mean()``; an unseen Gaussian has mean 0.
- ``max_radii2d`` float32: the largest screen radius (pixels) seen since the last densification.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from memgs_ros.core.gaussians.learning_rates import GaussianLearningRates
from memgs_ros.core.gaussians.map_records import RecordsIO
from memgs_ros.core.gaussians.records import PLY_F_REST, SH_C0, GaussianRecords  # noqa: F401 - re-exported
from memgs_ros.core.gaussians.tensors import Gaussians
from memgs_ros.errors import ConfigError, DataError

PARAM_NAMES = ("means", "log_scales", "quats_wxyz", "opacity_logits", "sh_dc", "sh_rest")
SIDE_NAMES = (
    "ids", "keyframe_ids", "created_iter", "densify_grad_sum", "densify_count",
    "merge_grad_sum", "merge_count", "max_radii2d",
)
_SIDE_DTYPES = {
    "ids": torch.int64, "keyframe_ids": torch.int64, "created_iter": torch.int64,
    "densify_grad_sum": torch.float32, "densify_count": torch.int64,
    "merge_grad_sum": torch.float32, "merge_count": torch.int64,
    "max_radii2d": torch.float32,
}


def num_sh_rest(sh_degree: int) -> int:
    """Number of higher-order SH coefficients per channel, K = (d + 1)^2 - 1."""
    if not 0 <= sh_degree <= 3:
        raise ConfigError(f"sh_degree must be in 0..3, got {sh_degree}")
    return (sh_degree + 1) ** 2 - 1


def rgb_to_sh_dc(rgb: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Colours in [0, 1] ([M, 3]) to SH DC coefficients ([M, 3]) as 3DGS initialises them."""
    return (rgb - 0.5) / SH_C0


def render_tensors(records: GaussianRecords, device: torch.device | str = "cpu") -> Gaussians:
    """The rasterizer's input from records, without a ``GaussianMap`` (no gradients, no
    optimiser state): means [N, 3], quats_wxyz [N, 4], log_scales [N, 3], opacity_logits [N, 1],
    sh_dc [N, 1, 3], sh_rest [N, 15, 3]; positions, rotations and scales share the records'
    memory on the CPU."""
    n = len(records)
    t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
    sh_rest = t(records.f_rest).reshape(n, 3, 15).transpose(1, 2).contiguous()
    return Gaussians(t(records.xyz), t(records.rot), t(records.scale), t(records.opacity).reshape(n, 1),
                     t(records.f_dc).reshape(n, 1, 3), sh_rest)


@dataclass(frozen=True)
class MemoryReport:
    """Bytes held by the map's per-Gaussian tensors (reference section 11 accounting).

    params: the six parameter tensors; grads: their gradients at their in-training size (they
    exist between backward and the optimiser step, which frees them), counted once the map has
    been trained or while gradients are allocated; optimizer: Adam's per-row moments
    (exp_avg, exp_avg_sq). Scalar step counters and the int
    side arrays are not counted, so at SH degree 3 a trained map holds 236 B + 236 B + 472 B
    = 944 B per Gaussian.
    """

    params: int
    grads: int
    optimizer: int
    total: int


def _expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """3DGS exponential decay: log-linear interpolation from lr_init to lr_final, then held."""
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


def _keep_then_append(old: torch.Tensor, new: torch.Tensor | None, idx: torch.Tensor | None) -> torch.Tensor:
    """Rows ``idx`` of ``old`` ([K] int64, None = all) followed by ``new``, in one new tensor (``old``
    itself when nothing changes). Row indices + index_select into one preallocated tensor: bool-mask
    indexing and a second copy for the append cost ~3x more on CPU (a merge pass at 150k rows: 54 ms)."""
    n_keep = old.shape[0] if idx is None else int(idx.shape[0])
    if idx is None and new is None:
        return old.contiguous()
    out = old.new_empty((n_keep + (0 if new is None else new.shape[0]),) + tuple(old.shape[1:]))
    if idx is None:
        out[:n_keep] = old
    else:
        torch.index_select(old, 0, idx, out=out[:n_keep])
    if new is not None:
        out[n_keep:] = new
    return out


def _seed_rows(points_w: np.ndarray | torch.Tensor, colors: np.ndarray | torch.Tensor, existing: np.ndarray,
               opacity: float) -> tuple[np.ndarray, ...] | None:
    """3DGS initial parameters of seed points (see ``GaussianMap.add_from_points``): (points [M, 3],
    log scales [M, 3], quaternions [M, 4], opacity logits [M, 1], SH DC [M, 3]) of the finite
    points, None when there are none. existing: [N, 3] float64 means of the map."""
    from scipy.spatial import cKDTree  # scipy only needed here

    pts = np.asarray(points_w.detach().cpu() if isinstance(points_w, torch.Tensor) else points_w,
                     dtype=np.float64)
    cols = np.asarray(colors.detach().cpu() if isinstance(colors, torch.Tensor) else colors,
                      dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or cols.shape != pts.shape:
        raise DataError(f"points_w and colors must both be [M, 3], got {pts.shape} and {cols.shape}")
    finite = np.isfinite(pts).all(1) & np.isfinite(cols).all(1)
    pts, cols = pts[finite], cols[finite]
    m = pts.shape[0]
    if m == 0:
        return None
    cloud = np.concatenate([existing, pts], 0)
    k = min(4, cloud.shape[0])  # the point itself plus up to 3 neighbours
    if k > 1:
        d, _ = cKDTree(cloud).query(pts, k=k)
        mean_sq = np.mean(np.asarray(d)[:, 1:] ** 2, axis=1)
    else:
        mean_sq = np.full(m, 1e-2)  # a lone point: no neighbour to size it by, 10 cm
    mean_sq = np.maximum(mean_sq, 1e-7)
    log_s = np.log(np.sqrt(mean_sq))[:, None].repeat(3, 1)
    quats = np.zeros((m, 4))
    quats[:, 0] = 1.0
    if not 0.0 < opacity < 1.0:
        raise DataError(f"seed opacity must be in (0, 1), got {opacity}")
    opac = np.full((m, 1), math.log(opacity / (1.0 - opacity)))
    return pts, log_s, quats, opac, np.asarray(rgb_to_sh_dc(np.clip(cols, 0.0, 1.0)))


class GaussianMap(RecordsIO):
    """A 3D Gaussian map with its Adam optimiser and per-Gaussian side arrays.

    Parameters (leaf ``torch.nn.Parameter``s, float32, on ``device``):
    means [N, 3], log_scales [N, 3], quats_wxyz [N, 4], opacity_logits [N, 1], sh_dc [N, 1, 3],
    sh_rest [N, K, 3] with K = (max_sh_degree + 1)^2 - 1.

    Not thread-safe: one thread drives it (the mapping session's worker).
    """

    # Per-Gaussian side arrays [N] (SIDE_NAMES, dtypes in _SIDE_DTYPES), resized with the parameters.
    ids: torch.Tensor  # int64, unique and increasing in creation order
    keyframe_ids: torch.Tensor  # int64, the keyframe that created the Gaussian (-1: loaded)
    created_iter: torch.Tensor  # int64, training iteration at creation
    densify_grad_sum: torch.Tensor  # float32, accumulated screen-space gradient norms
    densify_count: torch.Tensor  # int64, times seen since the last densification
    merge_grad_sum: torch.Tensor  # float32, accumulated 3D positional gradient norms
    merge_count: torch.Tensor  # int64
    max_radii2d: torch.Tensor  # float32, largest screen radius seen (px)

    def __init__(self, max_sh_degree: int = 3, device: torch.device | str = "cpu",
                 lrs: GaussianLearningRates | None = None, spatial_lr_scale: float = 1.0) -> None:
        self.max_sh_degree = int(max_sh_degree)
        self.k_rest = num_sh_rest(self.max_sh_degree)
        self.active_sh_degree = 0
        self.device = torch.device(device)
        self.lrs = lrs if lrs is not None else GaussianLearningRates()
        if not (math.isfinite(spatial_lr_scale) and spatial_lr_scale > 0):
            raise ConfigError(f"spatial_lr_scale must be positive, got {spatial_lr_scale}")
        self.spatial_lr_scale = float(spatial_lr_scale)
        self.next_id = 0
        shapes = {"means": (3,), "log_scales": (3,), "quats_wxyz": (4,), "opacity_logits": (1,),
                  "sh_dc": (1, 3), "sh_rest": (self.k_rest, 3)}
        self._row_shapes = shapes
        self.means = self._empty_param("means")
        self.log_scales = self._empty_param("log_scales")
        self.quats_wxyz = self._empty_param("quats_wxyz")
        self.opacity_logits = self._empty_param("opacity_logits")
        self.sh_dc = self._empty_param("sh_dc")
        self.sh_rest = self._empty_param("sh_rest")
        for name in SIDE_NAMES:
            setattr(self, name, torch.zeros(0, dtype=_SIDE_DTYPES[name], device=self.device))
        self._optimizer: torch.optim.Adam | None = None

    @property
    def optimizer(self) -> torch.optim.Adam:
        """Adam over the six parameters, made when first asked for: a map that is only rendered
        (scoring a saved map) needs none, and torch's first optimizer loads its compiler stack
        (1.4 s). The parameters keep their objects when rows change (``.data`` is replaced), so
        a later optimizer sees the same tensors with empty moments, as a new map's would."""
        if self._optimizer is None:
            base = self._base_lrs()
            groups = [{"params": [getattr(self, n)], "lr": base[n], "name": n} for n in PARAM_NAMES]
            try:  # one fused kernel per tensor: 1.5 ms instead of 7.9 ms a step at 31k Gaussians on CPU
                self._optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)
            except (RuntimeError, TypeError, ValueError):  # a torch or device without the fused Adam
                self._optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        return self._optimizer

    # ------------------------------------------------------------------ basics
    def _empty_param(self, name: str) -> torch.nn.Parameter:
        return torch.nn.Parameter(torch.zeros((0,) + self._row_shapes[name], dtype=torch.float32,
                                              device=self.device))

    def _base_lrs(self) -> dict[str, float]:
        lr = self.lrs
        return {"means": lr.means * self.spatial_lr_scale, "log_scales": lr.scaling,
                "quats_wxyz": lr.rotation, "opacity_logits": lr.opacity, "sh_dc": lr.sh_dc,
                "sh_rest": lr.sh_rest}

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_gaussians(self) -> int:
        return len(self)

    def gaussians(self) -> Gaussians:
        """The parameters as the rasterizer's input (the same tensors: gradients reach them)."""
        return Gaussians(self.means, self.quats_wxyz, self.log_scales, self.opacity_logits, self.sh_dc, self.sh_rest)

    def params(self) -> dict[str, torch.nn.Parameter]:
        """The six parameters by name (same objects for the map's lifetime)."""
        return {n: getattr(self, n) for n in PARAM_NAMES}

    def raise_sh_degree(self) -> int:
        """Activate one more SH band (up to max_sh_degree). Returns the active degree."""
        self.active_sh_degree = min(self.active_sh_degree + 1, self.max_sh_degree)
        return self.active_sh_degree

    def update_learning_rate(self, iteration: int) -> float:
        """Apply the position LR schedule for ``iteration``; returns the position LR in use."""
        base = self.lrs.means * self.spatial_lr_scale
        lr = base
        if self.lrs.means_decay:
            lr = _expon_lr(iteration, base, self.lrs.means_final * self.spatial_lr_scale,
                           self.lrs.means_decay_steps)
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = lr
        return lr

    def set_spatial_lr_scale(self, extent: float) -> None:
        """Re-scale the position LR to a new scene extent (metres)."""
        if not (math.isfinite(extent) and extent > 0):
            raise ConfigError(f"scene extent must be positive, got {extent}")
        self.spatial_lr_scale = float(extent)
        self.update_learning_rate(0)

    # ------------------------------------------------------------ activations
    def scales(self) -> torch.Tensor:
        """Activated scales exp(log_scales): [N, 3]."""
        return torch.exp(self.log_scales)

    def opacities(self) -> torch.Tensor:
        """Activated opacities sigmoid(logit): [N, 1]."""
        return torch.sigmoid(self.opacity_logits)

    # ------------------------------------------------------- the one resize helper
    def _resize(self, keep: torch.Tensor | None, new_params: dict[str, torch.Tensor] | None,
                new_side: dict[str, torch.Tensor] | None) -> None:
        """Keep rows ``keep`` ([N] bool, None = all) then append ``new_params`` rows.

        Parameters, Adam moments (new rows get zeros) and every side array change together.
        Parameter objects keep their identity (``.data`` is swapped) so the optimiser's
        param_groups and state keys stay valid; gradients are dropped.
        """
        n_new = 0 if new_params is None else int(new_params["means"].shape[0])
        params_in = new_params if new_params is not None else {}
        side_in = new_side if new_side is not None else {}
        idx = None if keep is None else torch.nonzero(keep).squeeze(1)
        rebuild = functools.partial(_keep_then_append, idx=idx)
        for name in PARAM_NAMES:
            p: torch.nn.Parameter = getattr(self, name)
            new = None
            if n_new:
                new = params_in[name].to(self.device, torch.float32).reshape((n_new,) + self._row_shapes[name])
            data = rebuild(p.data, new)
            state = self.optimizer.state.get(p)
            if state:
                for key in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
                    if key not in state:
                        continue
                    moment = state[key]
                    state[key] = rebuild(moment, moment.new_zeros((n_new,) + moment.shape[1:]) if n_new else None)
            p.data = data
            p.grad = None
        for name in SIDE_NAMES:
            arr = getattr(self, name)
            new = side_in[name].to(self.device, _SIDE_DTYPES[name]) if n_new else None
            setattr(self, name, rebuild(arr, new))

    # ------------------------------------------------------------------ grow
    def add(self, means: torch.Tensor, log_scales: torch.Tensor, quats_wxyz: torch.Tensor,
            opacity_logits: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor | None,
            keyframe_id: int | torch.Tensor, iteration: int,
            remove: torch.Tensor | None = None) -> torch.Tensor:
        """Append M Gaussians with fresh ids and zero Adam moments.

        means [M, 3], log_scales [M, 3], quats_wxyz [M, 4], opacity_logits [M, 1] or [M],
        sh_dc [M, 1, 3] or [M, 3], sh_rest [M, K', 3] (K' <= K, zero-padded; None = zeros).
        keyframe_id: an int or an int64 tensor [M]. remove: [N] bool, rows removed in the same
        pass (as ``remove`` would; a merge replaces pairs by one Gaussian with one copy of the
        map instead of two). Returns the new ids: [M] int64.
        """
        m = int(means.shape[0])
        if tuple(means.shape) != (m, 3):
            raise DataError(f"means must be [M, 3], got {tuple(means.shape)}")
        rest = torch.zeros((m, self.k_rest, 3), dtype=torch.float32, device=self.device)
        if sh_rest is not None and sh_rest.numel():
            k = min(int(sh_rest.shape[1]), self.k_rest)
            rest[:, :k] = sh_rest[:, :k].to(self.device, torch.float32)
        new = {"means": means, "log_scales": log_scales, "quats_wxyz": quats_wxyz,
               "opacity_logits": opacity_logits.reshape(m, 1), "sh_dc": sh_dc.reshape(m, 1, 3),
               "sh_rest": rest}
        for name in ("log_scales", "quats_wxyz"):
            if tuple(new[name].shape) != (m,) + self._row_shapes[name]:
                raise DataError(f"{name} must be [M, {self._row_shapes[name][0]}], got {tuple(new[name].shape)}")
        new = {k_: v.detach() for k_, v in new.items()}
        ids = torch.arange(self.next_id, self.next_id + m, dtype=torch.int64, device=self.device)
        self.next_id += m
        kf = torch.as_tensor(keyframe_id, dtype=torch.int64, device=self.device).expand(m).clone()
        side = {
            "ids": ids, "keyframe_ids": kf,
            "created_iter": torch.full((m,), int(iteration), dtype=torch.int64),
            "densify_grad_sum": torch.zeros(m), "densify_count": torch.zeros(m, dtype=torch.int64),
            "merge_grad_sum": torch.zeros(m), "merge_count": torch.zeros(m, dtype=torch.int64),
            "max_radii2d": torch.zeros(m),
        }
        keep = None
        if remove is not None:
            remove = torch.as_tensor(remove, dtype=torch.bool, device=self.device)
            if tuple(remove.shape) != (len(self),):
                raise DataError(f"remove mask must be [{len(self)}] bool, got {tuple(remove.shape)}")
            if bool(remove.any()):
                keep = ~remove
        self._resize(keep, new, side)
        return ids

    def add_from_points(self, points_w: np.ndarray | torch.Tensor, colors: np.ndarray | torch.Tensor,
                        keyframe_id: int, iteration: int, opacity: float = 0.1) -> torch.Tensor:
        """Initialise Gaussians at points as 3DGS does (reference section 3).

        points_w: [M, 3] world positions; colors: [M, 3] RGB in [0, 1].
        Scale = log(sqrt(mean squared distance to the 3 nearest neighbours)), the neighbours
        searched among the existing map's means AND the new points (so a seed dropped into an
        already covered region gets a size matching its neighbourhood, not the batch's spread);
        squared distance clamped at 1e-7. Identity rotation, opacity ``opacity`` (3DGS: 0.1), SH
        DC from the colour, higher bands zero. Returns the new ids [M].
        """
        seeds = _seed_rows(points_w, colors, self.means.detach().cpu().numpy().astype(np.float64), opacity)
        if seeds is None:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        pts, log_s, quats, opac, dc = seeds
        t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=self.device)  # noqa: E731
        return self.add(t(pts), t(log_s), t(quats), t(opac), t(dc).reshape(-1, 1, 3), None,
                        keyframe_id, iteration)

    # ---------------------------------------------------------------- shrink
    def remove(self, mask: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Remove the rows where ``mask`` ([N] bool) is True. Returns their ids [R] int64."""
        mask_t = torch.as_tensor(mask, dtype=torch.bool, device=self.device)
        if tuple(mask_t.shape) != (len(self),):
            raise DataError(f"remove mask must be [{len(self)}] bool, got {tuple(mask_t.shape)}")
        removed = self.ids[mask_t].clone()
        if removed.numel():
            self._resize(~mask_t, None, None)
        return removed

    def index_of(self, ids: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Row positions of ``ids`` ([M] int64); -1 for ids not in the map. Returns [M] int64."""
        q = torch.as_tensor(ids, dtype=torch.int64, device=self.device).reshape(-1)
        if len(self) == 0:
            return torch.full_like(q, -1)
        pos = torch.searchsorted(self.ids, q).clamp_max(len(self) - 1)
        return torch.where(self.ids[pos] == q, pos, torch.full_like(pos, -1))

    def reset_rows(self, index: torch.Tensor, *, moments: bool = True, accumulators: bool = True) -> None:
        """Zero Adam moments and/or the gradient accumulators of rows ``index`` ([M] int64 or [N] bool).

        Used after rows' parameters were overwritten in place (e.g. a merge that keeps ids).
        """
        with torch.no_grad():
            if moments:
                for p in self.params().values():
                    state = self.optimizer.state.get(p)
                    for key in ("exp_avg", "exp_avg_sq"):
                        if state and key in state:
                            state[key][index] = 0.0
            if accumulators:
                for name in ("densify_grad_sum", "densify_count", "merge_grad_sum", "merge_count",
                             "max_radii2d"):
                    getattr(self, name)[index] = 0

    # ------------------------------------------------------------ statistics
    def accumulate_stats(self, means2d_grad: torch.Tensor | None, visible: torch.Tensor,
                         radii: torch.Tensor, width: int, height: int) -> None:
        """Add one render's gradient statistics (call after backward, before the optimiser step).

        means2d_grad: [N, 2] gradient of the loss w.r.t. pixel positions (None = skip densify
        stats); visible: [N] bool; radii: [N] screen radii in pixels. The 2D gradient is scaled to
        normalised device coordinates (x W/2, x H/2) so the densify threshold means what it
        means in 3DGS whatever the render resolution. The 3D gradient comes from ``means.grad``.
        """
        with torch.no_grad():
            vis = visible.to(self.device, torch.bool)
            if means2d_grad is not None:
                g = means2d_grad.detach().to(self.device)
                scale = torch.tensor([width * 0.5, height * 0.5], device=self.device, dtype=g.dtype)
                self.densify_grad_sum += torch.where(vis, (g * scale).norm(dim=-1), 0.0).float()
                self.densify_count += vis.long()
            if self.means.grad is not None:
                self.merge_grad_sum += torch.where(vis, self.means.grad.norm(dim=-1), 0.0).float()
                self.merge_count += vis.long()
            r = radii.to(self.device).float()
            self.max_radii2d = torch.where(vis, torch.maximum(self.max_radii2d, r), self.max_radii2d)

    def densify_grad_mean(self) -> torch.Tensor:
        """Mean 2D (NDC) gradient norm per Gaussian since the last reset: [N]; 0 when unseen."""
        return self.densify_grad_sum / self.densify_count.clamp_min(1).float()

    def merge_grad_mean(self) -> torch.Tensor:
        """Mean 3D positional gradient norm per Gaussian: [N]; 0 when unseen (reference section 4)."""
        return self.merge_grad_sum / self.merge_count.clamp_min(1).float()

    def reset_densify_stats(self) -> None:
        self.densify_grad_sum.zero_()
        self.densify_count.zero_()
        self.max_radii2d.zero_()

    def reset_merge_stats(self) -> None:
        self.merge_grad_sum.zero_()
        self.merge_count.zero_()

    # ------------------------------------------------------ optimisation step
    def optimizer_step(self) -> None:
        """Adam step, then drop gradients."""
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    # ------------------------------------------------------------- memory
    def memory_bytes(self) -> MemoryReport:
        """Bytes of parameters, allocated gradients and Adam moments (see ``MemoryReport``)."""
        params = grads = opt = 0
        for p in self.params().values():
            params += p.numel() * p.element_size()
            state = self.optimizer.state.get(p)
            if p.grad is not None or state:
                grads += p.numel() * p.element_size()
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        opt += state[key].numel() * state[key].element_size()
        return MemoryReport(params=params, grads=grads, optimizer=opt, total=params + grads + opt)

    # ------------------------------------------------------------ records
    @staticmethod
    def from_records(records: GaussianRecords, max_sh_degree: int = 3, device: torch.device | str = "cpu",
                     lrs: GaussianLearningRates | None = None, spatial_lr_scale: float = 1.0,
                     keyframe_id: int = -1, iteration: int = 0) -> GaussianMap:
        """A new map holding ``records`` with their ids (next_id continues after the largest).

        SH coefficients beyond ``max_sh_degree`` are dropped. Keyframe ids are not part of the
        records: every row gets ``keyframe_id``.
        """
        gmap = GaussianMap(max_sh_degree, device, lrs, spatial_lr_scale)
        gmap.load_records(records, keyframe_id=keyframe_id, iteration=iteration)
        return gmap
