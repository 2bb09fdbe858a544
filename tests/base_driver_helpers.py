"""Shared set-up for the base driver tests: a simulated base, and waiting on the driver."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

from services.base_driver.controller import BaseDriver
from services.sim.robot import SimRobot
from services.sim.wheels import WheeledSimRobot
from shared.messages import DriverMode, PlanCommand
from shared.motion import Action, Pose
from tests.polling import wait_for

_ids = itertools.count(1)


def open_space(x: float, y: float) -> bool:
    return True


def sim_base(is_free: Callable[[float, float], bool] = open_space, **driver: object) -> WheeledSimRobot:
    """A started simulated base at the origin; stop() it."""
    from services.base_driver.config import DriverConfig
    robot = SimRobot(Pose(x=0.0, y=0.0, yaw=0.0), is_free)
    base = WheeledSimRobot(robot, DriverConfig(**driver)).start()  # type: ignore[arg-type]
    wait_for_mode(base.driver, DriverMode.READY)
    return base


def wait_for_mode(driver: BaseDriver, mode: DriverMode, timeout: float = 10.0) -> None:
    wait_for(lambda: driver.state().mode is mode, timeout, f"driver mode {mode.value}")


def command(action: Action | None = None, **velocity: float) -> PlanCommand:
    return PlanCommand(action_id=next(_ids), stamp=0.0, action=action, **velocity)


def run(driver: BaseDriver, cmd: PlanCommand, timeout: float = 15.0) -> str:
    """Submit ``cmd`` and wait until it completes; its outcome."""
    assert driver.submit(cmd) == "accepted"
    wait_for(lambda: driver.state().last_completed >= cmd.action_id, timeout, f"command {cmd.action_id}")
    state = driver.state()
    assert state.last_completed == cmd.action_id
    return str(state.last_outcome)


def wheels_at_rest(driver: BaseDriver, eps: float = 1e-3) -> bool:
    return all(abs(v) < eps for v in driver.wheel_speeds())


def heading_deg(a: Pose, b: Pose) -> float:
    return math.degrees(math.remainder(b.yaw - a.yaw, 2 * math.pi))
