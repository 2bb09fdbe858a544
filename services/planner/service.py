"""The planner service: task, driver state, odometry and maps in; commands and task events out.

A thin adapter around :class:`services.planner.executive.Executive`, on the
service's one thread (handlers and ticks never overlap, so no lock). In
lock-step mode a decision waits for a map that fused a frame taken after the
last command; rather than wait for the mapping service's next periodic
snapshot, the planner asks its queryable for one (without blocking: the reply
arrives as an event like any message).

The robot is reachable while the liveliness token of a service that drives it
(one whose outputs include ``driver/state``: ``base_driver``, ``sim``) is seen;
once every one has gone (the link to the robot is down), the executive waits
with the reason "robot unreachable" and resumes when one is back.
"""

from __future__ import annotations

import time
from typing import Any

from pydantic import Field

from services.planner.executive import DRIVER_OFF, Executive, ExecutiveConfig
from shared import keys
from shared.bus import BusCore
from shared.config import ServiceConfig
from shared.messages import DecisionTrace, MapSnapshot, PlanCommand, TaskEvent
from shared.service import Service
from shared.topology import TOPOLOGY

#: the services that drive a robot: their liveliness says whether it is reachable
DRIVERS = tuple(name for name, node in TOPOLOGY.items()
                if any(p.name == "driver_state" for p in node.outputs))


_PORTS = {PlanCommand: "plan_command", TaskEvent: "task_events", DecisionTrace: "plan_trace"}
"""The output port of each message type :meth:`Executive.poll` returns."""


class PlannerServiceConfig(ServiceConfig, ExecutiveConfig):
    tick_hz: float = Field(default=20.0, gt=0, description="how often the protocol is polled")
    query_timeout_s: float = Field(default=0.5, gt=0, description="wait this long for a map on request")


class PlannerService(Service):
    name = "planner"
    Config = PlannerServiceConfig
    config: PlannerServiceConfig

    def __init__(self, bus: BusCore, config: PlannerServiceConfig) -> None:
        super().__init__(bus, config)
        self.tick_hz = config.tick_hz
        self.executive = Executive(ExecutiveConfig.model_validate(
            config.model_dump(include=set(ExecutiveConfig.model_fields))))
        self._asked_for: int | None = None  # the command a map request in flight is for
        self._map_key = TOPOLOGY[self.name].port("queries", "map_snapshot").key(bus.robot_id)
        self._drivers: set[str] = set()  # the live tokens of services driving the robot

    def start(self) -> None:
        ex = self.executive
        self.wire({"task_current": ex.on_task, "driver_state": ex.on_driver, "camera_state": ex.on_camera,
                   "odom": ex.on_odom, "map_snapshot": ex.on_snapshot})
        for service in DRIVERS:
            self.bus.watch_liveliness(keys.alive(self.bus.robot_id, service), self._on_driver_token)

    def _on_driver_token(self, key: str, alive: bool) -> None:
        was = bool(self._drivers)
        (self._drivers.add if alive else self._drivers.discard)(key)
        if bool(self._drivers) != was:
            self.executive.on_robot_link(bool(self._drivers))
            if self._drivers:
                self.log.info("robot reachable (%s alive)", ", ".join(sorted(self._drivers)))
            elif self.executive.unreachable_why == DRIVER_OFF:
                self.log.info("the robot's driver shut down (%s gone after saying so); waiting for it", key)
            else:
                self.log.warning("robot unreachable: %s gone (the link to the robot is down, or its "
                                 "driver died); waiting for it", key)

    def tick(self) -> None:
        wanted = self.executive.map_wanted()
        if wanted is not None and self._asked_for is None:
            self._asked_for = wanted
            self.bus.request(self._map_key, MapSnapshot, self._on_map_reply, self.config.query_timeout_s)
        for msg in self.executive.poll(time.monotonic()):
            self.out[_PORTS[type(msg)]].put(msg)

    def _on_map_reply(self, snapshot: MapSnapshot | None) -> None:
        self._asked_for = None
        if snapshot is not None:
            self.executive.on_snapshot(snapshot)

    def info(self) -> dict[str, Any]:
        ex = self.executive
        task = ex.task
        return {"task": None if task is None else task.task_id,
                "state": None if task is None else task.state.value,
                "steps": 0 if task is None else task.steps,
                "found": [] if task is None else list(task.found),
                "waiting": ex.waiting, "robot_reachable": ex.robot_reachable,
                "in_flight": None if ex.in_flight is None else ex.in_flight.command.action_id}
