"""The mapping service: frames + perception results in, map snapshots out.

A thin adapter over :class:`ovamos.services.mapping.core.MappingCore` (how frames meet their
results, one map per odometry session, checkpoints): it wires the declared inputs to the core,
puts the snapshot :meth:`~MappingCore.poll` returns every ``1 / publish_hz`` s, and answers
snapshot queries, all on the service's one thread.
"""

from __future__ import annotations

import time
from typing import Any

from ovamos.services.mapping.config import MappingServiceConfig
from ovamos.services.mapping.core import MappingCore
from ovamos.services.mapping.state import MapState
from ovamos.shared.bus import BusCore
from ovamos.shared.messages import Odometry, RgbdFrame
from ovamos.shared.service import Service

__all__ = ["MappingService"]


class MappingService(Service):
    name = "mapping"
    Config = MappingServiceConfig
    config: MappingServiceConfig

    def __init__(self, bus: BusCore, config: MappingServiceConfig) -> None:
        config = config.for_robot(bus.robot_id)
        super().__init__(bus, config)
        self.tick_hz = config.publish_hz
        self.core = MappingCore(config, bus.log, time.monotonic())

    @property
    def state(self) -> MapState:
        """The current map (the core replaces it when the odometry session changes)."""
        return self.core.state

    def start(self) -> None:
        self.wire({"rgbd": self._on_frame, "perception_result": self.core.on_result, "odom": self._on_odom},
                  answers={"map_snapshot": self.core.snapshot})

    def _on_frame(self, frame: RgbdFrame) -> None:
        self.core.on_frame(frame, time.monotonic())

    def _on_odom(self, odom: Odometry) -> None:
        self.core.on_odom(odom, time.monotonic())

    def tick(self) -> None:
        snapshot = self.core.poll(time.monotonic())
        if snapshot is not None:
            self.out["map_snapshot"].put(snapshot)

    def info(self) -> dict[str, Any]:
        return self.core.info()

    def stop(self) -> None:
        self.core.close()
