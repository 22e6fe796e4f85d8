"""A saved map loaded at run time: ``memgs/load_map`` (``nav_msgs/srv/LoadMap``, answered as Nav2's
map_server answers it: ``map_url`` a map bundle's folder, or ``file://`` and the folder; ``result``
0 success, 1 the map does not exist, 2 its metadata (manifest) is invalid or made for another
camera, depth unit, tracker mode or format, 3 its data (a file) is missing, truncated or changed,
255 anything else; the response's ``map`` OccupancyGrid stays empty: a Gaussian map is no grid).

The merger serves ``memgs/load_map`` for the graph: it checks the bundle, then asks the mapper
(``memgs/mapper/load_map``) and the tracker (``memgs/tracker/load_map``) to restart on it. Each
of those restarts its node through the lifecycle (``ManagedNode.restart_with``: deactivate,
cleanup, which saves what it held, configure with ``map_bundle`` the new bundle, activate): the
tracker gives no pose until a frame relocalises in the new map, the mapper trains it on (or,
``map_mode`` localize, renders it), and the merger takes it from the mapper's snapshot (a new
delta epoch). The mapper's own checkpoint of the map it had is moved aside first
(``<checkpoint>.before-load-<time>``), so the new map is not overridden by it and the old one is
not lost; when the new configure fails the old map comes back.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from nav_msgs.srv import LoadMap
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.client import Client
from rclpy.node import Node

from memgs_ros.core.map_io.bundle import BundleError, check_bundle
from memgs_ros.ros.service_calls import call_within

__all__ = ["GraphMapLoader", "NodeMapLoader", "bundle_from_url", "set_aside_checkpoint"]

R = LoadMap.Response
RESULTS = {"missing": R.RESULT_MAP_DOES_NOT_EXIST, "metadata": R.RESULT_INVALID_MAP_METADATA,
           "data": R.RESULT_INVALID_MAP_DATA}
NODE_TIMEOUT_S = 120.0  # a mapper's cleanup saves its checkpoint and closes its session (up to 45 s)


def bundle_from_url(url: str) -> str:
    return url[len("file://"):] if url.startswith("file://") else url


def set_aside_checkpoint(path: str) -> Callable[[], Callable[[], None]]:
    """``prepare`` for a mapper's restart: its checkpoint moved aside (and back on undo)."""
    def prepare() -> Callable[[], None]:
        p = Path(path).expanduser() if path else None
        if p is None or not p.exists():
            return lambda: None
        aside = p.with_name(f"{p.name}.before-load-{int(time.time())}")
        p.replace(aside)

        def undo() -> None:
            aside.replace(p)

        return undo
    return prepare


class NodeMapLoader:
    """``service`` (LoadMap) on a managed tracker or mapper (made in its constructor: it outlives
    cleanups): the bundle checked with ``check()``'s keyword arguments, then the node restarted on it."""

    def __init__(self, node: Any, service: str, check: Callable[[], dict[str, Any]],
                 prepare: Callable[[], Callable[[], None]] | None = None) -> None:
        self.node, self.check, self.prepare = node, check, prepare
        node.create_service(LoadMap, service, self.on_load)

    def on_load(self, req: LoadMap.Request, res: LoadMap.Response) -> LoadMap.Response:
        log = self.node.get_logger()
        try:
            bundle, _ = check_bundle(bundle_from_url(req.map_url), **self.check())
        except BundleError as err:
            log.error(f"load_map refused: {err}")
            res.result = RESULTS[err.kind]
            return res
        why = self.node.restart_with({"map_bundle": str(bundle)}, self.prepare)
        if why is not None:
            log.error(f"load_map: could not start from {bundle}, back on the previous map: {why}")
        res.result = R.RESULT_SUCCESS if why is None else R.RESULT_INVALID_MAP_DATA
        return res


class GraphMapLoader:
    """The merger's ``memgs/load_map``: checks the bundle, then restarts the mapper and the tracker on it."""

    def __init__(self, node: Node) -> None:
        self.node = node
        group = ReentrantCallbackGroup()
        self.clients = [(what, node.create_client(LoadMap, f"memgs/{what}/load_map", callback_group=group))
                        for what in ("mapper", "tracker")]
        node.create_service(LoadMap, "memgs/load_map", self.on_load, callback_group=ReentrantCallbackGroup())

    async def _call(self, client: Client, url: str) -> int:
        if not client.service_is_ready():
            return R.RESULT_UNDEFINED_FAILURE
        res = await call_within(self.node, client, LoadMap.Request(map_url=url), NODE_TIMEOUT_S)
        return R.RESULT_UNDEFINED_FAILURE if res is None else int(res.result)

    async def on_load(self, req: LoadMap.Request, res: LoadMap.Response) -> LoadMap.Response:
        log = self.node.get_logger()
        try:
            bundle, _ = check_bundle(bundle_from_url(req.map_url))
        except BundleError as err:
            log.error(f"load_map refused: {err}")
            res.result = RESULTS[err.kind]
            return res
        for what, client in self.clients:
            res.result = await self._call(client, str(bundle))
            if res.result != R.RESULT_SUCCESS:
                log.error(f"load_map {bundle}: the {what} answered {res.result}")
                return res
        log.info(f"load_map: the graph restarted on {bundle}")
        return res
