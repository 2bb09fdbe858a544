"""``ovamos drive ACTION``: one primitive sent to a robot's base driver, measured by its odometry.

For the first run on a real robot (docs/deploying/first-run.md), before any search: is a
0.25 m / 30 deg primitive one, on this floor, with these wheels? The tool sends the command as the
planner does (re-sent until the driver reports it done: the driver's deadman stops a command nobody
re-sends), waits for the odometry that follows it (``after_action``), and says how far odometry
has the robot gone, to hold against a tape measure. It refuses while a planner is alive for the
robot: the two would give the base commands of one id sequence each.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.messages import DriverMode, DriverState, Odometry, PlanCommand
from ovamos.shared.motion import Action, wrap_angle

__all__ = ["DriveError", "Driven", "drive"]

RESEND_S = 0.2  # under every base's deadman (0.5 s as shipped)


class DriveError(RuntimeError):
    """The command could not be sent or did not complete: the message says why."""


@dataclass(frozen=True)
class Driven:
    """One primitive as the base's odometry saw it."""

    action: Action
    outcome: str
    distance_m: float
    turned_deg: float
    seconds: float


class _Latest:
    """The newest driver state and odometry, from the bus's dispatcher thread."""

    def __init__(self) -> None:
        self.changed = threading.Condition()
        self.state: DriverState | None = None
        self.odom: Odometry | None = None

    def on_state(self, state: DriverState) -> None:
        with self.changed:
            self.state = state
            self.changed.notify_all()

    def on_odom(self, odom: Odometry) -> None:
        with self.changed:
            self.odom = odom
            self.changed.notify_all()

    def until(self, ready: Callable[[], bool], deadline: float, what: str) -> None:
        with self.changed:
            if not self.changed.wait_for(ready, max(0.0, deadline - time.monotonic())):
                raise DriveError(what)


def drive(bus: Bus, action: Action, timeout_s: float = 30.0) -> Driven:
    """Send ``action`` to ``bus``'s robot's base and wait for it to end (module docstring)."""
    robot = bus.robot_id
    if any(r.ok is not None for r in bus.session.liveliness().get(keys.alive(robot, "planner"), timeout=1.0)):
        raise DriveError(f"a planner is running for {robot}: stop it (or its task) first; this tool is for a "
                         "base alone")
    latest = _Latest()
    bus.subscribe(keys.driver_state(robot), DriverState, latest.on_state)
    bus.subscribe(keys.odom(robot), Odometry, latest.on_odom)
    commands = bus.publisher(keys.plan_command(robot), PlanCommand, block=True)
    started = time.monotonic()
    deadline = started + timeout_s
    latest.until(lambda: latest.state is not None, deadline,
                 f"no base driver answered for {robot} within {timeout_s:g} s: is its profile up (ovamos up robot)?")
    state = latest.state
    assert state is not None
    if state.mode is not DriverMode.READY:
        raise DriveError(f"the base is {state.mode.value}" + (f": {'; '.join(state.faults)}" if state.faults else "")
                         + (" (the e-stop is latched: clear it first)" if state.estop_latched else ""))
    done = state.last_completed
    latest.until(lambda: latest.odom is not None and latest.odom.after_action >= done, deadline,
                 "no odometry of the base's last command")
    before = latest.odom
    assert before is not None
    command = PlanCommand(action_id=max(done, state.active_action or 0) + 1, stamp=time.time(), action=action)
    while True:
        commands.put(command)
        with latest.changed:
            latest.changed.wait_for(lambda: latest.state is not None and latest.state.last_completed >= command.action_id,
                                    RESEND_S)
            state = latest.state
        assert state is not None
        if state.last_completed >= command.action_id:
            break
        if time.monotonic() > deadline:
            raise DriveError(f"{action.value} did not complete within {timeout_s:g} s (the base is "
                             f"{state.mode.value}{': ' + '; '.join(state.faults) if state.faults else ''})")
    latest.until(lambda: latest.odom is not None and latest.odom.after_action >= command.action_id, deadline,
                 "no odometry after the command")
    after = latest.odom
    assert after is not None
    return Driven(action, str(state.last_outcome or "?"),
                  math.hypot(after.x - before.x, after.y - before.y),
                  math.degrees(wrap_angle(after.yaw - before.yaw)), time.monotonic() - started)
