"""One persistent thread pool per process for the CPU kernels that split their work (compositor
tiles, projection chunks): ``parallel_map``.

The kernels release the GIL (numba ``nogil``, torch ops), so Python threads run them in parallel.
A pool made per call started new threads every call; in a process lowered to niceness 10 (the
mapper, ``lower_priority``) those new threads kept landing on the core of the thread that made
them, and a 12k-Gaussian training step took 39 ms instead of 28 (57 ms inside the graph, every frame acknowledged).
Threads that live as long as the process are spread by the scheduler once and stay spread.

A job that itself calls ``parallel_map`` runs its inner jobs inline: a pool thread waiting on the
pool could otherwise wait for itself.
"""
from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

__all__ = ["MAX_THREADS", "cpu_threads", "parallel_map"]

_In = TypeVar("_In")
_Out = TypeVar("_Out")

MAX_THREADS = 4  # beyond 4 the kernels' per-call overhead outweighs the split at these image sizes
_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_in_pool = threading.local()


def cpu_threads() -> int:
    """Threads for one kernel call: the cores this process may run on, at most ``MAX_THREADS``."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_THREADS))


def _mark_pool_thread() -> None:
    _in_pool.active = True


def _shared_pool() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=MAX_THREADS, thread_name_prefix="memgs-kernels",
                                       initializer=_mark_pool_thread)
        return _pool


def parallel_map(fn: Callable[[_In], _Out], jobs: Sequence[_In], workers: int) -> list[_Out]:
    """``[fn(j) for j in jobs]`` on up to ``workers`` threads of the process's pool (results in
    job order; the first job's exception is raised after every job has ended)."""
    if workers <= 1 or len(jobs) <= 1 or getattr(_in_pool, "active", False):
        return [fn(j) for j in jobs]
    pool = _shared_pool()
    # n runners take the jobs in turn: at most n threads work on this call (another caller's
    # jobs may share the pool meanwhile), and one code path for any number of jobs.
    results: list[_Out | None] = [None] * len(jobs)
    cursor = iter(range(len(jobs)))
    take = threading.Lock()

    def runner() -> None:
        while True:
            with take:
                i = next(cursor, None)
            if i is None:
                return
            results[i] = fn(jobs[i])

    runners = [pool.submit(runner) for _ in range(min(workers, MAX_THREADS, len(jobs)))]
    # Each runner ends: it only runs kernels, which never wait on anything.
    errors = [r.exception() for r in runners]
    first = next((e for e in errors if e is not None), None)
    if first is not None:
        raise first
    return results  # type: ignore[return-value]
