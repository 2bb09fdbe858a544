"""Continuous motion in the planner's protocol, message by message: a navigation step goes out as a
path, kept alive while the driver runs it and decided on again every ``decide_every_s`` (or at
once when a target is confirmed, or at the object the path goes to) without waiting for the robot
to stop; every other step stays a primitive; a path being backed off from a bump is waited for."""

from __future__ import annotations

import pytest

from ovamos.services.planner.agent import AgentConfig
from ovamos.services.planner.executive import Executive, ExecutiveConfig
from ovamos.shared.messages import DriverState, ObjectInstance
from ovamos.shared.motion import Action
from tests.test_planner_executive import commands, driver, odom, snapshot, spec


def scanned(every_s: float = 1.0, careful: int = 5) -> tuple[Executive, float]:
    """A continuous executive past its one-turn look-around, its first path just sent; the time."""
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=1, motion="continuous", decide_every_s=every_s,
                                                     careful_steps=careful), resend_s=0.3))
    ex.on_task(spec())
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    [turn] = commands(ex.poll(0.0))
    assert turn.action is Action.TURN_LEFT and not turn.path  # the look-around: primitives
    ex.on_driver(driver(completed=1, outcome="done"))
    ex.on_odom(odom(yaw=0.5, after=1))
    ex.on_snapshot(snapshot(1))
    [path] = commands(ex.poll(0.1))
    assert path.action is None and len(path.path) >= 1
    return ex, 0.1


def test_a_navigation_step_goes_out_as_the_navigators_path_to_the_goal() -> None:
    ex, _ = scanned()
    [command] = commands([ex.in_flight.command])  # type: ignore[union-attr]
    goal = ex.agent.goal  # type: ignore[union-attr]
    end = command.path[-1]
    assert goal is not None and abs(end[0] - goal.x) < 0.3 and abs(end[1] - goal.y) < 0.3
    assert ex.task.steps == 1  # type: ignore[union-attr]  # the turn; the path is booked when decided on again


def test_the_path_is_kept_alive_then_decided_on_again_while_the_robot_drives() -> None:
    ex, t = scanned(every_s=1.0)
    first = ex.in_flight.command  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, active=first.action_id, outcome="done"))
    resent = commands(ex.poll(t + 0.35))
    assert resent == [first]  # the keep-alive: the same id
    ex.on_odom(odom(x=1.2, yaw=0.5, after=1))
    ex.on_snapshot(snapshot(2, after=1))  # the robot still moving: no frame after a completion
    assert commands(ex.poll(t + 0.6)) == []  # not yet due (nor a keep-alive)
    [second] = commands(ex.poll(t + 1.05))
    assert second.action_id == first.action_id + 1 and second.path
    assert ex.task.steps == 2 and ex.task.distance == pytest.approx(0.2)  # type: ignore[union-attr]


def test_a_target_confirmed_on_the_way_is_decided_on_at_once() -> None:
    ex, t = scanned(every_s=10.0)
    first = ex.in_flight.command  # type: ignore[union-attr]
    ex.on_driver(driver(completed=1, active=first.action_id, outcome="done"))
    cup = ObjectInstance(label="cup", x=4.0, y=4.0, score=0.9, hits=3, views=3, confirmed=True)
    ex.on_snapshot(snapshot(2, objects=(cup,), after=1))
    [second] = commands(ex.poll(t + 0.2))
    goal = ex.agent.goal  # type: ignore[union-attr]
    assert second.action_id == first.action_id + 1 and goal is not None and goal.label == "cup"


@pytest.mark.parametrize("careful", [0, 5])
def test_a_path_backing_off_from_a_bump_is_waited_for_and_booked_blocked(careful: int) -> None:
    """Then, within ``careful_steps`` of the bump, the way on is primitives, each checked on the map
    with the bump in it."""
    ex, t = scanned(every_s=0.5, careful=careful)
    first = ex.in_flight.command  # type: ignore[union-attr]
    backing = DriverState(**{**driver(completed=1, active=first.action_id, outcome="done").model_dump(),
                             "backing_off": True})
    ex.on_driver(backing)
    ex.on_snapshot(snapshot(2, after=1))
    assert commands(ex.poll(t + 1.0)) == [first]  # due by the clock, but its outcome is coming: kept alive
    ex.on_driver(driver(completed=first.action_id, outcome="blocked"))
    ex.on_odom(odom(x=1.1, yaw=0.5, after=first.action_id))
    ex.on_snapshot(snapshot(3, after=first.action_id))
    [second] = commands(ex.poll(t + 1.1))
    assert second.action_id == first.action_id + 1
    assert ex.agent.bumps.points(ex.task.steps)  # type: ignore[union-attr]  # the bump was marked
    assert (second.action is not None and not second.path) if careful else (second.path and second.action is None)


def test_stepwise_sends_primitives_only() -> None:
    ex = Executive(ExecutiveConfig(agent=AgentConfig(initial_turns=0)))
    ex.on_task(spec())
    ex.on_driver(driver())
    ex.on_snapshot(snapshot(0))
    ex.on_odom(odom())
    [command] = commands(ex.poll(0.0))
    assert command.action is not None and not command.path
