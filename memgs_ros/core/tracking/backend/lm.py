"""The one Levenberg-Marquardt loop of the tracker: local BA, global BA and the pose graph.

Each solver supplies two functions and keeps its own linear algebra:

- ``evaluate(x) -> (aux, cost)``: the cost of state ``x`` and whatever the linearisation needs
  again (residuals, camera-frame points);
- ``linearise(x, aux) -> propose``: forms the normal equations at ``x`` once and returns
  ``propose(lam)``, the damped step's new state, or None when that solve failed (the damping
  then grows, as for a step that did not lower the cost).

``lm_iterations`` yields after every outer iteration, so a caller can stop on a time budget or
spread the work over several calls (the back-end interleaves a global BA with local ones);
``solve`` runs it to the end.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

X = TypeVar("X")  # solver state (poses, points)
A = TypeVar("A")  # what evaluate hands to linearise

@dataclass(frozen=True)
class LMSettings:
    """Damping schedule and stop rule. A step that lowers the cost divides ``lam`` by ``lam_down``
    (not below ``lam_min``); a rejected or failed one multiplies it by 10, ``attempts`` times at
    most per iteration. Converged when the decrease is under ``abs_tol + rel_tol * cost``."""

    lam0: float = 1e-3
    lam_down: float = 3.0
    lam_min: float = 1e-7
    attempts: int = 6
    rel_tol: float = 1e-6
    abs_tol: float = 0.0


@dataclass(frozen=True, eq=False)
class LMProgress(Generic[X, A]):
    """The accepted state after ``iterations`` outer iterations (0: the initial one)."""

    x: X
    aux: A
    cost: float
    initial_cost: float
    n_evaluations: int
    iterations: int


def lm_iterations(x: X, evaluate: Callable[[X], tuple[A, float]],
                  linearise: Callable[[X, A], Callable[[float], X | None]], max_iterations: int,
                  settings: LMSettings = LMSettings()) -> Iterator[LMProgress[X, A]]:
    """Yield the initial state, then the state after each iteration until it stops improving,
    converges or ``max_iterations`` are done."""
    aux, cost = evaluate(x)
    cost0, lam, n_eval = cost, settings.lam0, 1
    yield LMProgress(x, aux, cost, cost0, n_eval, 0)
    for it in range(1, max_iterations + 1):
        propose = linearise(x, aux)
        improved = converged = False
        for _ in range(settings.attempts):
            x_new = propose(lam)
            if x_new is None:
                lam *= 10.0
                continue
            aux_new, cost_new = evaluate(x_new)
            n_eval += 1
            if np.isfinite(cost_new) and cost_new < cost:
                converged = cost - cost_new < settings.abs_tol + settings.rel_tol * cost
                x, aux, cost = x_new, aux_new, cost_new
                lam = max(lam / settings.lam_down, settings.lam_min)
                improved = True
                break
            lam *= 10.0
        yield LMProgress(x, aux, cost, cost0, n_eval, it)
        if not improved or converged:
            return


def solve(iterations: Iterator[LMProgress[X, A]], time_budget_s: float | None = None) -> LMProgress[X, A]:
    """Run ``iterations`` to the end, or until ``time_budget_s`` of wall time is spent (checked
    before each iteration, so a budget of 0 returns the initial state)."""
    t0 = time.perf_counter()
    last = next(iterations)
    while time_budget_s is None or time.perf_counter() - t0 <= time_budget_s:
        progress = next(iterations, None)
        if progress is None:
            break
        last = progress
    return last


__all__ = ["LMProgress", "LMSettings", "lm_iterations", "solve"]
