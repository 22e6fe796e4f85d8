"""What a mapping session keeps beside its mapper, on its worker thread: the keyframes by stamp
(``StampedKeyframes``: the graph names keyframes by stamp, the mapper by id) and the running
figures its status is built from (``SessionTally``)."""
from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from memgs_ros.core.mapper_service.session_records import SessionCounts, SessionStatus
from memgs_ros.errors import DataError

if TYPE_CHECKING:
    from memgs_ros.core.mapping.mapper import GaussianMapper, StepStats


class StampedKeyframes:
    """The mapper's keyframes by stamp (ids 0, 1, ... by arrival), each edit counted in ``counts``."""

    def __init__(self, mapper: GaussianMapper, counts: SessionCounts) -> None:
        self.mapper, self.counts = mapper, counts
        self.ids: dict[int, int] = {}  # keyframe stamp -> keyframe id

    def ids_of(self, poses: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
        return {self.ids[s]: T for s, T in poses.items() if s in self.ids}

    def update_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        updated = self.mapper.update_keyframe_poses(self.ids_of(poses))
        self.counts.keyframe_pose_updates += updated
        self.counts.refined_poses_of_dropped_keyframes += len(poses) - updated
        return updated

    def retire(self, stamps: list[int]) -> tuple[int, int]:
        retired, handed = self.mapper.retire_keyframes([self.ids[s] for s in stamps if s in self.ids])
        self.counts.keyframes_retired += retired
        self.counts.gaussians_handed_on += handed
        return retired, handed

    def correct(self, poses: Mapping[int, np.ndarray]) -> tuple[int, int]:
        corrected, moved = self.mapper.correct_keyframes(self.ids_of(poses))
        self.counts.keyframes_corrected += corrected
        self.counts.gaussians_corrected += moved
        return corrected, moved

    def table(self) -> dict[str, Any]:
        """The stamp table as a checkpoint's ``extra`` holds it (JSON keys)."""
        return {"keyframe_stamps": {str(s): k for s, k in self.ids.items()}}

    def load(self, extra: Mapping[str, Any]) -> None:
        """The stamp table of a checkpoint's ``extra``."""
        try:
            self.ids = {int(s): int(k) for s, k in extra.get("keyframe_stamps", {}).items()}
        except (TypeError, ValueError, AttributeError) as err:
            raise DataError(f"checkpoint keyframe_stamps are not a stamp -> id table: {err}") from err


class SessionTally:
    """The figures between two statuses: the counters, the last step's loss and the peaks of
    model bytes, Gaussians and accounted bytes."""

    def __init__(self) -> None:
        self.counts = SessionCounts()
        self.last_loss: float | None = None
        self._peaks = [0, 0, 0]  # model bytes, Gaussians, accounted bytes

    def step(self, st: StepStats) -> None:
        c = self.counts
        c.merged_removed += st.merged_removed
        c.merged_added += st.merged_added
        c.budget_merged += st.budget_merged
        c.budget_pruned += st.budget_pruned
        self.last_loss = round(sum(st.terms.values()), 5)

    def status(self, m: GaussianMapper, **session: Any) -> SessionStatus:  # noqa: ANN401 - SessionStatus fields
        """The status of mapper ``m`` now, with the ``session``'s own fields (keyframes, timing, ...)."""
        model = m.gmap.memory_bytes().total
        account = m.memory_account()
        cuda = torch.cuda.max_memory_allocated(m.device) if m.device.type == "cuda" else None
        self._peaks = [max(self._peaks[0], model), max(self._peaks[1], len(m.gmap)),
                       max(self._peaks[2], account.total)]
        return SessionStatus(
            iteration=m.iteration, gaussians=len(m.gmap), keyframes_trained=len(m.keyframes),
            keyframes_dropped=m.keyframes_dropped, budget_gaussians=m.budget_gaussians, model_bytes=model,
            model_bytes_peak=self._peaks[0], keyframe_bytes=account.keyframes, accounted_bytes=account.total,
            accounted_bytes_peak=self._peaks[2], gaussians_peak=self._peaks[1], loss=self.last_loss,
            cuda_max_allocated=cuda, cuda_peak_by_work=dict(m.peaks.by_work),
            counters=self.counts.with_map(m.merge.passes, m.seeds_covered), **session)
