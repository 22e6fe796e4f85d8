"""Map bundles over ROS: what each node's part service shares (the parts' paths, their answer,
writing off the executor). The merger's ``nodes/merger/bundles.py`` assembles the parts.

``memgs/save_map`` (std_srvs/Trigger, the merger) with ``bundle_dir`` set asks the tracker
(``memgs/tracker/save_map_part``) and the mapper (``memgs/mapper/save_map_part``) for their
parts, each written atomically into ``<bundle_dir>/.parts`` and answered with its path, then
moves them into a staging folder with the PLY of its own map and commits the bundle
(``core/map_io/bundle.py``): the answer's first word is the bundle's path. The three nodes must
share that folder's file system (one robot). Every wait is a coroutine's (the executors go on:
the tracker keeps tracking while its part is written, after a copy of milliseconds on its
thread) and bounded.

Loading: ``map_bundle`` on the tracker (its ``tracker.npz``: no pose until a frame relocalises
in it) and the mapper (its ``mapper.npz``: trained on, or with ``map_mode`` localize only
rendered). ``memgs run --map`` checks the bundle before any node starts; a node that still
cannot take it (a camera_info that differs) reports it and gives no pose rather than start a
new world.
"""
from __future__ import annotations

import os
import secrets
import threading
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any, TypeVar

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_srvs.srv import Trigger

from memgs_ros.errors import MemgsError
from memgs_ros.ros.hand_over import HandOver

__all__ = ["PART_TIMEOUT_S", "PartService", "answer", "in_thread", "part_path"]

T = TypeVar("T")
PART_TIMEOUT_S = 120.0  # a mapper part holds every keyframe view: seconds on a busy CPU


def in_thread(fn: Callable[[], T], name: str) -> Future[T]:
    """``fn()`` on a thread of its own; its result or error through the future."""
    done: Future[T] = Future()

    def run() -> None:
        try:
            done.set_result(fn())
        except BaseException as err:  # noqa: BLE001 - handed to the awaiting coroutine
            done.set_exception(err)

    threading.Thread(target=run, name=name, daemon=True).start()
    return done


def part_path(bundle_dir: str, node: str, suffix: str = ".npz") -> Path:
    parts = Path(bundle_dir).expanduser() / ".parts"
    parts.mkdir(parents=True, exist_ok=True)
    return parts / f"{node}-{os.getpid()}-{secrets.token_hex(4)}{suffix}"


def answer(res: Trigger.Response, ok: bool, message: str) -> Trigger.Response:
    res.success, res.message = ok, message
    return res


class PartService:
    """A node's part of a bundle: ``memgs/<name>/save_map_part`` (std_srvs/Trigger), refused while
    ``bundle_dir`` is empty. ``write(path)`` starts writing the part (on a thread or a worker: the
    future resolves once it is on disk) or answers why there is none yet (a string);
    ``saved()`` counts a part written. Answered with the part's path (and ``note``)."""

    def __init__(self, node: Node, name: str, bundle_dir: str, hand_over: HandOver,
                 write: Callable[[Path], Future[Any] | str], saved: Callable[[], None], what: str,
                 note: str = "") -> None:
        self.name, self.bundle_dir, self.hand_over = name, bundle_dir, hand_over
        self._write, self._saved, self._what, self._note = write, saved, what, note
        node.create_service(Trigger, f"memgs/{name}/save_map_part", self.on_save,
                            callback_group=ReentrantCallbackGroup())

    async def on_save(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        if not self.bundle_dir:
            return answer(res, False, "bundle_dir is not set: no map bundle to save into")
        path = part_path(self.bundle_dir, self.name)
        started = self._write(path)
        if isinstance(started, str):
            return answer(res, False, started)
        try:
            await self.hand_over.result(started)
        except (OSError, MemgsError) as err:
            return answer(res, False, f"could not write {self._what} {path}: {err}")
        self._saved()
        return answer(res, True, f"{path}{self._note}")
