"""What every reader offers (TumFolder, BagSource, SyntheticSource, a repeated source): the
protocol the player, the runner and the evaluation read frames through."""
from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol, runtime_checkable

import numpy as np

from memgs_ros.core.geometry.camera import PinholeCamera
from memgs_ros.core.geometry.frame import Frame


@runtime_checkable
class FrameSource(Protocol):
    """Frames in order, their camera, and the ground truth (stamps [N] ns, poses [N, 4, 4]) where known."""

    name: str

    @property
    def camera(self) -> PinholeCamera: ...

    def __iter__(self) -> Iterator[Frame]: ...

    def __len__(self) -> int: ...

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]: ...
