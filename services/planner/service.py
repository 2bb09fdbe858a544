"""The planner service: task, driver state, odometry and maps in; commands and task events out.

A thin adapter around :class:`ovamos.services.planner.executive.Executive`, on the
service's one thread (handlers and ticks never overlap, so no lock). In
lock-step mode a decision waits for a map that fused a frame taken after the
last command; rather than wait for the mapping service's next periodic
snapshot, the planner asks its queryable for one (without blocking: the reply
arrives as an event like any message).

The robot is reachable while the liveliness token of a service that drives it
(one whose outputs include ``driver/state``: ``base_driver``, ``sim``) is seen;
once every one has gone (the link to the robot is down), the executive waits
with the reason "robot unreachable" and resumes when one is back.

A planner restarted mid-task (killed, crashed) goes on with the progress the gateway's
TaskSpec carries (steps, distance, found targets, the budget left), and books as steps the
commands its predecessor sent after the last one it reported (``last_action``) that the
driver completed: the task's count is the commands the robot ran, whatever restarted.

Perception says which of a task's targets it can never see (``unknown_targets``, with each copy
of the task: a closed vocabulary, the sim backend's, the classes a simulated house can hold,
names them and why, ``did you mean 'candle'?``), and the task fails with that reason instead of
waiting at step 0 for ever. A real model's vocabulary is open: it names none, and nothing changes.
"""

from __future__ import annotations

import math
import time
from typing import Any

from ovamos.services.planner.config import PlannerServiceConfig
from ovamos.services.planner.executive import DRIVER_OFF, Executive, ExecutiveConfig
from ovamos.shared import keys
from ovamos.shared.bus import BusCore
from ovamos.shared.messages import (
    DecisionTrace,
    DriverState,
    MapSnapshot,
    PlanCommand,
    TaskEvent,
    TaskSpec,
    TaskStatus,
    UnknownTargets,
)
from ovamos.shared.service import Service
from ovamos.shared.topology import DRIVERS, TOPOLOGY

_PORTS = {PlanCommand: "plan_command", TaskEvent: "task_events", DecisionTrace: "plan_trace"}
"""The output port of each message type :meth:`Executive.poll` returns."""


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
        self._resumed: TaskSpec | None = None  # a task taken over mid-way, until its commands are booked
        self._lost: tuple[str, float] | None = None  # a driver's token gone: (key, when to say so)

    def start(self) -> None:
        ex = self.executive
        self.wire({"task_current": self._on_task, "driver_state": self._on_driver_state, "camera_state": ex.on_camera,
                   "unknown_targets": self._on_unknown_targets, "odom": ex.on_odom, "map_snapshot": ex.on_snapshot})
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
            else:  # said once the driver's last word could have come (it travels apart from the token)
                self._lost = (key, time.monotonic() + self.config.off_grace_s)

    def _on_driver_state(self, state: DriverState) -> None:
        self.executive.on_driver(state)
        if self._lost is not None and self.executive.unreachable_why == DRIVER_OFF:
            self.log.info("the robot's driver shut down (%s gone, saying so just after); waiting for it",
                          self._lost[0])
            self._lost = None

    def _say_if_lost(self, now: float) -> None:
        if self._lost is not None and (self._drivers or now >= self._lost[1]):
            if not self._drivers:
                self.log.warning("robot unreachable: %s gone (the link to the robot is down, or its "
                                 "driver died); waiting for it", self._lost[0])
            self._lost = None

    def _on_task(self, spec: TaskSpec) -> None:
        """A task new to this planner that already booked commands (``last_action``) is taken over
        mid-way from a planner that stopped: its unreported commands are booked once seen."""
        task = self.executive.task
        self.executive.on_task(spec)
        if self.executive.task is not task:
            self._resumed = spec if spec.last_action else None

    def _book_unreported(self) -> None:
        """Book the commands of a resumed task that the driver completed after the last one
        reported, once it is idle and the odometry after them is in (what the first decision
        waits for too), measured from the task's last reported position. Not once this planner
        has sent a command of its own: the driver's count would hold it."""
        spec, ex = self._resumed, self.executive
        task, d, odom = ex.task, ex.driver, ex.odom
        if spec is None:
            return
        if ex.in_flight is not None or task is None or task.state is not TaskStatus.SEARCHING:
            self._resumed = None
            return
        if d is None or d.active_action is not None or odom is None or odom.after_action < d.last_completed:
            return
        self._resumed = None
        if d.last_completed > task.last_action:
            moved = 0.0  # unknown without a reported position in the driver's frame
            if spec.x is not None and spec.y is not None and spec.odom_session == odom.odom_session:
                moved = math.hypot(odom.x - spec.x, odom.y - spec.y)
            self.log.warning("task %s: booking commands %d-%d (%.2f m), completed after the last one the "
                             "planner before this one reported", task.task_id, task.last_action + 1,
                             d.last_completed, moved)
            task.book_unreported(d.last_completed, moved)
            self._publish_event()

    def _publish_event(self) -> None:
        """The task's state now, not at the executive's next periodic event."""
        self.out["task_events"].put(self.executive.event())

    def tick(self) -> None:
        wanted = self.executive.map_wanted()
        if wanted is not None and self._asked_for is None:
            self._asked_for = wanted
            self.bus.request(self._map_key, MapSnapshot, self._on_map_reply, self.config.query_timeout_s)
        self._book_unreported()
        now = time.monotonic()
        self._say_if_lost(now)
        for msg in self.executive.poll(now):
            self.out[_PORTS[type(msg)]].put(msg)

    def _on_unknown_targets(self, unknown: UnknownTargets) -> None:
        """Fail the task when perception says it can never see one of its remaining targets."""
        task = self.executive.task
        if task is not None and task.state is TaskStatus.SEARCHING and set(unknown.targets) & set(task.remaining):
            task.fail(unknown.reason)
            self.log.warning("task %s failed: %s", task.task_id, unknown.reason)
            self._publish_event()

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
                "waiting": ex.waiting, "robot_reachable": ex.robot_reachable, "blind_stops": ex.blind_stops,
                "sessions": ex.sessions.info(),
                "in_flight": None if ex.in_flight is None else ex.in_flight.command.action_id}
