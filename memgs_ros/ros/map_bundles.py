"""Map bundles over ROS: what each node's part service shares (the parts' paths, their answer,
writing off the executor). The merger's ``nodes/merger/bundles.py`` assembles the parts.

``memgs/save_map`` (std_srvs/Trigger, the merger) with ``bundle_dir`` set asks the tracker
(``memgs/tracker/save_map_part``) and the mapper (``memgs/mapper/save_map_part``) for their
parts, each written atomically into ``<bundle_dir>/.parts`` and answered with its path, then
moves them into a staging folder with the PLY of its own map and commits the bundle
(``core/maps/bundle.py``): the answer's first word is the bundle's path. The three nodes must
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
from typing import TypeVar

from std_srvs.srv import Trigger

__all__ = ["PART_TIMEOUT_S", "answer", "in_thread", "part_path"]

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
