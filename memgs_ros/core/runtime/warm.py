"""Kernels loaded (on a fresh install: compiled) beside a node's executor, not on its first frame."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

__all__ = ["WarmUpThread"]


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
