"""Kernels loaded (on a fresh install: compiled) beside a node's executor, not on its first frame,
and the heap settled once a node has started (``settle_heap``)."""
from __future__ import annotations

import gc
import threading
import time
from collections.abc import Callable

__all__ = ["WarmUpThread", "settle_heap"]


def settle_heap() -> None:
    """Collect what starting left behind, then exempt every object alive now from the cyclic
    garbage collector's full passes (``gc.freeze``). A node's imports (numba, scipy, rclpy, torch)
    leave ~150k tracked objects, and each full pass walked them all: 70-86 ms with the GIL held, a
    pass every few hundred frames, 4-5 frames of a 60 Hz camera that the tracker's queue then
    dropped. Reference counting still frees the frozen objects; only cycles among them stay."""
    gc.collect()
    gc.freeze()


class WarmUpThread:
    """Runs ``warm`` on a thread of its own; ``on_done(seconds, error or None)`` is called on that
    thread when it ends, then ``ready`` is set (also after a failure: a failed warm-up only costs
    the first frame the time)."""

    def __init__(self, warm: Callable[[], None], on_done: Callable[[float, Exception | None], None],
                 name: str = "warm-up") -> None:
        self.ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(warm, on_done), name=name, daemon=True)
        self._thread.start()

    def _run(self, warm: Callable[[], None], on_done: Callable[[float, Exception | None], None]) -> None:
        t0 = time.perf_counter()
        error: Exception | None = None
        try:
            warm()
            settle_heap()  # what compiling left, before the first frame
        except Exception as err:  # noqa: BLE001 - reported through on_done
            error = err
        try:
            on_done(time.perf_counter() - t0, error)
        finally:
            self.ready.set()

    def wait(self, timeout_s: float) -> bool:
        """Whether it has ended within ``timeout_s``."""
        return self.ready.wait(timeout_s)

    def join(self, timeout_s: float) -> None:
        """Wait at most ``timeout_s`` for the thread (a process exiting under a native compile aborts)."""
        self._thread.join(timeout_s)
