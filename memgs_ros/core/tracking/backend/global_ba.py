"""Global bundle adjustment: every keyframe and point, sparse Schur complement.

The reduced camera system is accumulated only over pairs of observations of the same point (each
point is seen by a handful of keyframes: ``BAGeometry.reduce``), so one Levenberg-Marquardt step
costs O(sum over points of n_obs^2) plus one dense [6C, 6C] solve.

Same residuals, Huber IRLS weights, normal-equation blocks and point elimination (``BAGeometry``)
and Levenberg-Marquardt loop (``lm``) as the local BA, damped on the camera blocks instead of the
reduced system; the tracker's back-end runs it after a loop correction (ORB-SLAM's global BA),
one iteration at a time between its other work (``global_ba_iterations``).
"""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from memgs_ros.core.tracking.backend.bundle_adjustment import (
    BAAux,
    BAGeometry,
    BAProblem,
    BAResult,
    BAState,
)
from memgs_ros.core.tracking.backend.lm import LMProgress, lm_iterations, solve


def global_ba_iterations(prob: BAProblem, K: np.ndarray, bf: float, huber_px: float, max_iterations: int,
                         compiled: bool | None = None) -> tuple[BAGeometry, Iterator[LMProgress[BAState, BAAux]]]:
    """The problem's geometry and its LM iterations (first the initial state); ``geometry.result``
    turns any of them into a BAResult. ``compiled``: see ``BAGeometry``."""
    g = BAGeometry(prob, K, bf, huber_px, compiled)
    return g, lm_iterations(g.initial(), g.evaluate, g.linearise(damp_cameras=True), max_iterations)


def global_bundle_adjustment(prob: BAProblem, K: np.ndarray, bf: float, huber_px: float,
                             max_iterations: int, time_budget_s: float | None = None,
                             compiled: bool | None = None) -> BAResult:
    """Jointly refine the free keyframe poses and all points (see the module docstring).

    prob: BAProblem (T_cw [C, 4, 4], fixed [C], points_w [P, 3], observations [O]); at least one
    camera should be fixed (the gauge). Stops after ``max_iterations``, on convergence, or once
    ``time_budget_s`` of wall time is spent (the result so far). ``compiled``: see ``BAGeometry``.
    """
    g, iterations = global_ba_iterations(prob, K, bf, huber_px, max_iterations, compiled)
    return g.result(solve(iterations, time_budget_s))


__all__ = ["global_ba_iterations", "global_bundle_adjustment"]
