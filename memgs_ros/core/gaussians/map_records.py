"""A Gaussian map's rows in and out as ``GaussianRecords`` (the PLY's and the delta protocol's
layout): a mixin of ``GaussianMap``."""
from __future__ import annotations

import numpy as np
import torch

from memgs_ros.core.gaussians.records import PLY_F_REST, GaussianRecords
from memgs_ros.errors import DataError

__all__ = ["RecordsIO"]


class RecordsIO:
    """Mixin of ``GaussianMap``: ``to_records`` and ``load_records`` over its parameters and ids."""

    device: torch.device
    k_rest: int
    next_id: int
    ids: torch.Tensor
    means: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor
    opacity_logits: torch.Tensor
    log_scales: torch.Tensor
    quats_wxyz: torch.Tensor

    def __len__(self) -> int:
        raise NotImplementedError

    def add(self, means: torch.Tensor, log_scales: torch.Tensor, quats_wxyz: torch.Tensor,
            opacity_logits: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor | None,
            keyframe_id: int | torch.Tensor, iteration: int,
            remove: torch.Tensor | None = None) -> torch.Tensor:
        raise NotImplementedError

    def to_records(self, index: torch.Tensor | None = None) -> GaussianRecords:
        """The map (or rows ``index``) as ``GaussianRecords``; exact float32 copies."""
        with torch.no_grad():
            sel = (lambda t: t) if index is None else (lambda t: t[index])  # noqa: E731
            n = int(sel(self.ids).shape[0])
            rest = torch.zeros((n, 3, 15), dtype=torch.float32, device=self.device)
            rest[:, :, : self.k_rest] = sel(self.sh_rest.detach()).transpose(1, 2)
            np_ = lambda t: t.detach().cpu().numpy()  # noqa: E731
            return GaussianRecords.from_arrays(
                np_(sel(self.ids)), np_(sel(self.means)), np_(sel(self.sh_dc).reshape(n, 3)),
                np_(rest.reshape(n, PLY_F_REST)), np_(sel(self.opacity_logits).reshape(n)),
                np_(sel(self.log_scales)), np_(sel(self.quats_wxyz)))


    def load_records(self, records: GaussianRecords, keyframe_id: int = -1, iteration: int = 0) -> torch.Tensor:
        """Append ``records`` keeping their ids (they must all exceed the map's ids). Returns ids."""
        n = len(records)
        if n == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        ids = torch.as_tensor(records.ids, dtype=torch.int64, device=self.device)
        if bool((ids[1:] <= ids[:-1]).any()) or (len(self) and int(ids[0]) <= int(self.ids[-1])) or int(ids[0]) < 0:
            order = np.argsort(records.ids, kind="stable")
            if np.any(np.diff(records.ids[order]) == 0) or records.ids.min() < 0:
                raise DataError("GaussianRecords.ids must be unique non-negative integers")
            if len(self) and int(records.ids.min()) <= int(self.ids[-1]):
                raise DataError("GaussianRecords.ids must be larger than every id already in the map")
            records = records.select(order)
            ids = torch.as_tensor(records.ids, dtype=torch.int64, device=self.device)
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32, device=self.device)  # noqa: E731
        rest = t(records.f_rest).reshape(n, 3, 15).transpose(1, 2)[:, : self.k_rest]
        saved_next = self.next_id
        self.next_id = int(ids[0])  # add() numbers sequentially; rewrite ids below
        self.add(t(records.xyz), t(records.scale), t(records.rot), t(records.opacity),
                 t(records.f_dc), rest, keyframe_id, iteration)
        self.ids[-n:] = ids
        self.next_id = max(saved_next, int(ids[-1]) + 1)
        return ids
