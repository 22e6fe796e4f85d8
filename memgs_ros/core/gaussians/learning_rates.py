"""The trainable map's Adam learning rates (torch-free: the mapper's config takes them)."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

from memgs_ros.errors import ConfigError


@dataclass(frozen=True)
class GaussianLearningRates:
    """Adam learning rates per parameter (reference section 5).

    ``means`` is multiplied by the scene extent (``spatial_lr_scale``). With ``means_decay`` the
    position LR follows the 3DGS schedule: log-linear from ``means`` to ``means_final`` over
    ``means_decay_steps`` iterations; otherwise it stays at ``means``.
    """

    means: float = 1.6e-4
    means_final: float = 1.6e-6
    means_decay_steps: int = 30_000
    means_decay: bool = False
    sh_dc: float = 0.0025
    sh_rest: float = 0.0025 / 20.0
    opacity: float = 0.05
    scaling: float = 0.005
    rotation: float = 0.001

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"learning rate {f.name} must be a positive finite number, got {v}")
