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

Each keyframe's six numbers have their own Adam moments (one Adam over the whole table would
keep moving rows whose keyframe was not drawn), and after each step the corrections are
re-centred on zero mean. ~100 B per keyframe.
"""
from __future__ import annotations

import math

import torch

from memgs_ros.errors import DataError

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-15  # as the Gaussians' optimiser


class ExposureCompensation:
    """The per-keyframe affine corrections of one mapper (see module docstring).

    lr: Adam learning rate; reg_weight: weight of the pull towards identity. Not thread-safe
    (the mapper's one training thread uses it). The corrections live in one table
    ([K, 2, 3]: row 0 gain offsets a, row 1 biases b) with per-row Adam moments, so a step moves
    only the keyframe that was drawn, and re-centring all of them is one op.
    """

    def __init__(self, lr: float = 0.005, reg_weight: float = 0.01, device: torch.device | str = "cpu") -> None:
        if not (math.isfinite(lr) and lr > 0) or not (math.isfinite(reg_weight) and reg_weight >= 0):
            raise DataError(f"exposure compensation needs lr > 0 and reg_weight >= 0, got {lr}, {reg_weight}")
        self.lr = float(lr)
        self.reg_weight = float(reg_weight)
        self.device = torch.device(device)
        self._rows: dict[int, int] = {}  # kf_id -> row of the tables
        self._table = torch.zeros(0, 2, 3, device=self.device, requires_grad=True)
        self._exp_avg = torch.zeros(0, 2, 3, device=self.device)
        self._exp_avg_sq = torch.zeros(0, 2, 3, device=self.device)
        self._steps: list[int] = []
        self._pending: int | None = None  # row trained since the last step()

    def __len__(self) -> int:
        return len(self._rows)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._rows

    def _row(self, kf_id: int) -> int:
        row = self._rows.get(kf_id)
        if row is None:
            row = len(self._rows)
            self._rows[kf_id] = row
            zero = torch.zeros(1, 2, 3, device=self.device)
            with torch.no_grad():
                self._table = torch.cat([self._table.detach(), zero]).requires_grad_(True)
            self._exp_avg = torch.cat([self._exp_avg, zero])
            self._exp_avg_sq = torch.cat([self._exp_avg_sq, zero])
            self._steps.append(0)
        return row

    def apply(self, kf_id: int, color: torch.Tensor, train: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Correct render ``color`` [3, H, W] of keyframe ``kf_id`` for training.

        Returns (corrected colour [3, H, W], regularisation loss []). ``train``: the correction
        takes part in the backward pass and ``step`` updates it; otherwise it is applied as a
        constant (the mapper trains it only on full-resolution views: on coarse, blurry levels
        of a keyframe whose region the map has barely learned it would fit the map's misfit).
        """
        row = self._row(int(kf_id))
        params = self._table[row] if train else self._table[row].detach()
        if train:
            self._pending = row
        corrected = color * (1.0 + params[0]).view(3, 1, 1) + params[1].view(3, 1, 1)
        reg = self.reg_weight * (params * params).sum()
        return corrected, reg

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step of the correction trained since the last call (nothing when none was),
        then re-centre all of them on zero mean: the map keeps the keyframes' average exposure
        (without it the corrections drift together and the map, rendered alone, with them)."""
        row, self._pending = self._pending, None
        grad = self._table.grad
        if row is None or grad is None:
            return
        g = grad[row]
        b1, b2 = ADAM_BETAS
        self._steps[row] += 1
        t = self._steps[row]
        m, v = self._exp_avg[row], self._exp_avg_sq[row]
        m.mul_(b1).add_(g, alpha=1 - b1)
        v.mul_(b2).addcmul_(g, g, value=1 - b2)
        denom = (v / (1 - b2 ** t)).sqrt_().add_(ADAM_EPS)
        self._table[row].addcdiv_(m, denom, value=-self.lr / (1 - b1 ** t))
        if len(self._rows) > 1:
            self._table.sub_(self._table.mean(0, keepdim=True))
        self._table.grad = None

    def remove(self, kf_id: int) -> None:
        """Forget keyframe ``kf_id``'s correction (it left training)."""
        row = self._rows.pop(int(kf_id), None)
        if row is None:
            return
        keep = [r for r in range(self._table.shape[0]) if r != row]
        idx = torch.tensor(keep, dtype=torch.long, device=self.device)
        with torch.no_grad():
            self._table = self._table.detach().index_select(0, idx).requires_grad_(True)
        self._exp_avg = self._exp_avg.index_select(0, idx)
        self._exp_avg_sq = self._exp_avg_sq.index_select(0, idx)
        del self._steps[row]
        self._rows = {k: (r if r < row else r - 1) for k, r in self._rows.items()}
        if self._pending == row:
            self._pending = None
        elif self._pending is not None and self._pending > row:
            self._pending -= 1

    def get(self, kf_id: int) -> tuple[float, ...]:
        """(a_r, a_g, a_b, b_r, b_g, b_b) of keyframe ``kf_id``; identity (zeros) when it has none."""
        row = self._rows.get(int(kf_id))
        if row is None:
            return (0.0,) * 6
        return tuple(float(x) for x in self._table[row].detach().reshape(-1).cpu())

    def set(self, kf_id: int, values: tuple[float, ...]) -> None:
        """Restore a keyframe's correction (a checkpoint); its Adam moments restart at zero."""
        if len(values) != 6 or not all(math.isfinite(float(v)) for v in values):
            raise DataError(f"keyframe {kf_id}: exposure needs 6 finite numbers, got {values}")
        row = self._row(int(kf_id))
        with torch.no_grad():
            self._table[row] = torch.tensor(values, dtype=self._table.dtype).view(2, 3)
