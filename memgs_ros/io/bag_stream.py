"""The one ROS 2 bag writer: already-serialised CDR messages, one at a time, into a bag that
appears under its name only when closed whole.

Light on purpose (rosbags only, no numpy, scipy or rclpy): the recorder node streams a run's
outputs through it and starts in a fraction of a second; :mod:`memgs_ros.io.bag_writer` writes
frames through it.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from memgs_ros.errors import DataError

__all__ = ["BagStream", "ros2_typestore"]


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
    Thread-safe: the lock orders writes from several callbacks and a concurrent close.
    """

    def __init__(self, out_path: str | os.PathLike[str], storage: str | None = None,
                 overwrite: bool = False) -> None:
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
        self.typestore = ros2_typestore()
        self._tmp_root = _tmp_sibling(out)
        self._bag_dir = self._tmp_root / out.name
        self._connections: dict[str, Any] = {}
        self._counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self._writer: Any = Writer(self._bag_dir, version=9, storage_plugin=plugins[storage])
        try:
            self._writer.open()
        except Exception as err:  # rosbags' WriterError or OSError: nothing usable was made
            self.abort()
            raise DataError(f"{out}: cannot open a bag there ({err})") from err

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

    def add_topic(self, topic: str, msgtype: str, offered_qos: Sequence[Any] = ()) -> None:
        """Register ``topic`` with ``msgtype`` (``pkg/msg/Name``, a Jazzy type) before writing to it.

        offered_qos: rosbags ``Qos`` profiles of its publishers, kept in the bag so a player can
        offer them again (a latched map stays latched). DataError for a type the Jazzy store
        does not know: its schema could not be written."""
        if msgtype not in self.typestore.types:
            raise DataError(f"{self.path}: topic {topic}: message type {msgtype} is not a ROS 2 Jazzy type "
                            "this writer knows")
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
