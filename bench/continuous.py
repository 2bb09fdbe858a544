"""A continuous search in simulated time: the robot follows paths while the camera free-runs.

The planner's continuous motion (:mod:`ovamos.services.planner.continuous`) on a wheeled base's
controller and simulated device, all on one :class:`~ovamos.shared.simtime.SimClock`: a frame
every ``1 / frame_hz`` simulated seconds from where the robot truly is, perceived and fused into
the map at once; a decision on the newest map when the command in flight completes, a path's
:class:`~ovamos.services.planner.continuous.Redecision` falls due or a turn nears its end
(:func:`~ovamos.services.planner.continuous.turn_ahead`); the new command submitted
``perception + mapping + decision`` seconds after the frame it was decided on, the robot driving
on meanwhile; a path re-sent every :data:`RESEND_S` (the executive's keep-alive). Deterministic per
episode: one thread, simulated time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ovamos.services.planner.agent import Reason, Step
from ovamos.services.planner.continuous import PathStep, booked_step, chains, path_step, turn_ahead
from ovamos.services.planner.executive import ExecutiveConfig
from ovamos.shared.messages import PlanCommand, TaskStatus
from ovamos.shared.motion import Action, Pose

if TYPE_CHECKING:
    from ovamos.bench.episode import EpisodeWorld, TaskRun

RESEND_S: float = ExecutiveConfig.model_fields["resend_s"].default
"""How often the planner re-sends the command in flight (the path's keep-alive)."""


class ContinuousNeedsWheels(ValueError):
    """Continuous motion on the kinematic robot: there are no wheels to follow a path with."""


@dataclass
class _Flight:
    command: PlanCommand
    step: Step
    pose: Pose          # odometry at the decision
    distance: float     # the true distance driven by then
    drive: PathStep | None  # a path's content and when it is decided on again


def step_kind(step: Step, drive: PathStep | None = None) -> str:
    """What a step's time is booked as, in where the search time goes: ``path`` or ``careful path``
    (continuous), ``navigate`` (a primitive towards the goal), else why the step was taken (``scan``,
    ``look``, ``idle``, ``check``, ``found``, ``wander``)."""
    if drive is not None:
        return "careful path" if drive.careful else "path"
    return step.reason.value


def search_continuously(world: EpisodeWorld, search: TaskRun) -> None:
    """Run ``search`` to its end on ``world``'s wheels in simulated time."""
    clock, wheels = world.clock, world.wheels
    if clock is None or wheels is None:
        raise ContinuousNeedsWheels("continuous motion follows paths on a wheeled base: choose one "
                                    "(--base kobuki, opencr or odrive)")
    task, agent, driver, latency = search.task, search.agent, wheels.driver, world.config.latency
    period = 1.0 / world.config.frame_hz
    thinking = latency.perception_s + latency.mapping_s + latency.decision_s
    flight: _Flight | None = None
    booked_at = clock()
    while task.state is TaskStatus.SEARCHING:
        now, state = clock(), driver.state()
        snapshot = world.observe(search, stamp=now, after_action=state.last_completed)
        world.seq += 1
        pose = world.pose()
        turning: _Flight | None = None  # a turn decided on ahead of its end (turn_ahead)
        if flight is not None:
            completed = state.last_completed >= flight.command.action_id
            ahead = None if completed or state.backing_off else turn_ahead(flight.command.action, flight.pose, pose, agent.config)
            if not completed and ahead is None and (state.backing_off or flight.drive is None or
                                                    not flight.drive.redecision.due(now, snapshot, pose,
                                                                                    task.remaining, agent.config)):
                clock.sleep(period)
                continue
            _book(world, search, flight, blocked=completed and state.last_outcome == "blocked")
            search.time_by_step[step_kind(flight.step, flight.drive)] += now - booked_at
            if ahead is not None:
                turning, pose = flight, ahead
            flight, booked_at = None, now
            if task.state is not TaskStatus.SEARCHING:
                break
        step = agent.next_step(snapshot, pose)
        if step.action is None:
            break
        drive = path_step(agent, step, snapshot, pose, now)
        clock.sleep(thinking)  # perceived, fused, decided on: the command in flight (if any) runs on
        spent = thinking
        if turning is not None and not chains(turning.command.action, step, drive):
            turned = turning.command.action_id  # sent as the turn ends
            spent += clock.run_until(lambda: driver.state().last_completed >= turned, driver.config.primitive_timeout_s,
                                     1.0 / driver.config.control_hz, f"the end of turn {turned}")
        command = world.command(drive=drive) if drive else world.command(step.action)
        if driver.submit(command) != "accepted":
            raise RuntimeError(f"the simulated base refused command {command.action_id}: {driver.state()}")
        world.keep_alive = command if drive else None
        flight = _Flight(command, step, pose, world.robot.distance, drive)
        clock.sleep(period * math.ceil(spent / period) - spent)  # to the camera's next frame
    world.keep_alive = None
    driver.submit(world.command(Action.STOP))  # the task is over: whatever runs stops


def _book(world: EpisodeWorld, search: TaskRun, flight: _Flight, blocked: bool) -> None:
    """The step of ``flight``, completed or cut short by the next decision. A STOP is judged where the
    robot came to rest; a blocked path marks the obstacle ahead of where it was blocked."""
    world.keep_alive = None
    world.blocked += blocked
    if flight.step.reason is Reason.FOUND:
        search.stop_at(world, flight.step, world.robot.pose)
    step, at = booked_step(flight.step, bool(flight.command.path), blocked, flight.pose, world.pose())
    search.agent.executed(step, world.robot.distance - flight.distance, blocked, at)
    search.booked(world, flight.step)
