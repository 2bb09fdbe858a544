"""The planner's protocol with the rest of the system, without Zenoh: tasks in, commands out.

The service feeds it what arrives (task specs, driver states, odometry, map
snapshots) and calls :meth:`Executive.poll` periodically; ``poll`` returns the
messages to publish. Keeping this apart from the adapter lets the lock-step
rules be tested message by message:

* one command in flight at a time, identified by ``action_id``; it is re-sent
  every ``resend_s`` until the driver reports it completed (a put can be lost,
  and while the driver runs it the copies are its keep-alive: a driver with
  ``command_timeout_s`` stops a primitive whose copies stop coming), and the
  driver executes an id once;
* the robot unreachable (the liveliness of every service that drives it gone:
  the link is down, or the driver died): no command goes out, the task waits
  with the reason ``robot unreachable``, and resumes by itself when the robot is
  back, from the driver's first state after it (the one from before is stale);
* lock-step, causal: after command N completes, the step is booked with an
  odometry measured after it (``Odometry.after_action >= N``) and the next
  decision waits for a map that fused a frame captured after it
  (``MapSnapshot.after_action >= N``). No clock of another host is read, so
  skew between laptop and robot cannot stall the planner or let it decide on a
  stale map;
* a command the driver is running that this planner did not send (it was
  restarted) is waited for, and new ids continue after it, so the driver
  never drops a new command as a duplicate of an old one;
* one odometry session (:data:`ovamos.shared.messages.OdomSession`): a decision only on a map of the
  driver's current session, else the task waits (naming both sessions);
  the driver's session changes on evidence only (:mod:`ovamos.shared.sessions`: a sustained stream of
  driver states of the new one while the current one is quiet, or the first state after the
  robot was unreachable), so a forged driver state is counted and ignored; when it changes
  (the driver restarted: odometry starts again at its initial pose,
  wherever the robot is) the command in flight is forgotten and the search goes on with a
  new agent (a look-around first) on the task's progress so far, since every place the old
  agent remembers is in the old frame;
* no new decision while the camera reports a fault (``CameraState.fault``: the map
  would stop growing), with the camera's reason as the task's;
* no decision before the map holds a value layer of every remaining target: a new task's
  first decision waits for perception's reading of the view in front of the robot (perception
  scores its latest frame again for new targets; one that started after that frame gets the
  next, or the lock-step simulator's re-published one). Deciding on the map of before the task
  was blind or not by a race between perception and the planner: a fleet robot whose shared
  perception came up late searched otherwise than its episode run alone (162 steps, not 208);
* nothing is sent while the driver is in fault or e-stop, or advertises primitive sizes
  (``DriverState.primitives``) other than the planner's;
* the task's progress goes out as a :class:`TaskEvent` after every step and
  again every ``event_every_s`` (the gateway may have missed one);
* every decision goes out as a :class:`DecisionTrace` (the options weighed, the goal, why);
* continuous motion (:mod:`ovamos.services.planner.continuous`): a path is decided on again while
  it is driven, and a turn's next step is decided before the turn ends, for the heading it ends
  at; a turn the same way goes at once (the driver chains it), anything else when the turn ends.

``now`` in :meth:`Executive.poll` is a monotonic clock (timers only); the
stamps of outgoing messages come from ``wall_clock`` (for people and logs).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from ovamos.services.planner.agent import AgentConfig, Reason, SearchAgent, Step
from ovamos.services.planner.continuous import PERIOD, Redecision, booked_step, chains, path_step, turn_ahead
from ovamos.services.planner.task import SearchTask, SearchTaskError
from ovamos.shared.messages import (
    FINAL,
    CameraState,
    DecisionTrace,
    DriverMode,
    DriverState,
    Goal,
    JsonMessage,
    MapSnapshot,
    Odometry,
    PlanCommand,
    TaskEvent,
    TaskSpec,
    TaskStatus,
)
from ovamos.shared.motion import Pose
from ovamos.shared.sessions import SessionFollower, SessionSwitch

log = logging.getLogger("ovamos.planner")

OLD_MAP = "map from an earlier odometry session: waiting for a new map"
"""Why the planner waits while its map is of another odometry session than the driver's (the
waiting message goes on with both sessions)."""
ROBOT_UNREACHABLE = "robot unreachable"
"""Why it waits once every driver's token is gone without a word (the link, or the driver died)."""
BLIND = ("continuous motion: the map has fused no frame since the path was decided, so the robot "
         "stops until one comes (has the camera stopped, or does it take a frame only after each "
         "command? then set lock_step = false on the camera, or start with ovamos up --motion continuous)")
"""Why a path is left to stop: a decision on a map that saw nothing new would send the robot on blind."""
DRIVER_OFF = "the robot's driver shut down"
"""Why it waits once the driver said it was going off (``DriverMode.OFF``) and its token went."""


class ExecutiveConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    agent: AgentConfig = Field(default_factory=AgentConfig)
    lock_step: bool = Field(default=True, description="decide only on a map with the newest frame")
    resend_s: float = Field(default=0.3, gt=0, description="re-send an unacknowledged command")
    event_every_s: float = Field(default=1.0, gt=0, description="re-publish the task's progress")
    session_switch: SessionSwitch = Field(
        default_factory=SessionSwitch, description="when driver states of a new odometry session "
        "are followed (the driver restarted) while the robot stays reachable")


@dataclass
class _InFlight:
    command: PlanCommand
    step: Step
    pose: Pose
    sent: float
    redecision: Redecision | None = None  # a path's (continuous motion): when it is decided on again
    blind: bool = False  # due for a new decision, no frame fused since this one: left to stop
    after: int | None = None  # decided ahead of a turn's end (turn_ahead): sent once this command completes


class Executive:
    def __init__(self, config: ExecutiveConfig | None = None,
                 wall_clock: Callable[[], float] = time.time,
                 receipt_clock: Callable[[], float] = time.monotonic) -> None:
        """``receipt_clock``: when a driver state came (the evidence of a session change)."""
        self.config = config or ExecutiveConfig()
        self._wall_clock = wall_clock
        self.task: SearchTask | None = None
        self.agent: SearchAgent | None = None
        self.driver: DriverState | None = None
        self.odom: Odometry | None = None
        self.camera: CameraState | None = None
        self.snapshot: MapSnapshot | None = None
        self.in_flight: _InFlight | None = None
        self.waiting = ""           # why no command is going out, for status and events
        self.robot_reachable = True  # False once every driver's liveliness token is gone
        self.unreachable_why = ROBOT_UNREACHABLE  # a link lost, or a driver that said it shut down
        self._next_id = 1
        self.sessions = SessionFollower(self.config.session_switch, clock=receipt_clock)  # states, odometry
        self._odom_session: str | None = None  # of the last one taken, kept while it is unreachable
        self._decided_on = -2       # snapshot seq of the last decision
        self.blind_stops = 0        # paths left to stop for want of a newer map (continuous motion)
        self._blind_task: str | None = None  # the task the last of them was logged in
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
            self.task = SearchTask.from_spec(spec)  # a restarted planner goes on from its progress
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
        except SearchTaskError:
            return
        self._event_due = self._event_due or bool(added or removed)

    def on_driver(self, state: DriverState) -> None:
        """A driver state: taken only when of the driver's session (see the module). A driver's
        word that it goes off can arrive after its liveliness token's loss (they travel apart):
        it still names why the robot is unreachable."""
        if not self.robot_reachable and state.mode is DriverMode.OFF and state.odom_session == self._odom_session:
            self.unreachable_why = DRIVER_OFF
            return
        if not self._admit("driver_state", state.odom_session, state.stamp):
            return
        self.driver = state
        newest = max(state.last_completed, state.active_action or 0)
        if newest >= self._next_id:  # ids continue after the driver's (a planner restart)
            self._next_id = newest + 1

    def _admit(self, stream: str, session: str, order: float) -> bool:
        """Whether a driver state or odometry is of the driver's session, following a new one when
        the message completes the evidence of a restart (one follower for both: what either stream
        shows of a restart counts, and a forged stream of either reaches no pose, path or event);
        others are counted and sampled in the log."""
        before = self._odom_session
        if not self.sessions.admit(stream, session, order, log):
            return False
        if before is not None and session != before:
            self._new_odom_session(session, before)
        self._odom_session = session
        return True

    def _new_odom_session(self, session: str, before: str) -> None:
        """The driver restarted its odometry: nothing decided in the old frame still holds."""
        evidence = self.sessions.switched_on
        assert evidence is not None  # a switch has just happened
        log.warning("the driver's odometry session is now %r (was %r; on %s): the command in flight "
                    "is dropped; the search goes on, with a look-around, on a map of the new session",
                    session, before, evidence.describe())
        self.in_flight = None
        if self.task is not None and self.task.state is TaskStatus.SEARCHING:
            self.agent = SearchAgent(self.task, self.config.agent)
        self._event_due = True

    def on_robot_link(self, reachable: bool) -> None:
        """Whether a service driving the robot is alive (its liveliness token is seen)."""
        if reachable != self.robot_reachable and not reachable:
            off = self.driver is not None and self.driver.mode is DriverMode.OFF
            self.unreachable_why = DRIVER_OFF if off else ROBOT_UNREACHABLE
            self.driver = None  # whatever it said before the loss may be stale when it returns
        if reachable and not self.robot_reachable:
            self.sessions.reconnected()  # a restarted driver's first state is its session
        self.robot_reachable = reachable

    def on_camera(self, state: CameraState) -> None:
        self.camera = state

    def on_odom(self, odom: Odometry) -> None:
        """Odometry: taken only when of the driver's session, as its states are."""
        if self._admit("odom", odom.odom_session, odom.seq):
            self.odom = odom

    def on_snapshot(self, snapshot: MapSnapshot) -> None:
        """Keep the newest map; one of another odometry session replaces a map that is not of the
        driver's session (a fresh map's seq starts again)."""
        kept = self.snapshot
        if kept is None or (snapshot.seq >= kept.seq if snapshot.odom_session == kept.odom_session
                            else kept.odom_session != self._odom_session):
            self.snapshot = snapshot

    # -- what the service asks -----------------------------------------------------------------
    def map_wanted(self) -> int | None:
        """The command a decision waits for the map to have seen the world after (lock-step):
        the service then asks the mapping service for a snapshot instead of waiting for its
        next periodic one. None when nothing is waited for."""
        d = self.driver
        if not self.config.lock_step or d is None or self.in_flight:
            return None
        if self.snapshot is not None and self.snapshot.has_seen_after(d.last_completed) \
                and self.snapshot.odom_session == d.odom_session:
            return None
        return d.last_completed

    def poll(self, now: float) -> list[JsonMessage]:
        """The messages to publish now (commands, task events)."""
        commands: list[JsonMessage] = []
        if self.task is not None and self.task.state is TaskStatus.SEARCHING:
            commands = self._drive(now)
        out: list[JsonMessage] = []
        if self.task is not None and (self._event_due or now - self._last_event >= self.config.event_every_s):
            # the event first: a found target must reach perception before the next frame does
            out.append(self.event())
            self._event_due, self._last_event = False, now
        return out + commands

    def event(self) -> TaskEvent:
        task = self.task
        assert task is not None
        pose, agent = self._pose(), self.agent
        searching = task.state is TaskStatus.SEARCHING and agent is not None
        return TaskEvent(task_id=task.task_id, status=task.state, targets=tuple(task.targets),
                         found=tuple(task.found.values()), steps=task.steps,
                         distance_m=task.distance, stamp=self._wall_clock(),
                         message=task.reason or self.waiting or (agent.condition if searching and agent is not None else ""),
                         misses=agent.misses() if task.state is TaskStatus.FAILED and agent is not None else (),
                         x=None if pose is None else pose.x, y=None if pose is None else pose.y,
                         goal=self._goal(), last_action=task.last_action,
                         odom_session="" if self.odom is None else self.odom.odom_session)

    def _goal(self) -> Goal | None:
        """The agent's goal while the task searches (the operator's map shows it)."""
        task, agent = self.task, self.agent
        if task is None or agent is None or agent.goal is None or task.state is not TaskStatus.SEARCHING:
            return None
        goal = agent.goal
        return Goal(kind=goal.kind.value, x=goal.x, y=goal.y, label=goal.label)

    # -- the loop ------------------------------------------------------------------------------
    def _drive(self, now: float) -> list[JsonMessage]:
        if not self.robot_reachable:
            return self._wait(self.unreachable_why)
        d = self.driver
        if d is None:
            return self._wait("no driver state yet")
        if d.mode is DriverMode.OFF:
            return self._wait(DRIVER_OFF)
        if d.mode in (DriverMode.FAULT, DriverMode.ESTOP):
            reason = "e-stop latched" if d.mode is DriverMode.ESTOP else f"driver fault: {', '.join(d.faults)}"
            return self._wait(reason)
        ours = self.config.agent.primitives
        if d.primitives is not None and not d.primitives.matches(ours):
            return self._wait(f"driver's primitives ({d.primitives}) differ from the planner's "
                              f"({ours}): fix the configs")
        if self.in_flight is not None:
            return self._follow_up(now, d)
        if d.active_action is not None:
            return self._wait(f"waiting for command {d.active_action}, sent before this planner "
                              f"started, to finish")
        return self._decide(now, d)

    def _follow_up(self, now: float, d: DriverState) -> list[JsonMessage]:
        flight = self.in_flight
        assert flight is not None and self.agent is not None
        if flight.after is not None:  # decided ahead of a turn's end: sent as it ends
            if d.last_completed < flight.after:
                return []
            flight.after, flight.sent = None, now
            return [flight.command]
        action_id = flight.command.action_id
        if d.last_completed >= action_id:
            if self.odom is None or self.odom.after_action < action_id:
                # odometry and driver state travel separately: the pose after the command must
                # be in before the step is booked (distance) and the next one decided (pose)
                return self._wait(f"waiting for odometry after command {action_id}")
            self._book(flight, d.last_outcome == "blocked")
            return self._decide(now, d) if self.task and self.task.state is TaskStatus.SEARCHING else []
        if (turning := self._turn_ahead(flight, d)) is not None:
            return self._decide(now, d, turning)
        why = self._redecision(now, flight)  # continuous: the path is decided on again while it is driven
        if why is not None:
            if self.snapshot is not None and self.snapshot.seq == self._decided_on:
                return self._blind(flight)
            if why != PERIOD:  # (once a second: the log would hold little else)
                log.info("step %d: path of command %d decided on again: %s", self.agent.task.steps,
                         flight.command.action_id, why)
            self._book(flight, blocked=False)
            return self._decide(now, d) if self.task and self.task.state is TaskStatus.SEARCHING else []
        if now - flight.sent >= self.config.resend_s:  # lost, or running: the driver's keep-alive
            flight.sent = now
            return [flight.command]
        return []

    def _book(self, flight: _InFlight, blocked: bool) -> None:
        """The step of ``flight`` done: completed, or (a path) cut short by the next decision."""
        assert self.agent is not None
        self.in_flight = None
        pose = self._pose() or flight.pose
        moved = math.hypot(pose.x - flight.pose.x, pose.y - flight.pose.y)
        step, at = booked_step(flight.step, bool(flight.command.path), blocked, flight.pose, pose)
        self.agent.executed(step, moved, blocked, at)
        self.agent.task.last_action = flight.command.action_id  # reported: a restarted planner goes on after it
        self._event_due = True

    def _redecision(self, now: float, flight: _InFlight) -> str | None:
        """Why a path in flight is due for a new decision (on a map of the driver's session), if it is."""
        snapshot, pose, agent = self.snapshot, self._pose(), self.agent
        if flight.redecision is None or snapshot is None or pose is None or agent is None or self.driver is None \
                or snapshot.odom_session != self.driver.odom_session or self.driver.backing_off:
            return None
        return flight.redecision.due(now, snapshot, pose, agent.task.remaining, agent.config)

    def _turn_ahead(self, flight: _InFlight, d: DriverState) -> Pose | None:
        """Continuous motion: where the turn in flight will end, once it is near enough to decide the
        next step ahead of it (:func:`turn_ahead`) on a map of the driver's session newer than its
        decision."""
        snapshot, pose, agent = self.snapshot, self._pose(), self.agent
        if self.config.agent.motion != "continuous" or snapshot is None or pose is None or agent is None \
                or snapshot.seq == self._decided_on or snapshot.odom_session != d.odom_session:
            return None
        return turn_ahead(flight.command.action, flight.pose, pose, agent.config)

    def _blind(self, flight: _InFlight) -> list[JsonMessage]:
        """A path due for a new decision on a map that has fused no frame since it was decided: the
        robot would drive on blind. The keep-alive stops, so the driver's deadman stops the path
        (booked when the driver reports it), and the next decision waits, as lock-step's do, for a
        frame taken after it."""
        if not flight.blind:
            flight.blind = True
            self.blind_stops += 1
            task_id = None if self.task is None else self.task.task_id
            if task_id != self._blind_task:  # once a task: a camera left lock-stepped would fill the log
                self._blind_task = task_id
                log.warning("command %d: %s", flight.command.action_id, BLIND)
        return self._wait(BLIND)

    def _decide(self, now: float, d: DriverState, ahead: Pose | None = None) -> list[JsonMessage]:
        """The next step, sent; ``ahead``: decided before the turn in flight ends, for the pose it ends
        at (booked here, once nothing else holds the decision up), and sent at once only when the base
        chains it onto the turn."""
        assert self.agent is not None
        if self.camera is not None and self.camera.fault:
            return self._wait(f"camera: {self.camera.fault}")
        snapshot, pose = self.snapshot, self._pose()
        if snapshot is None or pose is None:
            return self._wait("waiting for the map" if snapshot is None else "waiting for odometry")
        if snapshot.odom_session != d.odom_session:
            return self._wait(f"{OLD_MAP} (the map is of session {snapshot.odom_session!r}, the "
                              f"driver's is {d.odom_session!r})")
        if self.odom is not None and self.odom.odom_session != d.odom_session:
            return self._wait("waiting for odometry of the driver's odometry session")
        if self.config.lock_step:
            if not snapshot.has_seen_after(d.last_completed):
                return self._wait(f"waiting for the map to fuse a frame taken after command "
                                  f"{d.last_completed}")
            if self.odom is None or self.odom.after_action < d.last_completed:
                return self._wait(f"waiting for odometry after command {d.last_completed}")
        elif snapshot.seq == self._decided_on:
            return []
        if self.task is not None and (unseen := [t for t in self.task.remaining if t not in snapshot.layers]):
            return self._wait(f"waiting for perception: the map has no values of {', '.join(unseen)} yet")
        self.waiting = ""
        self._decided_on = snapshot.seq
        turning = self.in_flight if ahead is not None else None
        if turning is not None and ahead is not None:
            self._book(turning, blocked=False)
            pose = ahead
        decisions = self.agent.decisions
        step = self.agent.next_step(snapshot, pose)
        trace: list[JsonMessage] = ([self._trace(snapshot, pose)] if self.agent.decisions != decisions
                                    else [])
        if step.action is None:
            self._event_due = True
            return trace
        drive = path_step(self.agent, step, snapshot, pose, now) if self.config.agent.motion == "continuous" else None
        # a path is decided in the map and followed in the base's odometry frame
        command = PlanCommand(action_id=self._next_id, stamp=self._wall_clock(), task_id=self.task.task_id if self.task
                              else None, action=None if drive else step.action,
                              **(drive.in_odom(snapshot.to_odom) if drive else {}))
        self._next_id += 1
        after = (turning.command.action_id if turning is not None and not chains(turning.command.action, step, drive)
                 else None)
        self.in_flight = _InFlight(command, step, pose, now, drive.redecision if drive else None, after=after)
        if step.reason is Reason.FOUND:
            self._event_due = True
        return trace if after is not None else trace + [command]

    def _trace(self, snapshot: MapSnapshot, pose: Pose) -> DecisionTrace:
        """The agent's newest decision, as the planner's decision trace."""
        task, agent = self.task, self.agent
        assert task is not None and agent is not None
        g = agent.goal
        return DecisionTrace(task_id=task.task_id, step=task.steps, stamp=self._wall_clock(),
                             map_seq=snapshot.seq, robot_x=pose.x, robot_y=pose.y,
                             remaining=tuple(task.remaining), options=() if g is None else g.options,
                             goal=None if g is None else Goal(kind=g.kind.value, x=g.x, y=g.y, label=g.label),
                             reason="nothing left to go to" if g is None else g.reason)

    def _wait(self, reason: str) -> list[JsonMessage]:
        if reason != self.waiting:
            self.waiting = reason
            self._event_due = True
        return []

    def _pose(self) -> Pose | None:
        """The robot in the map: its odometry placed by the map's ``map_T_odom`` (localization's)."""
        o = self.odom
        if o is None:
            return None
        pose = Pose(x=o.x, y=o.y, yaw=o.yaw)
        s = self.snapshot
        return pose if s is None or s.odom_session != o.odom_session else s.to_map(pose)
