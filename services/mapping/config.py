"""Every parameter of the mapping module (paper values as defaults).

:class:`MappingConfig` is the map's own (grid, projection, fusion, objects): the benchmark and
the tools build maps with it and no service. :class:`MappingServiceConfig` adds what the
service needs around the map: its rates, how frames wait for their results, its checkpoint and
when it follows a new odometry session.
"""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import Field

from ovamos.services.mapping.localization import LocalizationConfig
from ovamos.services.mapping.loops import LoopConfig
from ovamos.shared.config import ServiceConfig
from ovamos.shared.messages import MAX_MAP_SIDE
from ovamos.shared.robot import ROBOT
from ovamos.shared.sessions import SessionSwitch

__all__ = ["MappingConfig", "MappingServiceConfig"]


class MappingConfig(ServiceConfig):
    grid_cells: int = Field(default=1000, ge=10, le=MAX_MAP_SIDE,
                            description="the grid is square, this many cells a side (a larger map "
                                        "could not be sent: ovamos.shared.messages.MAX_MAP_SIDE)")
    resolution: float = Field(default=0.05, gt=0, description="metres per cell")
    center: tuple[float, float] = Field(default=(0.0, 0.0), description="world xy of the grid centre")
    min_obstacle_height: float = Field(default=0.15, description="points between these heights are obstacles")
    max_obstacle_height: float = Field(default=1.5)
    depth_min: float = Field(default=0.5, gt=0)
    depth_max: float = Field(default=5.0, gt=0)
    pixel_stride: int = Field(default=2, ge=1, description="use every n-th pixel row and column")
    confidence_floor: float = Field(default=0.25, ge=0, le=1,
                                    description="readings with a lower FOV confidence are ignored")
    decision_threshold: float = Field(default=0.35, ge=0, le=1,
                                      description="detection score from which a detection counts")
    robot_radius: float = Field(default=ROBOT.radius_m, ge=0, description="frontiers keep this far from obstacles")
    frontier_min_cells: int = Field(default=5, ge=1, description="smaller frontier segments are dropped")
    object_merge_distance_m: float = Field(default=0.5, gt=0)
    object_confirm_hits: int = Field(default=2, ge=1)
    object_min_hit_ratio: float = Field(
        default=0.3, ge=0, le=1,
        description="also needed to confirm: hits / views of its place (views within "
                    "object_view_range_m, unoccluded); 0 = off (see services/mapping/objects.py)")
    object_view_range_m: float = Field(default=3.0, gt=0)
    localization: LocalizationConfig = Field(
        default_factory=LocalizationConfig, description="frames matched against the map, which then "
        "lives in a map frame that odometry drift does not move (services/mapping/localization.py)")
    loops: LoopConfig = Field(default_factory=LoopConfig, description="while the map localizes by scan: "
                              "a pose graph over keyframes that re-places the map when an old place is "
                              "seen again (services/mapping/loops.py; off by default)")
    remember_frames: int = Field(
        default=16, ge=1,
        description="the newest fused frames whose targets are remembered: such a frame arriving "
                    "again adds no update counts, a second result for it only new targets' values")

    def covering(self, width_m: float, depth_m: float, margin_m: float = 2.0) -> MappingConfig:
        """This config with a grid that covers a ``width_m`` x ``depth_m`` building (its corner at the
        origin) with ``margin_m`` round it: the simulated homes' maps, a smaller grid than a map
        for any building (the per-step copies stay cheap)."""
        side = max(width_m, depth_m) + 2 * margin_m
        return self.model_copy(update={"center": (width_m / 2, depth_m / 2),
                                       "grid_cells": int(math.ceil(side / self.resolution))})


class MappingServiceConfig(MappingConfig):
    publish_hz: float = Field(default=2.0, gt=0, description="snapshot publication rate")
    match_timeout_s: float = Field(default=1.0, gt=0, description="wait this long for a frame's result")
    max_pending: int = Field(default=16, ge=1, description="frames or results waiting for their pair, "
                                                           "and fused frames kept for a second result")
    checkpoint_path: Path | None = Field(
        default=None, description="'{robot_id}' in it is replaced: one map per robot, never another's")
    checkpoint_every_s: float = Field(default=5.0, gt=0)
    session_switch: SessionSwitch = Field(
        default_factory=SessionSwitch, description="when odometry or frames of a new odometry "
        "session start a fresh map (the driver restarted)")

    def for_robot(self, robot_id: str) -> MappingServiceConfig:
        """This config with ``{robot_id}`` in ``checkpoint_path`` replaced by ``robot_id``."""
        if self.checkpoint_path is None:
            return self
        return self.model_copy(update={"checkpoint_path": Path(
            str(self.checkpoint_path).replace("{robot_id}", robot_id))})
