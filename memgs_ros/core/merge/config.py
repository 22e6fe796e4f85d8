"""The voxel merge's parameters (reference section 4), apart from the torch code that uses them
(``voxel_merge``): nodes and the runner check a config without loading torch."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Literal

from memgs_ros.errors import ConfigError

CHI2_3DOF_95 = 7.815  # chi-square critical value, 3 degrees of freedom, 95 % confidence


@dataclass(frozen=True)
class MergeConfig:
    """Parameters of the voxel merge (reference section 4).

    enabled: run merging at all (the mapper's schedule decides when).
    tau: candidate threshold on the mean 3D positional gradient norm. Paper 1e-3; the released
        configs use 1e-4 (fewer candidates, fewer merges).
    window_keyframes: only Gaussians created by the newest ``window_keyframes`` keyframes
        (``K_min = newest - window + 1 .. K_max = newest``, keyframe ids consecutive) are candidates.
    min_age_iters: ... and only those created at least this many iterations before the pass: a seed
        not trained yet has no gradient to be still by (the released code counts an unseen Gaussian
        as still), and a live mapper merging every few keyframes folded 70 % of its fresh seeds
        before they were trained (0: the released code's rule).
    voxel_size_m: voxel edge (released configs 0.01 m).
    chi2_gate: merge a voxel's best pair only if d2 < this (3 dof, 95 %: 7.815).
    max_per_voxel: occupancy cap for pair generation. A voxel with n candidates has n(n-1)/2
        pairs; only its ``max_per_voxel`` oldest candidates are paired (the rest wait for the
        next pass: a voxel merges at most one pair per pass anyway), bounding pairs per voxel
        at cap(cap-1)/2.
    colour_from: "older" (paper: colour, SH and opacity of the older Gaussian i) or "newer"
        (released code).
    lbfgs_lr: initial step of the strong-Wolfe line search. Released code: 1e-3; with a line
        search the natural quasi-Newton step is 1, which saves the 3-4 extrapolating evaluations
        per iteration that 1e-3 costs (same optimum).
    lbfgs_max_iter, lbfgs_history: released settings (15, 20).
    lbfgs_tolerance_change: stop when the loss changes by less than this. The loss here is the
        SUM over pairs of W2 terms in per-pair normalised units (covariances divided by the
        pair's squared geometric-mean scale), so the tolerance is absolute on that sum. The
        released 1e-6 was on a loss in m^2 (~1e-5 per pair, i.e. barely any iteration); in
        these units 1e-6 leaves ~2e-4 relative covariance error on a single pair and 1e-8
        ~1e-5, for one or two more iterations (measured), hence 1e-8.
    lbfgs_tolerance_grad: stop when every gradient entry (normalised units) is below this.
    lbfgs_parametrization: "sqrt_cov" (default: L-BFGS over the symmetric square root of the
        merged covariance, converted to quaternion + scale at the end) or "quat_scale" (the
        paper's variables; converges far more slowly in one batched run; see
        ``merge_covariance``).
    init_scale_offset_m: the paper's [delta1, delta2, delta3] added to the mean scale (metres)
        to start L-BFGS away from repeated eigenvalues. The W2 here does not need it for
        stability; it is kept for fidelity and only moves the starting point.
    slerp_t: interpolation parameter of the rotation initialisation (paper 0.5).
    """

    enabled: bool = True
    tau: float = 1e-3
    window_keyframes: int = 50
    min_age_iters: int = 200
    voxel_size_m: float = 0.01
    chi2_gate: float = CHI2_3DOF_95
    max_per_voxel: int = 32
    colour_from: Literal["older", "newer"] = "older"
    lbfgs_lr: float = 1.0
    lbfgs_max_iter: int = 15
    lbfgs_history: int = 20
    lbfgs_tolerance_change: float = 1e-8
    lbfgs_tolerance_grad: float = 1e-7
    lbfgs_parametrization: Literal["sqrt_cov", "quat_scale"] = "sqrt_cov"
    init_scale_offset_m: tuple[float, float, float] = (0.001, 0.002, 0.003)
    slerp_t: float = 0.5

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "tau": (0.0, 1e30), "chi2_gate": (0.0, 1e3), "window_keyframes": (1, 10**5), "voxel_size_m": (1e-4, 10.0),
        "min_age_iters": (0, 10**8),
        "max_per_voxel": (2, 10**4),
        "lbfgs_lr": (1e-6, 1e3), "lbfgs_max_iter": (1, 10**4), "lbfgs_history": (1, 1000),
        "lbfgs_tolerance_change": (0.0, 1.0), "lbfgs_tolerance_grad": (0.0, 1.0), "slerp_t": (0.0, 1.0),
    }
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {"colour_from": ("older", "newer"),
                                                     "lbfgs_parametrization": ("sqrt_cov", "quat_scale")}

    def __post_init__(self) -> None:
        positive = {"tau": self.tau, "voxel_size_m": self.voxel_size_m, "chi2_gate": self.chi2_gate,
                    "lbfgs_lr": self.lbfgs_lr, "lbfgs_tolerance_change": self.lbfgs_tolerance_change,
                    "lbfgs_tolerance_grad": self.lbfgs_tolerance_grad}
        for name, v in positive.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"MergeConfig.{name} must be a positive finite number, got {v!r}")
        for name in ("window_keyframes", "lbfgs_max_iter", "lbfgs_history"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ConfigError(f"MergeConfig.{name} must be an integer >= 1, got {v!r}")
        if not (isinstance(self.max_per_voxel, int) and self.max_per_voxel >= 2):
            raise ConfigError(f"MergeConfig.max_per_voxel must be an integer >= 2, got {self.max_per_voxel!r}")
        if self.lbfgs_parametrization not in ("sqrt_cov", "quat_scale"):
            raise ConfigError("MergeConfig.lbfgs_parametrization must be 'sqrt_cov' or 'quat_scale', "
                              f"got {self.lbfgs_parametrization!r}")
        if self.colour_from not in ("older", "newer"):
            raise ConfigError(f"MergeConfig.colour_from must be 'older' or 'newer', got {self.colour_from!r}")
        if len(self.init_scale_offset_m) != 3 or not all(math.isfinite(d) and d >= 0
                                                         for d in self.init_scale_offset_m):
            raise ConfigError("MergeConfig.init_scale_offset_m must be 3 finite numbers >= 0, "
                              f"got {self.init_scale_offset_m!r}")
        if not 0.0 < self.slerp_t < 1.0:
            raise ConfigError(f"MergeConfig.slerp_t must be in (0, 1), got {self.slerp_t!r}")
