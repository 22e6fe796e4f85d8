"""Per-keyframe exposure compensation: an affine colour correction trained with the map.

A camera with auto exposure and white balance (TUM's fr1 Kinect, a RealSense) records the same
surface brighter in one frame than in the next. Trained on such frames as they are, the map
averages the exposures into view-dependent colour (SH bands, floaters). Here each keyframe k
gets a gain and a bias per channel, applied to the render before the loss:

    C'_k = (1 + a_k) * C + b_k            a_k, b_k: [3]

trained by Adam beside the Gaussians and pulled towards identity by ``reg_weight * (|a|^2 +
|b|^2)`` (also what pins the gauge: without it the map could get brighter while every
keyframe's gain shrinks). Only training sees the correction: renders for evaluation and for the
rendered-view topics are the map alone (the paper's protocol: nothing is fitted to the frames
being scored).

Each keyframe's six numbers have their own Adam moments (a shared tensor would keep moving
rows whose keyframe was not drawn). ~100 B per keyframe.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from memgs_ros.errors import DataError

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-15  # as the Gaussians' optimiser


@dataclass
class _Affine:
    """One keyframe's correction: params [2, 3] (row 0 gain offset a, row 1 bias b) and Adam state."""

    params: torch.Tensor
    exp_avg: torch.Tensor
    exp_avg_sq: torch.Tensor
    steps: int = 0


class ExposureCompensation:
    """The per-keyframe affine corrections of one mapper (see module docstring).

    lr: Adam learning rate; reg_weight: weight of the pull towards identity. Not thread-safe
    (the mapper's one training thread uses it).
    """

    def __init__(self, lr: float = 0.005, reg_weight: float = 0.01, device: torch.device | str = "cpu") -> None:
        if not (math.isfinite(lr) and lr > 0) or not (math.isfinite(reg_weight) and reg_weight >= 0):
            raise DataError(f"exposure compensation needs lr > 0 and reg_weight >= 0, got {lr}, {reg_weight}")
        self.lr = float(lr)
        self.reg_weight = float(reg_weight)
        self.device = torch.device(device)
        self._kfs: dict[int, _Affine] = {}
        self._pending: _Affine | None = None  # applied since the last step()

    def __len__(self) -> int:
        return len(self._kfs)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._kfs

    def _get(self, kf_id: int) -> _Affine:
        aff = self._kfs.get(kf_id)
        if aff is None:
            zeros = torch.zeros(2, 3, device=self.device)
            aff = _Affine(zeros.clone().requires_grad_(True), zeros.clone(), zeros.clone())
            self._kfs[kf_id] = aff
        return aff

    def apply(self, kf_id: int, color: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Correct render ``color`` [3, H, W] of keyframe ``kf_id`` for training.

        Returns (corrected colour [3, H, W], regularisation loss []); ``step`` after backward
        updates this keyframe's correction.
        """
        aff = self._get(int(kf_id))
        self._pending = aff
        a, b = aff.params[0], aff.params[1]
        corrected = color * (1.0 + a).view(3, 1, 1) + b.view(3, 1, 1)
        reg = self.reg_weight * (aff.params * aff.params).sum()
        return corrected, reg

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step of the correction used since the last call (nothing when none was)."""
        aff, self._pending = self._pending, None
        if aff is None or aff.params.grad is None:
            return
        g = aff.params.grad
        b1, b2 = ADAM_BETAS
        aff.steps += 1
        aff.exp_avg.mul_(b1).add_(g, alpha=1 - b1)
        aff.exp_avg_sq.mul_(b2).addcmul_(g, g, value=1 - b2)
        step = self.lr / (1 - b1 ** aff.steps)
        denom = (aff.exp_avg_sq / (1 - b2 ** aff.steps)).sqrt_().add_(ADAM_EPS)
        aff.params.addcdiv_(aff.exp_avg, denom, value=-step)
        aff.params.grad = None

    def remove(self, kf_id: int) -> None:
        """Forget keyframe ``kf_id``'s correction (it left training)."""
        self._kfs.pop(int(kf_id), None)

    def get(self, kf_id: int) -> tuple[float, ...]:
        """(a_r, a_g, a_b, b_r, b_g, b_b) of keyframe ``kf_id``; identity (zeros) when it has none."""
        aff = self._kfs.get(int(kf_id))
        if aff is None:
            return (0.0,) * 6
        return tuple(float(x) for x in aff.params.detach().reshape(-1).cpu())

    def set(self, kf_id: int, values: tuple[float, ...]) -> None:
        """Restore a keyframe's correction (a checkpoint); its Adam moments restart at zero."""
        if len(values) != 6 or not all(math.isfinite(float(v)) for v in values):
            raise DataError(f"keyframe {kf_id}: exposure needs 6 finite numbers, got {values}")
        aff = self._get(int(kf_id))
        with torch.no_grad():
            aff.params.copy_(torch.tensor(values, dtype=aff.params.dtype).view(2, 3))
