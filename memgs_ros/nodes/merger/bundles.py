"""The merger's ``memgs/save_map``: asks the tracker and the mapper for their parts of a map bundle,
adds the PLY of its own map and commits the bundle (``ros/map_bundles.py`` has the protocol)."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.client import Client
from rclpy.node import Node
from std_srvs.srv import Trigger

from memgs_ros.core.gaussians.records import GaussianRecords
from memgs_ros.core.map_io.bundle import (
    MAPPER_FILE,
    PLY_FILE,
    TRACKER_FILE,
    Manifest,
    commit_bundle,
    discard_staging,
    new_staging,
)
from memgs_ros.core.map_io.ply import ids_sidecar_path, save_ply
from memgs_ros.errors import MemgsError, PipelineError
from memgs_ros.nodes.merger.stats import MergerStats
from memgs_ros.ros.hand_over import HandOver
from memgs_ros.ros.map_bundles import PART_TIMEOUT_S, in_thread
from memgs_ros.ros.service_calls import call_within

__all__ = ["BundleAssembler"]


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
