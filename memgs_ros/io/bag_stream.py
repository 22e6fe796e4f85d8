"""The one ROS 2 bag writer: already-serialised CDR messages, one at a time, into a bag that
appears under its name only when closed whole.

Light on purpose (rosbags only, no numpy, scipy or rclpy): the recorder node streams a run's
outputs through it and starts in a fraction of a second; :mod:`memgs_ros.io.bag_writer` writes
frames through it.
"""
from __future__ import annotations

import contextlib
import os
import queue
import shutil
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from memgs_ros.errors import DataError

# How long close() waits for the writer thread to write what is queued (at most ``max_queued``
# messages), and abort() for it to drop the queue; past that the bag is reported, not waited for.
CLOSE_TIMEOUT_S = 120.0
ABORT_TIMEOUT_S = 10.0

__all__ = ["BackgroundBagStream", "BagStream", "ros2_typestore"]


def ros2_typestore() -> Any:
    """The ROS 2 Jazzy type store (pinned: ``Stores.LATEST`` moves with rosbags releases)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _tmp_sibling(out: Path) -> Path:
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    except OSError as err:
        raise DataError(f"{out}: cannot create the output there ({err.strerror or err})") from err


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


class BagStream:
    """A ROS 2 bag written message by message from serialised CDR bytes (Jazzy types).

    Written under a hidden temporary folder beside ``out_path`` and moved into place by
    :meth:`close`, so ``out_path`` holds either nothing (or the file it held before) or a whole
    bag with its summary and footer; :meth:`abort` (or leaving a ``with`` block by an exception)
    removes the partial one. ``out_path`` ending in ``.mcap`` / ``.db3`` is a single storage file
    that rosbags, ``ros2 bag`` and Foxglove open without ``metadata.yaml``; anything else is a
    bag folder. ``overwrite``: replace an existing file at close instead of refusing at open.
    ``typestore``: a Jazzy store already loaded (:func:`ros2_typestore`), else one is loaded here.
    Thread-safe: the lock orders writes from several callbacks and a concurrent close.
    """

    def __init__(self, out_path: str | os.PathLike[str], storage: str | None = None,
                 overwrite: bool = False, typestore: Any = None) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        out = Path(out_path)
        if storage is None:
            storage = "sqlite3" if out.suffix == ".db3" else "mcap"
        plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
        if storage not in plugins:
            raise DataError(f"{out}: unknown bag storage {storage!r}; use mcap or sqlite3")
        self.single_file = out.suffix in (".mcap", ".db3")
        if self.single_file and out.suffix != {"mcap": ".mcap", "sqlite3": ".db3"}[storage]:
            raise DataError(f"{out}: suffix {out.suffix} does not match storage {storage}")
        if out.is_dir() or (out.exists() and not (overwrite and self.single_file)):
            raise DataError(f"{out}: already exists; refusing to overwrite")
        self.path = out
        self.typestore = typestore if typestore is not None else ros2_typestore()
        self._tmp_root = _tmp_sibling(out)
        self._bag_dir = self._tmp_root / out.name
        self._connections: dict[str, Any] = {}
        self._counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self._writer: Any = None
        try:
            self._writer = Writer(self._bag_dir, version=9, storage_plugin=plugins[storage])
            self._writer.open()
        except BaseException as err:  # nothing usable was made: leave no temporary folder either
            self.abort()
            if isinstance(err, Exception):  # rosbags' WriterError, OSError; a Ctrl-C passes as it is
                raise DataError(f"{out}: cannot open a bag there ({err})") from err
            raise

    def __enter__(self) -> BagStream:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    @property
    def is_open(self) -> bool:
        return self._writer is not None

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far, by topic."""
        with self._lock:
            return dict(self._counts)

    def check_type(self, topic: str, msgtype: str) -> None:
        """DataError unless the Jazzy type store knows ``msgtype`` (its schema goes into the bag)."""
        if msgtype not in self.typestore.types:
            raise DataError(f"{self.path}: topic {topic}: message type {msgtype} is not a ROS 2 Jazzy type "
                            "this writer knows")

    def add_topic(self, topic: str, msgtype: str, offered_qos: Sequence[Any] = ()) -> None:
        """Register ``topic`` with ``msgtype`` (``pkg/msg/Name``, a Jazzy type) before writing to it.

        offered_qos: rosbags ``Qos`` profiles of its publishers, kept in the bag so a player can
        offer them again (a latched map stays latched). DataError for a type the Jazzy store
        does not know: its schema could not be written."""
        self.check_type(topic, msgtype)
        with self._lock:
            if self._writer is None:
                raise DataError(f"{self.path}: the bag is closed")
            if topic not in self._connections:
                self._connections[topic] = self._writer.add_connection(
                    topic, msgtype, typestore=self.typestore, offered_qos_profiles=list(offered_qos))
                self._counts[topic] = 0

    def write(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> bool:
        """Append one serialised (CDR) message of a registered topic at bag time ``stamp_ns``.

        False (nothing written) once the bag is closed: a recorder's callbacks may still run
        while it stops."""
        with self._lock:
            if self._writer is None:
                return False
            try:
                self._writer.write(self._connections[topic], int(stamp_ns), data)
            except OSError as err:  # disk full: the caller decides; abort() removes the partial bag
                raise DataError(f"{self.path}: cannot write bag ({err.strerror or err})") from err
            self._counts[topic] += 1
            return True

    def close(self) -> int:
        """Finish the bag (summary, footer, metadata) and move it to ``path``; returns its size in
        bytes. A second call does nothing and returns the size."""
        with self._lock:
            if self._writer is None:
                return _size(self.path) if self.path.exists() else 0
            writer, self._writer = self._writer, None
            try:
                writer.close()
                if self.single_file:
                    produced = next(p for p in self._bag_dir.iterdir() if p.suffix == self.path.suffix)
                    os.replace(produced, self.path)
                else:
                    os.replace(self._bag_dir, self.path)
            except OSError as err:
                raise DataError(f"{self.path}: cannot write bag ({err.strerror or err})") from err
            finally:
                shutil.rmtree(self._tmp_root, ignore_errors=True)
            return _size(self.path)

    def abort(self) -> None:
        """Drop the partial bag; ``path`` is left as it was."""
        with self._lock:
            writer, self._writer = self._writer, None
            if writer is not None:
                with contextlib.suppress(Exception):  # the partial bag is removed either way
                    writer.close()
            shutil.rmtree(self._tmp_root, ignore_errors=True)


class BackgroundBagStream:
    """A :class:`BagStream` fed through a queue and written by a thread of its own.

    Python raises KeyboardInterrupt (Ctrl-C; rclpy's SIGINT handler chains to it) in the main
    thread between any two bytecodes, so a write cut there would leave half a record in the file.
    Here callers only enqueue: a Ctrl-C can lose the message being enqueued, never corrupt the
    bag, and the file I/O leaves the caller's (executor) thread. At most ``max_queued`` messages
    wait; a full queue makes :meth:`write` wait, which pushes back on the subscription's queue.
    A write error in the thread (disk full) is raised as DataError by the next call.
    """

    def __init__(self, out_path: str | os.PathLike[str], overwrite: bool = False, typestore: Any = None,
                 max_queued: int = 1000) -> None:
        self._bag = BagStream(out_path, "mcap", overwrite=overwrite, typestore=typestore)
        self.path = self._bag.path
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=max_queued)
        self._closing = False
        self._error: Exception | None = None
        self._thread = threading.Thread(target=self._run, name="bag-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            if self._error is not None:
                continue  # drain; the caller hears of the error
            try:
                if item[0] == "topic":
                    self._bag.add_topic(*item[1:])
                else:
                    self._bag.write(*item[1:])
            except Exception as err:  # noqa: BLE001 - handed to the caller's thread
                self._error = err

    def _raise_error(self) -> None:
        if self._error is not None:
            raise DataError(f"{self.path}: cannot write bag ({self._error})") from self._error

    def _put(self, item: tuple[Any, ...]) -> bool:
        self._raise_error()
        while not self._closing:
            try:
                self._queue.put(item, timeout=0.1)  # re-checks closing: the thread may have ended
                return True
            except queue.Full:
                continue
        return False

    @property
    def is_open(self) -> bool:
        return not self._closing

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far (not those still queued), by topic."""
        return self._bag.counts

    def add_topic(self, topic: str, msgtype: str, offered_qos: Sequence[Any] = ()) -> None:
        """:meth:`BagStream.add_topic`, queued before the topic's messages; an unknown type is
        refused here, at once."""
        self._bag.check_type(topic, msgtype)
        self._put(("topic", topic, msgtype, list(offered_qos)))

    def write(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> bool:
        """Queue one serialised message; False (dropped) once closing."""
        return self._put(("message", topic, int(stamp_ns), data))

    def _stop(self, timeout_s: float) -> bool:
        """Ask the thread to end after what is queued; False when it has not ended in ``timeout_s``
        (a writer stuck in I/O)."""
        end = time.monotonic() + timeout_s
        if not self._closing:
            self._closing = True
            while self._thread.is_alive():
                try:
                    self._queue.put(None, timeout=0.1)
                    break
                except queue.Full:
                    if time.monotonic() > end:
                        break
        self._thread.join(max(0.0, end - time.monotonic()))
        return not self._thread.is_alive()

    def close(self) -> int:
        """Write what is queued, finish the bag and move it into place; its size in bytes.
        DataError when writing failed or did not finish within ``CLOSE_TIMEOUT_S``."""
        if not self._stop(CLOSE_TIMEOUT_S):
            self._error = self._error or TimeoutError(f"the writer did not finish within {CLOSE_TIMEOUT_S:.0f} s")
        if self._error is not None:
            self._bag.abort()
            self._raise_error()
        return self._bag.close()

    def abort(self) -> None:
        """Drop the queue and the partial bag; the path is left as it was."""
        self._error = self._error or DataError("aborted")  # the thread skips what is still queued
        self._stop(ABORT_TIMEOUT_S)
        self._bag.abort()
