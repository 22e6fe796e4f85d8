"""The mapper's part of a map bundle (``ros/map_bundles.py``): ``memgs/mapper/save_map_part``."""
from __future__ import annotations

from typing import Any

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_srvs.srv import Trigger

from memgs_ros.core.mapping import checkpoint
from memgs_ros.errors import MemgsError
from memgs_ros.nodes.mapper.stats import MapperStats
from memgs_ros.ros.hand_over import HandOver
from memgs_ros.ros.map_bundles import answer, part_path

__all__ = ["MapperMapPart"]


class MapperMapPart:
    """The mapper's part (``memgs/mapper/save_map_part``): the session's state as a checkpoint file,
    captured and written on the session's worker (``MappingSession.save_state``)."""

    def __init__(self, node: Node, params: Any, stats: MapperStats, session: Any, hand_over: HandOver,
                 sh_degree: int) -> None:
        self.params, self.stats, self.session, self.hand_over = params, stats, session, hand_over
        self.sh_degree = sh_degree
        node.create_service(Trigger, "memgs/mapper/save_map_part", self.on_save,
                            callback_group=ReentrantCallbackGroup())

    async def on_save(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        if not self.params.bundle_dir:
            return answer(res, False, "bundle_dir is not set: no map bundle to save into")
        path = part_path(self.params.bundle_dir, "mapper")
        try:
            await self.hand_over.result(self.session.save_state(lambda st: checkpoint.save(st, path)))
        except (OSError, MemgsError) as err:
            return answer(res, False, f"could not write the mapper state {path}: {err}")
        self.stats.post_add(MapperStats.map_parts)
        return answer(res, True, f"{path} sh_degree={self.sh_degree}")
