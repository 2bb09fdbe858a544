"""The perception service: a thin adapter over :class:`ovamos.services.perception.core.PerceptionCore`.

Wiring (:data:`ovamos.shared.topology.TOPOLOGY`, ``perception``): ``sensors/rgbd``
frames, ``task/current`` and ``task/events`` in, ``perception/result`` out, for
each robot in ``robots`` (default: its own ``--robot-id``; ``["*"]``: every
robot on the network), each result on its frame's robot's key. Everything runs
on the service's one thread (:func:`ovamos.shared.service.run_service`): Zenoh's
callbacks only enqueue on the bus's inbox, the handlers below and the model
calls run one at a time, and :meth:`PerceptionService.info` is read by that
thread too (the loop copies it for stats queries), so the state needs no lock.
After each message, and on every tick, the adapter publishes the results of the
batches that are due (:meth:`~PerceptionCore.poll`).

Frames: while the model works, only the newest ``queue_frames`` frames of each
robot wait in the inbox (default 1: a newer frame replaces the waiting one,
counted as ``dropped`` on that robot's frame key), so a slow model never works
on stale frames or lets memory grow. Task messages are never dropped and keep
their order. A frame the core rejects is counted as ``malformed`` on its frame
key (as the bus counts undecodable ones).

Replicas: membership is the set of ``ready`` liveliness tokens under this
service's own robot id (a fleet's perception runs under one id, e.g. ``fleet``),
watched through the inbox like messages; this replica declares its own once the
backend is loaded and its inputs are wired, and withdraws it first when it
stops. Each robot it serves by name also sees it among its own services (an
``alive`` token and stats under that robot: ``ovamos status``, the gateway's health).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from ovamos.services.perception.backend import PerceptionBackend, load_backend
from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.core import PerceptionCore
from ovamos.shared import keys
from ovamos.shared.bus import BusCore
from ovamos.shared.messages import TaskSpec
from ovamos.shared.service import Service

__all__ = ["PerceptionService"]


class PerceptionService(Service):
    name = "perception"
    Config = PerceptionServiceConfig
    config: PerceptionServiceConfig
    #: how often a batch still waiting for frames is checked against ``batch_wait_ms``
    tick_hz = 200.0

    def __init__(self, bus: BusCore, config: PerceptionServiceConfig,
                 backend: PerceptionBackend | None = None) -> None:
        super().__init__(bus, config)
        self.core = PerceptionCore(config, backend or load_backend(config), config.robots or [bus.robot_id],
                                   bus.instance, bus.log, self._count_malformed)
        self._ready: Any = None

    def start(self) -> None:
        robot = self.bus.robot_id
        core = self.core
        self.wire_robots(core.robots, {
            "task_current": self._fed(self._on_task), "task_events": self._fed(core.on_event),
            "rgbd": self._fed(core.on_frame)}, keep={"rgbd": self.config.queue_frames})
        self.bus.watch_liveliness(keys.ready(robot, self.name), self._on_member)
        for other in core.robots:
            if other not in (robot, keys.ANY):
                self.bus.serve_robot(other)
        # Last: the backend is loaded (in __init__) and frames are taken, so the others may now
        # hand this replica its share.
        self._ready = self.bus.declare_token(keys.ready(robot, self.name, self.bus.instance))

    def _fed(self, handler: Callable[[str, Any, float], None]) -> Callable[[str, Any], None]:
        """An input handler: the core's ``handler`` with the message's time of arrival, then a
        :meth:`tick`, so a batch runs as soon as the message makes it due."""
        def feed(robot: str, msg: Any) -> None:
            handler(robot, msg, time.monotonic())
            self.tick()
        return feed

    def _on_task(self, robot: str, task: TaskSpec, now: float) -> None:
        """The core's, then its word on targets it can never see, with every copy of the task the
        gateway re-sends (so a planner started later hears it too)."""
        self.core.on_task(robot, task, now)
        unknown = self.core.unknown_targets(robot)
        if unknown is not None and not task.cancelled:
            self.output("unknown_targets", robot).put(unknown)

    def _on_member(self, key: str, alive: bool) -> None:
        self.core.on_replica(keys.parse_service_key(key).instance, alive)

    def _count_malformed(self, robot: str) -> None:
        self.bus.counters.bump(keys.rgbd(robot), "malformed")

    def tick(self) -> None:
        """Publish the results of the batches now due, each on its robot's key."""
        for robot, result in self.core.poll(time.monotonic()):
            self.output("perception_result", robot).put(result)

    def info(self) -> dict[str, Any]:
        return self.core.info()

    def stop(self) -> None:
        """Withdraw the ``ready`` token first: the others take over this replica's share at once
        (the loop has ended, so no frame is in progress; the bus closes the rest)."""
        if self._ready is not None:
            token, self._ready = self._ready, None
            token.undeclare()
