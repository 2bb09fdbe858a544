"""Turns chained by the base controller (continuous motion's look-arounds), in simulated time: a
turn sent while a turn the same way runs carries on without stopping and lands a whole turn further;
anything else still supersedes the running turn."""

from __future__ import annotations

import math

from ovamos.services.sim.robot import SimRobot
from ovamos.services.sim.wheels import WheeledSimRobot
from ovamos.shared.messages import PlanCommand
from ovamos.shared.motion import Action, Pose
from ovamos.shared.simtime import SimClock
from tests.base_driver_helpers import open_space

TICK = 0.02


def _base() -> tuple[WheeledSimRobot, SimClock]:
    clock = SimClock()
    base = WheeledSimRobot(SimRobot(Pose(x=0.0, y=0.0, yaw=0.0), open_space), clock=clock).start()
    base.wait_ready()
    return base, clock


def _turned_deg(start: Pose, now: Pose) -> float:
    return math.degrees(math.remainder(now.yaw - start.yaw, 2 * math.pi))


def test_twelve_turns_sent_before_each_ends_are_one_rotation_that_lands_a_full_turn_on() -> None:
    base, clock = _base()
    try:
        start, driver = base.pose, base.driver
        turn = driver.config.turn_deg
        yaws: list[float] = []  # the heading every tick from the first command to the last one's end
        unwrapped = 0.0
        for n in range(1, 13):
            assert driver.submit(PlanCommand(action_id=n, stamp=0.0, action=Action.TURN_LEFT)) == "accepted"
            if n > 1:  # the turn before it is done: the new one carries it on
                assert (driver.state().last_completed, driver.state().last_outcome) == (n - 1, "done")
            goal = n * turn
            while unwrapped < goal - 10.0:  # sent again within 10 degrees of the running turn's end
                previous = base.pose
                clock.sleep(TICK)
                unwrapped += _turned_deg(previous, base.pose)
                yaws.append(unwrapped)
        clock.run_until(lambda: driver.state().last_completed >= 12, 10.0, TICK, "the last turn")
        assert driver.state().last_outcome == "done"
        assert abs(_turned_deg(start, base.pose)) < 1.0  # 12 x 30 degrees: where it began
        assert driver.counters["chained_turns"] == 11
        after_start = [b - a for a, b in zip(yaws, yaws[1:])][25:]  # past the first turn's ramp
        assert min(after_start) > 0.5, "the rotation slowed to a stop between turns"
    finally:
        base.stop()


def test_a_turn_the_other_way_or_a_move_still_supersedes_a_running_turn() -> None:
    base, clock = _base()
    try:
        driver = base.driver
        for n, (first, then) in enumerate(((Action.TURN_LEFT, Action.TURN_RIGHT),
                                           (Action.TURN_RIGHT, Action.MOVE_FORWARD)), 0):
            start = base.pose
            assert driver.submit(PlanCommand(action_id=2 * n + 1, stamp=0.0, action=first)) == "accepted"
            clock.run_until(lambda: abs(_turned_deg(start, base.pose)) > 10.0, 5.0, TICK, "the turn under way")
            turned = base.pose
            assert driver.submit(PlanCommand(action_id=2 * n + 2, stamp=0.0, action=then)) == "accepted"
            assert (driver.state().last_completed, driver.state().last_outcome) == (2 * n + 1, "aborted")
            clock.run_until(lambda: driver.state().last_completed >= 2 * n + 2, 10.0, TICK, "the second command")
            assert driver.counters["chained_turns"] == 0
            if then is Action.TURN_RIGHT:  # 30 degrees from where it stood, not from the first's goal
                assert abs(_turned_deg(turned, base.pose) + driver.config.turn_deg) < 1.5
    finally:
        base.stop()
