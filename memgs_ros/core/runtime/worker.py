"""The command worker: one thread, one queue of commands, a future per command (an actor).

Mutable state that several threads need belongs to one object that derives from
:class:`CommandWorker`: callers ``submit`` commands (closures over the state's methods) and get
``concurrent.futures.Future`` objects; only the worker thread runs them, in submission order, so
the state needs no lock. Between commands a subclass may do background work one unit at a time
(``_background``: a training step, say), so a command waits at most for the unit in progress.

What the base guarantees, whatever the commands do:

- an exception from a command goes to that command's future; one from background work goes to
  ``_on_background_error`` (by default: logged, and background work pauses briefly);
- if the worker loop itself dies (a bug in a subclass hook), it records why, ``alive`` turns
  False and every pending future fails with :class:`WorkerStopped` naming the cause, so no
  caller waits forever;
- ``close`` fails every command still queued, and every later ``submit`` fails at once.

This module holds the package's only lock and condition variable for such state: a subclass
keeps its own fields to the worker thread and hands out immutable values.
"""
from __future__ import annotations

import logging
import os
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Generic, TypeVar

from memgs_ros.errors import MemgsError

logger = logging.getLogger(__name__)

T = TypeVar("T")

# After background work failed, it pauses this long (one bad step, e.g. a CUDA hiccup, must not spin).
BACKGROUND_ERROR_PAUSE_S = 0.1


class WorkerStopped(MemgsError):
    """A command reached, or was queued on, a worker that is closed or died."""


class Command(Generic[T]):
    """A queued call: ``run`` executes on the worker; its result or exception goes to ``future``."""

    __slots__ = ("future", "name", "run")

    def __init__(self, name: str, run: Callable[[], T]) -> None:
        self.name = name
        self.run = run
        self.future: Future[T] = Future()


class CommandWorker:
    """Base of an actor (module docstring). ``name`` names the thread and the errors.

    Subclasses call ``start()`` once their state exists, and may override ``_has_background``,
    ``_background``, ``_on_background_error`` and ``_after_command``.
    """

    def __init__(self, name: str, niceness: int = 0) -> None:
        self.name = name
        self.niceness = niceness  # of the worker's thread alone (Linux keeps one per thread); 0: its creator's
        self._commands: deque[Command[Any]] = deque()
        self._cv = threading.Condition()
        self._closed = False
        self._death: BaseException | None = None
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    # ------------------------------------------------------------------ callers
    @property
    def alive(self) -> bool:
        """True while the worker runs commands (False once closed, or dead: see ``death``)."""
        return self._thread.is_alive() and not self._closed and self._death is None

    @property
    def death(self) -> BaseException | None:
        """What ended the worker loop, when it died rather than being closed."""
        return self._death

    @property
    def queued(self) -> int:
        return len(self._commands)

    def submit(self, name: str, run: Callable[[], T]) -> Future[T]:
        """Queue ``run`` (executed on the worker); its future gives the result or the exception.
        Raises :class:`WorkerStopped` when the worker is closed or dead."""
        cmd: Command[T] = Command(name, run)
        with self._cv:
            self._check_open()
            self._commands.append(cmd)
            self._cv.notify()
        return cmd.future

    def on_worker(self) -> bool:
        return threading.current_thread() is self._thread

    def close(self, timeout_s: float = 30.0, drain: bool = False) -> bool:
        """Refuse new commands and stop after the command or background unit in progress; queued
        commands fail with :class:`WorkerStopped`, or with ``drain`` run first. Returns True when
        the thread ended within ``timeout_s``. Idempotent."""
        with self._cv:
            self._closed = True
            dropped = [] if drain else list(self._commands)
            if not drain:
                self._commands.clear()
            self._cv.notify_all()
        stopped = WorkerStopped(f"{self.name} closed before the command ran")
        self._fail(dropped, stopped)
        if not self.on_worker() and self._thread.ident is not None:
            self._thread.join(timeout_s)
        if self._thread.is_alive():  # stuck in a command: what is still queued will never run
            with self._cv:
                dropped = list(self._commands)
                self._commands.clear()
            self._fail(dropped, stopped)
        return not self._thread.is_alive()

    # -------------------------------------------------------------- subclasses
    def _has_background(self) -> bool:
        """True when there is background work to do now (called under the worker's condition)."""
        return False

    def _background(self) -> float:
        """Do one unit of background work; return seconds to wait for a command before the next
        unit (0: go on at once)."""
        return 0.0

    def _on_background_error(self, err: Exception) -> float:
        """A unit of background work raised ``err``; returns the pause before the next one."""
        logger.warning("%s: background work failed: %s", self.name, err)
        return BACKGROUND_ERROR_PAUSE_S

    def _after_command(self, cmd: Command[Any]) -> None:
        """Runs on the worker after each command, before its future resolves (e.g. publish a new
        status value that includes it)."""

    def _take(self, cmd: Command[Any]) -> None:
        """A command leaves the queue to run (called under the worker's condition)."""

    def _drop_queued(self, pick: Callable[[Command[Any]], bool]) -> Command[Any] | None:
        """Remove and return the oldest queued command for which ``pick`` is true (its future is
        the caller's to resolve); for overload policies, called from ``submit`` overrides."""
        with self._cv:
            cmd = next((c for c in self._commands if pick(c)), None)
            if cmd is not None:
                self._commands.remove(cmd)
            return cmd

    @property
    def _condition(self) -> threading.Condition:
        """For a subclass's ``submit`` variant that must decide and queue atomically."""
        return self._cv

    def _check_open(self) -> None:
        if self._death is not None:
            raise WorkerStopped(f"{self.name} died: {type(self._death).__name__}: {self._death}")
        if self._closed:
            raise WorkerStopped(f"{self.name} is closed")

    def _append(self, cmd: Command[Any]) -> None:
        """Queue ``cmd`` (the caller holds ``_condition`` and has checked ``_check_open``)."""
        self._commands.append(cmd)
        self._cv.notify()

    # ------------------------------------------------------------------ worker
    def _loop(self) -> None:
        if self.niceness > 0:
            try:
                tid = threading.get_native_id()
                os.setpriority(os.PRIO_PROCESS, tid, max(os.getpriority(os.PRIO_PROCESS, tid), self.niceness))
            except OSError as err:  # a priority is a preference: the work still runs
                logger.warning("%s: could not lower its priority: %s", self.name, err)
        try:
            self._serve()
        except BaseException as err:  # noqa: BLE001 - a dead worker must fail its futures, not hang them
            logger.error("%s died: %s: %s", self.name, type(err).__name__, err)
            with self._cv:
                self._death = err
                dropped = list(self._commands)
                self._commands.clear()
            self._fail(dropped, WorkerStopped(f"{self.name} died: {type(err).__name__}: {err}"))

    def _serve(self) -> None:
        pause = 0.0
        while True:
            with self._cv:
                while True:
                    if self._commands:  # closed with drain: the queue still runs
                        cmd: Command[Any] | None = self._commands.popleft()
                        self._take(cmd)  # type: ignore[arg-type]
                        break
                    if self._closed:
                        return
                    if not self._has_background():
                        self._cv.wait()
                    elif pause > 0:
                        self._cv.wait(pause)  # a command ends the pause
                        pause = 0.0
                    else:
                        cmd = None
                        break
            if cmd is None:
                try:
                    pause = self._background()
                except Exception as err:  # noqa: BLE001 - one failed unit must not end the worker
                    pause = self._on_background_error(err)
                continue
            if not cmd.future.set_running_or_notify_cancel():
                continue
            error: BaseException | None = None
            try:
                result = cmd.run()
            except BaseException as err:  # noqa: BLE001 - handed to the caller through its future
                error = err
            try:  # the hook first: whoever waited on the future then reads a status that includes it
                self._after_command(cmd)
            finally:  # resolved even when the hook fails (which ends the worker)
                if error is not None:
                    cmd.future.set_exception(error)
                else:
                    cmd.future.set_result(result)

    @staticmethod
    def _fail(commands: list[Command[Any]], err: WorkerStopped) -> None:
        for cmd in commands:
            if not cmd.future.done():
                cmd.future.set_exception(err)
