"""Shared set-up for the base driver tests: a simulated base, and waiting on the driver."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

from ovamos.services.base_driver.controller import BaseDriver
from ovamos.services.base_driver.hardware import HardwareDefaults
from ovamos.services.base_driver.kinematics import integrate_arc
from ovamos.services.sim.robot import SimRobot
from ovamos.services.sim.wheels import WheeledSimRobot
from ovamos.shared.messages import DriverMode, PlanCommand
from ovamos.shared.motion import Action, Pose
from tests.polling import wait_for

_ids = itertools.count(1)


def open_space(x: float, y: float) -> bool:
    return True


def sim_base(is_free: Callable[[float, float], bool] = open_space, **driver: object) -> WheeledSimRobot:
    """A started simulated base at the origin; stop() it."""
    from ovamos.services.base_driver.config import DriverConfig
    robot = SimRobot(Pose(x=0.0, y=0.0, yaw=0.0), is_free)
    base = WheeledSimRobot(robot, DriverConfig(**driver)).start()
    wait_for_mode(base.driver, DriverMode.READY)
    return base


def wait_for_mode(driver: BaseDriver, mode: DriverMode, timeout: float = 10.0) -> None:
    wait_for(lambda: driver.state().mode is mode, timeout, f"driver mode {mode.value}")


def command(action: Action | None = None, path: tuple[tuple[float, float], ...] = (), **velocity: float) -> PlanCommand:
    return PlanCommand(action_id=next(_ids), stamp=0.0, action=action, path=path, **velocity)


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


class FakeHardware(HardwareDefaults):
    """An ideal base behind the BaseHardware protocol, on an injected clock: the wheels follow
    the last setpoint exactly; tests set its sensors and failures directly."""

    name = "fake"

    def __init__(self, clock: Callable[[], float], track_width_m: float = 0.287,
                 wheel_radius_m: float = 0.033) -> None:
        self.clock, self.track, self.radius = clock, track_width_m, wheel_radius_m
        self.left = self.right = 0.0            # wheel positions, rad
        self.v = self.w = 0.0
        self.last = self.stamp = clock()
        self.setpoints: list[tuple[float, float]] = []
        self.opens = self.halts = 0
        self.bumpers: tuple[str, ...] = ()
        self.wheel_drops: tuple[str, ...] = ()
        self.cliffs: tuple[str, ...] = ()
        self.silent = False                     # feedback stops updating
        self.stalled = False                    # the wheels do not turn, whatever is commanded
        self.broken: str | None = None          # set_velocity and open raise this

    def _advance(self) -> None:
        now = self.clock()
        dt, self.last = now - self.last, now
        if not self.stalled:
            self.left += (self.v - self.w * self.track / 2) / self.radius * dt
            self.right += (self.v + self.w * self.track / 2) / self.radius * dt
        if not self.silent:
            self.stamp = now

    def open(self) -> None:
        from ovamos.services.base_driver.hardware import HardwareError
        self.opens += 1
        if self.broken:
            raise HardwareError(self.broken)

    def set_velocity(self, linear_m_s: float, angular_rad_s: float) -> None:
        from ovamos.services.base_driver.hardware import HardwareError
        if self.broken:
            raise HardwareError(self.broken)
        self._advance()
        self.v, self.w = linear_m_s, angular_rad_s
        self.setpoints.append((linear_m_s, angular_rad_s))

    def halt(self) -> None:
        self._advance()
        self.v = self.w = 0.0
        self.halts += 1

    def feedback(self):
        from ovamos.services.base_driver.hardware import WheelFeedback
        self._advance()
        if self.silent:  # the last message, again
            return self._last_fb
        self._last_fb = WheelFeedback(stamp=self.stamp, left_pos_rad=self.left, right_pos_rad=self.right,
                             left_vel_rad_s=(self.v - self.w * self.track / 2) / self.radius,
                             right_vel_rad_s=(self.v + self.w * self.track / 2) / self.radius,
                             bumpers=self.bumpers, wheel_drops=self.wheel_drops, cliffs=self.cliffs)
        return self._last_fb

    def counters(self) -> dict[str, int]:
        return {"fake_opens": self.opens}

    def close(self) -> None:
        pass


class FakeOdometryBase(FakeHardware):
    """An ideal base that keeps its own odometry, as a ROS 2 base publishes ``nav_msgs/Odometry``:
    its pose (from ``start``, in its own frame) and body velocity, no wheel positions; with
    ``report_velocity`` False, the pose alone."""

    name = "fake-odometry"

    def __init__(self, clock: Callable[[], float], start: Pose, report_velocity: bool = True) -> None:
        super().__init__(clock)
        self.pose, self.report_velocity = start, report_velocity

    def _advance(self) -> None:
        now = self.clock()
        dt = now - self.last
        super()._advance()
        self.pose = integrate_arc(self.pose, (self.v - self.w * self.track / 2) * dt,
                                  (self.v + self.w * self.track / 2) * dt, self.track)

    def feedback(self):
        from ovamos.services.base_driver.hardware import WheelFeedback
        self._advance()
        return WheelFeedback(stamp=self.stamp, left_pos_rad=0.0, right_pos_rad=0.0, pose=self.pose,
                             body_vel=(self.v, self.w) if self.report_velocity else None,
                             bumpers=self.bumpers)


def free_run(pose: Pose, heading: float, is_free: Callable[[float, float], bool]) -> float:
    """How far the robot's centre can go from ``pose`` along ``heading`` (by 2 cm steps, up to 20 m)."""
    d = 0.0
    while d < 20 and is_free(pose.x + (d + 0.02) * math.cos(heading), pose.y + (d + 0.02) * math.sin(heading)):
        d += 0.02
    return d


def turns_to_nearest_wall(pose: Pose, is_free: Callable[[float, float], bool]) -> tuple[int, float]:
    """How many 30-degree left turns from ``pose`` face the nearest obstacle, and how far it is then."""
    return min(((turns, free_run(pose, pose.yaw + math.radians(30 * turns), is_free)) for turns in range(12)),
               key=lambda t: t[1])

