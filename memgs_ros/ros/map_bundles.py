"""Map bundles over ROS: each node's part, and the merger's ``memgs/save_map`` that assembles them.

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

import json
import os
import secrets
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.client import Client
from rclpy.node import Node
from std_srvs.srv import Trigger

from memgs_ros.core.gaussians.records import GaussianRecords
from memgs_ros.core.maps.bundle import (
    MAPPER_FILE,
    PLY_FILE,
    TRACKER_FILE,
    Manifest,
    commit_bundle,
    discard_staging,
    new_staging,
)
from memgs_ros.core.maps.ply import ids_sidecar_path, save_ply
from memgs_ros.errors import MemgsError, PipelineError
from memgs_ros.ros.diagnostics import MergerStats
from memgs_ros.ros.hand_over import HandOver
from memgs_ros.ros.service_calls import call_within

__all__ = ["BundleAssembler", "answer", "in_thread", "part_path"]

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


def _tracker_header(path: Path) -> dict[str, Any]:
    with np.load(path, allow_pickle=False) as z:
        return dict(json.loads(bytes(z["header"]).decode()))


class BundleAssembler:
    """The merger's side of ``memgs/save_map``: the parts asked for, the bundle committed."""

    def __init__(self, node: Node, params: Any, stats: MergerStats) -> None:
        self.node, self.params, self.stats = node, params, stats
        group = ReentrantCallbackGroup()
        self.tracker = node.create_client(Trigger, "memgs/tracker/save_map_part", callback_group=group)
        self.mapper = node.create_client(Trigger, "memgs/mapper/save_map_part", callback_group=group)
        self.hand_over = HandOver(node)

    async def _part(self, client: Client, what: str) -> list[str]:
        if not client.service_is_ready():
            raise PipelineError(f"no {what} answers {client.srv_name}: cannot save a map bundle")
        res = await call_within(self.node, client, Trigger.Request(), PART_TIMEOUT_S)
        if res is None:
            raise PipelineError(f"the {what} did not write its part within {PART_TIMEOUT_S:.0f} s")
        if not res.success:
            raise PipelineError(f"the {what} could not save its part: {res.message}")
        return str(res.message).split()

    async def save(self, records: GaussianRecords, frame: str) -> Path | None:
        """The bundle of ``records`` and the nodes' parts, or None: no ``bundle_dir``, an empty map,
        or a save that failed (``problem.bundle_failed``: the PLY beside it is saved all the same)."""
        if not self.params.bundle_dir or not len(records):
            return None
        try:
            return await self._save(records, frame)
        except (MemgsError, OSError) as err:
            self.stats.problem("bundle_failed", f"could not save a map bundle in {self.params.bundle_dir}: {err}")
            return None

    async def _save(self, records: GaussianRecords, frame: str) -> Path:
        """Ask for the parts, then stage and commit the bundle (on a thread: hashing ~100 MB)."""
        tracker_part = Path((await self._part(self.tracker, "tracker"))[0])
        mapper_answer = await self._part(self.mapper, "mapper")
        mapper_part = Path(mapper_answer[0])
        sh = int(dict(kv.split("=", 1) for kv in mapper_answer[1:] if "=" in kv).get("sh_degree", 3))
        records = records.select(np.arange(len(records)))  # a copy: deltas go on meanwhile
        p = self.params

        def assemble() -> Path:
            staging = new_staging(p.bundle_dir)
            try:
                os.replace(tracker_part, staging / TRACKER_FILE)
                os.replace(mapper_part, staging / MAPPER_FILE)
                save_ply(records, staging / PLY_FILE)
                h = _tracker_header(staging / TRACKER_FILE)
                manifest = Manifest(0, h["camera"], h["mode"], float(h.get("depth_scale", 0.0)), sh, frame,
                                    int(h.get("frames", 0)), int(h["keyframes"]), len(records), p.map_source,
                                    time.strftime("%Y-%m-%dT%H:%M:%S%z"))
                return commit_bundle(staging, manifest)
            except BaseException:
                discard_staging(staging)
                raise

        bundle = await self.hand_over.result(in_thread(assemble, "map-bundle"))
        self.stats.bundles += 1
        size = sum(f.stat().st_size for f in bundle.iterdir() if f.is_file())
        self.stats.bundle_mb = round(size / 1e6, 2)
        self.node.get_logger().info(f"map bundle saved: {bundle} ({size / 1e6:.1f} MB; the PLY "
                                    f"{(bundle / PLY_FILE).stat().st_size / 1e6:.1f} MB, its ids "
                                    f"{ids_sidecar_path(bundle / PLY_FILE).stat().st_size / 1e6:.2f} MB)")
        return bundle
