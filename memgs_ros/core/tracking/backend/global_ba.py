"""Global bundle adjustment: every keyframe and point, sparse Schur complement.

``local_bundle_adjustment`` forms the camera-point blocks densely per point ([P, 3, 6C]), fine for a
window of ~10 keyframes but quadratic in memory and time for the whole map. Here the reduced camera
system is accumulated only over pairs of observations of the same point (each point is seen by a
handful of keyframes), so one Levenberg-Marquardt step costs O(sum over points of n_obs^2) plus one
dense [6C, 6C] solve: ~0.1 s for 60 keyframes and 20k observations.

Same residuals, Huber IRLS weights, normal-equation blocks (``BAGeometry``) and Levenberg-Marquardt
loop (``lm``) as the local BA; the tracker's back-end runs it after a loop correction (ORB-SLAM's
global BA), one iteration at a time between its other work (``global_ba_iterations``).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from memgs_ros.core.tracking.backend.bundle_adjustment import (
    BAAux,
    BAGeometry,
    BAProblem,
    BAResult,
    BAState,
    _obs_pairs,
)
from memgs_ros.core.tracking.backend.lm import LMProgress, lm_iterations, solve


def global_ba_iterations(prob: BAProblem, K: np.ndarray, bf: float, huber_px: float, max_iterations: int
                         ) -> tuple[BAGeometry, Iterator[LMProgress[BAState, BAAux]]]:
    """The problem's geometry and its LM iterations (first the initial state); ``geometry.result``
    turns any of them into a BAResult."""
    g = BAGeometry(prob, K, bf, huber_px)
    nf = g.nf
    # Observation pairs of one point, both by free cameras: the reduced system's off-diagonal blocks.
    q1, q2 = _obs_pairs(g.of_pt, g.n_points)
    pair_idx = ((g.of_slot[q1] * 6)[:, None, None] + np.arange(6)[None, :, None]) * (6 * nf) \
        + (g.of_slot[q2] * 6)[:, None, None] + np.arange(6)[None, None, :]  # [Q, 6, 6] into S.ravel()

    def linearise(x: BAState, aux: BAAux) -> Callable[[float], BAState | None]:
        b = g.blocks(x, aux)

        def propose(lam: float) -> BAState | None:
            Hpp_inv = np.linalg.inv(b.Hpp + lam * b.Hpp * np.eye(3) + 1e-9 * np.eye(3))  # [P, 3, 3]
            W = np.matmul(b.Hcp, Hpp_inv[g.of_pt])  # [F, 6, 3]
            S = np.zeros((6 * nf, 6 * nf))
            for i in range(nf):
                S[6 * i:6 * i + 6, 6 * i:6 * i + 6] = b.Hcc[i] + lam * b.Hcc[i] * np.eye(6) + 1e-9 * np.eye(6)
            blocks = np.matmul(W[q1], b.Hcp[q2].transpose(0, 2, 1))  # [Q, 6, 6]
            S -= np.bincount(pair_idx.ravel(), blocks.ravel(), minlength=S.size).reshape(S.shape)
            rhs = b.gc - g.per_cam.sum(np.einsum("fij,fj->fi", W, b.gp[g.of_pt]))
            try:
                dc = -np.linalg.solve(S, rhs.ravel()).reshape(nf, 6)
            except np.linalg.LinAlgError:
                return None
            corr = g.per_free_point.sum(np.einsum("fij,fi->fj", b.Hcp, dc[g.of_slot]))  # dX = Hpp^-1 (-gp - Hpc dc)
            return g.stepped(x, dc, -np.einsum("pij,pj->pi", Hpp_inv, b.gp + corr))

        return propose

    return g, lm_iterations(g.initial(), g.evaluate, linearise, max_iterations)


def global_bundle_adjustment(prob: BAProblem, K: np.ndarray, bf: float, huber_px: float,
                             max_iterations: int, time_budget_s: float | None = None) -> BAResult:
    """Jointly refine the free keyframe poses and all points (see the module docstring).

    prob: BAProblem (T_cw [C, 4, 4], fixed [C], points_w [P, 3], observations [O]); at least one
    camera should be fixed (the gauge). Stops after ``max_iterations``, on convergence, or once
    ``time_budget_s`` of wall time is spent (the result so far).
    """
    g, iterations = global_ba_iterations(prob, K, bf, huber_px, max_iterations)
    return g.result(solve(iterations, time_budget_s))


__all__ = ["global_ba_iterations", "global_bundle_adjustment"]
