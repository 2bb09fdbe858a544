"""The planner's protocol with the rest of the system, without Zenoh: tasks in, commands out.

The service feeds it what arrives (task specs, driver states, odometry, map
snapshots) and calls :meth:`Executive.poll` periodically; ``poll`` returns the
messages to publish. Keeping this apart from the adapter lets the lock-step
rules be tested message by message:

* one command in flight at a time, identified by ``action_id``; it is re-sent
  until the driver reports it active or completed (a put can be lost), and the
  driver executes an id once;
* lock-step: after a command completes, the next decision waits for a map that
  fused the frame taken after it (``DriverState.frame_seq``; or, from a driver
  that cannot know it, a map and an odometry newer than the completion);
* nothing is sent while the driver is in fault or e-stop;
* the task's progress goes out as a :class:`TaskEvent` after every step and
  again every ``event_every_s`` (the gateway may have missed one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from services.planner.agent import AgentConfig, Reason, SearchAgent, Step
from services.planner.task import FINAL, Task, TaskError, TaskState
from shared.messages import (DriverMode, DriverState, FoundObject, JsonMessage, MapSnapshot,
                             Odometry, PlanCommand, TaskEvent, TaskSpec, TaskStatus)
from shared.motion import Pose

_STATUS = {TaskState.IDLE: TaskStatus.QUEUED, TaskState.SEARCHING: TaskStatus.SEARCHING,
           TaskState.DONE: TaskStatus.DONE, TaskState.FAILED: TaskStatus.FAILED,
           TaskState.CANCELLED: TaskStatus.CANCELLED}


class ExecutiveConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    agent: AgentConfig = Field(default_factory=AgentConfig)
    lock_step: bool = Field(default=True, description="decide only on a map with the newest frame")
    resend_s: float = Field(default=0.3, gt=0, description="re-send an unacknowledged command")
    event_every_s: float = Field(default=1.0, gt=0, description="re-publish the task's progress")


@dataclass
class _InFlight:
    command: PlanCommand
    step: Step
    pose: Pose
    sent: float


class Executive:
    def __init__(self, config: ExecutiveConfig | None = None) -> None:
        self.config = config or ExecutiveConfig()
        self.task: Task | None = None
        self.agent: SearchAgent | None = None
        self.driver: DriverState | None = None
        self.odom: Odometry | None = None
        self.snapshot: MapSnapshot | None = None
        self.in_flight: _InFlight | None = None
        self.waiting = ""           # why no command is going out, for status and events
        self._next_id = 1
        self._decided_on = -2       # snapshot seq of the last decision (free-running mode)
        self._event_due = True
        self._last_event = -math.inf

    # -- inputs --------------------------------------------------------------------------------
    def on_task(self, spec: TaskSpec) -> None:
        task = self.task
        if task is None or task.task_id != spec.task_id:
            if spec.cancelled:
                return  # a cancelled task this planner never ran: nothing to do
            if task is not None and task.state not in FINAL:
                task.cancel()  # superseded (the gateway runs one task per robot)
            self.task = Task(spec.task_id, list(spec.targets), max_steps=spec.max_steps)
            self.agent = SearchAgent(self.task, self.config.agent)
            self.in_flight = None
            self._event_due = True
            return
        if task.state in FINAL:
            return
        if spec.cancelled:
            task.cancel()
            self._event_due = True
            return
        try:
            added = [t for t in spec.targets if t not in task.targets]
            removed = [t for t in task.targets if t not in spec.targets]
            if added:
                task.add_targets(added)
            if removed:
                task.remove_targets(removed)
        except TaskError:
            return
        self._event_due = self._event_due or bool(added or removed)

    def on_driver(self, state: DriverState) -> None:
        self.driver = state
        if state.last_completed >= self._next_id:  # ids continue after a planner restart
            self._next_id = state.last_completed + 1

    def on_odom(self, odom: Odometry) -> None:
        self.odom = odom

    def on_snapshot(self, snapshot: MapSnapshot) -> None:
        if self.snapshot is None or snapshot.seq >= self.snapshot.seq:
            self.snapshot = snapshot

    # -- what the service asks -----------------------------------------------------------------
    def wanted_seq(self) -> int | None:
        """The frame seq a decision is waiting for in the map (lock-step), if any."""
        d = self.driver
        if not self.config.lock_step or d is None or d.frame_seq is None or self.in_flight:
            return None
        if self.snapshot is not None and self.snapshot.seq >= d.frame_seq:
            return None
        return d.frame_seq

    def poll(self, now: float) -> list[JsonMessage]:
        """The messages to publish now (commands, task events)."""
        commands: list[JsonMessage] = []
        if self.task is not None and self.task.state is TaskState.SEARCHING:
            commands = self._drive(now)
        out: list[JsonMessage] = []
        if self.task is not None and (self._event_due or now - self._last_event >= self.config.event_every_s):
            # the event first: a found target must reach perception before the next frame does
            out.append(self.event(now))
            self._event_due, self._last_event = False, now
        return out + commands

    def event(self, now: float) -> TaskEvent:
        task = self.task
        assert task is not None
        found = tuple(FoundObject(label=f.label, x=f.x, y=f.y, step=f.step) for f in task.found.values())
        pose = self._pose()
        return TaskEvent(task_id=task.task_id, status=_STATUS[task.state], targets=tuple(task.targets),
                         found=found, steps=task.steps, distance_m=task.distance, stamp=now,
                         message=task.reason or self.waiting,
                         x=None if pose is None else pose.x, y=None if pose is None else pose.y)

    # -- the loop ------------------------------------------------------------------------------
    def _drive(self, now: float) -> list[JsonMessage]:
        d = self.driver
        if d is None:
            return self._wait("no driver state yet")
        if d.mode in (DriverMode.FAULT, DriverMode.ESTOP):
            reason = "e-stop latched" if d.mode is DriverMode.ESTOP else f"driver fault: {', '.join(d.faults)}"
            return self._wait(reason)
        if self.in_flight is not None:
            return self._follow_up(now, d)
        return self._decide(now, d)

    def _follow_up(self, now: float, d: DriverState) -> list[JsonMessage]:
        flight = self.in_flight
        assert flight is not None and self.agent is not None
        action_id = flight.command.action_id
        if d.last_completed >= action_id:
            if self.odom is None or self.odom.stamp < d.completed_stamp:
                # odometry and driver state travel separately: the pose after the command must
                # be in before the step is booked (distance) and the next one decided (pose)
                return self._wait("waiting for odometry after the command")
            self.in_flight = None
            pose = self._pose() or flight.pose
            moved = math.hypot(pose.x - flight.pose.x, pose.y - flight.pose.y)
            self.agent.executed(flight.step, moved, d.last_outcome == "blocked", flight.pose)
            self._event_due = True
            return self._decide(now, d) if self.task and self.task.state is TaskState.SEARCHING else []
        if d.active_action != action_id and now - flight.sent >= self.config.resend_s:
            flight.sent = now
            return [flight.command]
        return []

    def _decide(self, now: float, d: DriverState) -> list[JsonMessage]:
        assert self.agent is not None
        snapshot, pose = self.snapshot, self._pose()
        if snapshot is None or pose is None:
            return self._wait("waiting for the map" if snapshot is None else "waiting for odometry")
        if self.config.lock_step:
            if d.frame_seq is not None and snapshot.seq < d.frame_seq:
                return self._wait(f"waiting for the map to fuse frame {d.frame_seq}")
            if d.frame_seq is None and (snapshot.stamp < d.completed_stamp
                                        or self.odom is None or self.odom.stamp < d.completed_stamp):
                return self._wait("waiting for a map and odometry newer than the last command")
        elif snapshot.seq == self._decided_on:
            return []
        self.waiting = ""
        self._decided_on = snapshot.seq
        step = self.agent.next_step(snapshot, pose)
        if step.action is None:
            self._event_due = True
            return []
        command = PlanCommand(action_id=self._next_id, stamp=now, task_id=self.task.task_id if self.task
                              else None, action=step.action)
        self._next_id += 1
        self.in_flight = _InFlight(command, step, pose, now)
        if step.reason is Reason.FOUND:
            self._event_due = True
        return [command]

    def _wait(self, reason: str) -> list[JsonMessage]:
        if reason != self.waiting:
            self.waiting = reason
            self._event_due = True
        return []

    def _pose(self) -> Pose | None:
        o = self.odom
        return None if o is None else Pose(x=o.x, y=o.y, yaw=o.yaw)
