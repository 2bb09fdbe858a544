"""The planner service: task, driver state, odometry and maps in; commands and task events out.

A thin adapter around :class:`services.planner.executive.Executive`. In lock-step
mode a decision waits for the map that fused the frame taken after the last
command; rather than wait for the mapping service's next periodic snapshot,
the planner asks its queryable for one as soon as the driver reports the frame.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from pydantic import Field

from services.planner.executive import Executive, ExecutiveConfig
from shared import keys
from shared.bus import Bus
from shared.messages import DriverState, JsonMessage, MapSnapshot, Odometry, PlanCommand, TaskEvent, TaskSpec
from shared.service import Service, ServiceConfig


class PlannerServiceConfig(ServiceConfig, ExecutiveConfig):
    tick_hz: float = Field(default=20.0, gt=0, description="how often the protocol is polled")
    query_timeout_s: float = Field(default=0.5, gt=0, description="wait this long for a map on request")


class PlannerService(Service):
    name = "planner"
    Config = PlannerServiceConfig
    config: PlannerServiceConfig

    def __init__(self, bus: Bus, config: PlannerServiceConfig) -> None:
        super().__init__(bus, config)
        self.tick_hz = config.tick_hz
        self._lock = threading.Lock()
        self.executive = Executive(ExecutiveConfig.model_validate(
            config.model_dump(include=set(ExecutiveConfig.model_fields))))

    def start(self) -> None:
        robot = self.bus.robot_id
        self.commands = self.bus.publisher(keys.plan_command(robot), PlanCommand)
        self.events = self.bus.publisher(keys.task_events(robot), TaskEvent)
        ex = self.executive
        self.bus.subscribe(keys.task_current(robot), TaskSpec, self._locked(ex.on_task))
        self.bus.subscribe(keys.driver_state(robot), DriverState, self._locked(ex.on_driver))
        self.bus.subscribe(keys.odom(robot), Odometry, self._locked(ex.on_odom), latest_only=True)
        self.bus.subscribe(keys.map_snapshot(robot), MapSnapshot, self._locked(ex.on_snapshot),
                           latest_only=True)

    def _locked(self, handler: Any) -> Any:
        def call(msg: Any) -> None:
            with self._lock:
                handler(msg)
        return call

    def tick(self) -> None:
        with self._lock:
            wanted = self.executive.wanted_seq()
        if wanted is not None:  # lock-step: fetch the map now instead of waiting for its next put
            snapshot = self.bus.get(keys.map_snapshot(self.bus.robot_id), MapSnapshot,
                                    self.config.query_timeout_s)
            if snapshot is not None:
                with self._lock:
                    self.executive.on_snapshot(snapshot)
        with self._lock:
            out = self.executive.poll(time.time())
        for msg in out:
            self._publish(msg)

    def _publish(self, msg: JsonMessage) -> None:
        if isinstance(msg, PlanCommand):
            self.commands.put(msg)
        elif isinstance(msg, TaskEvent):
            self.events.put(msg)

    def info(self) -> dict[str, Any]:
        with self._lock:
            ex = self.executive
            task = ex.task
            return {"task": None if task is None else task.task_id,
                    "state": None if task is None else task.state.value,
                    "steps": 0 if task is None else task.steps,
                    "found": [] if task is None else list(task.found),
                    "waiting": ex.waiting,
                    "in_flight": None if ex.in_flight is None else ex.in_flight.command.action_id}
