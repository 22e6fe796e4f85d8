"""How the runner (``memgs run`` / ``demo`` / ``eval``) ends on a signal, with every node it started.

SIGTERM (what ``timeout``, systemd and CI send) and SIGHUP (the terminal went away) take the
path Ctrl-C takes: :class:`StopRequested` (a ``KeyboardInterrupt``) is raised in the main
thread, so the ``finally`` that stops the nodes (SIGINT, the merger saves its map) runs. Nodes
run in sessions of their own (a Ctrl-C reaches the runner alone, which stops them in order) and
end with the runner however it ends, SIGKILL included (``memgs_ros.core.runtime.cpu.die_with_parent``).
"""
from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class StopRequested(KeyboardInterrupt):
    """A signal asked the runner to stop (``signum``); exit status 128 + signum."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise(signum: int, _frame: FrameType | None) -> None:
    raise StopRequested(signum)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within the block SIGTERM and SIGHUP raise :class:`StopRequested` in the main thread (off
    the main thread, where Python cannot install handlers, nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def exit_status(err: KeyboardInterrupt) -> tuple[int, str]:
    """(exit status, the signal's name) for an interrupt: 130 for Ctrl-C, 128 + n for signal n."""
    signum = getattr(err, "signum", signal.SIGINT)
    return 128 + int(signum), signal.Signals(signum).name
