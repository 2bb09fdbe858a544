"""Shared pieces of the perception tests: rendered frames and services run in threads."""

from __future__ import annotations

import math
import threading

from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.service import PerceptionService
from ovamos.shared import keys
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.fake_bus import FakeNetwork
from ovamos.shared.messages import PerceptionResult, RgbdFrame, TaskEvent, TaskSpec
from ovamos.shared.service import run_service
from ovamos.world.render import SceneRenderer
from tests.sim_scenes import two_rooms

ROBOT = "r1"


def render_frames(count: int, width: int = 160, height: int = 120) -> list[RgbdFrame]:
    """Frames from the kitchen of :func:`two_rooms`, turning from the fridge (west) round."""
    with SceneRenderer(two_rooms(), width, height) as renderer:
        return [renderer.render(1.5, 3.0, math.pi + i * math.pi / 4, seq=i, stamp=float(i))
                for i in range(count)]


class Robot:
    """A robot's camera and its planner's task messages on a fake network, and its results."""

    def __init__(self, network: FakeNetwork, robot_id: str = ROBOT) -> None:
        bus = network.bus(robot_id, "test-robot")
        self.frames = bus.publisher(keys.rgbd(robot_id), RgbdFrame)
        self.tasks = bus.publisher(keys.task_current(robot_id), TaskSpec)
        self.events = bus.publisher(keys.task_events(robot_id), TaskEvent)
        self.results: list[PerceptionResult] = []
        bus.subscribe(keys.perception_result(robot_id), PerceptionResult, self.results.append)


class RunningPerception:
    """A perception service instance on its own Zenoh session, in a thread of this process."""

    def __init__(self, endpoint: str, config: PerceptionServiceConfig, instance: str = "0") -> None:
        self.stop = threading.Event()
        self.thread = threading.Thread(target=run_service, args=(
            PerceptionService, build_config(connect=[endpoint]), config),
            kwargs={"robot_id": ROBOT, "instance": instance, "stop": self.stop})
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(30)
        assert not self.thread.is_alive()
