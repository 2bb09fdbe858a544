"""The simulated robot's motion: discrete primitives and wheel-velocity integration.

Pose is (x, y, yaw) in REP-103 (yaw 0 along +x, counter-clockwise positive).
Collisions are checked against the true free space for the robot's centre; a
blocked motion leaves the robot where it was (a primitive) or where it touched
(wheel integration), and is counted, as a bumper would report it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ovamos.services.base_driver.kinematics import integrate_arc
from ovamos.services.sim.odometry import OdometryErrors, WheelSlip, odometry_errors
from ovamos.shared.motion import Action, Pose, wrap_angle
from ovamos.shared.robot import PRIMITIVES, ROBOT, Primitives


class MotionConfig(BaseModel):
    """Primitive sizes and the base's wheel geometry (defaults: :mod:`ovamos.shared.robot`)."""

    model_config = ConfigDict(extra="forbid")
    forward_m: float = Field(default=PRIMITIVES.forward_m, gt=0)
    turn_deg: float = Field(default=PRIMITIVES.turn_deg, gt=0, le=180)
    wheel_radius_m: float = Field(default=ROBOT.wheel_radius_m, gt=0)
    track_width_m: float = Field(default=ROBOT.track_width_m, gt=0)
    collision_step_m: float = Field(default=0.02, gt=0, description="spacing of collision checks")
    odometry: OdometryErrors = Field(default_factory=OdometryErrors, description="how the true motion departs "
                                     "from what the wheels report: a preset (ideal, realistic, hard) or the errors")
    odometry_seed: int = Field(default=0, description="the seed of those errors (a robot's systematic ones and "
                               "its slip): the same seed, the same drift")

    @field_validator("odometry", mode="before")
    @classmethod
    def _preset(cls, value: object) -> object:
        return odometry_errors(value) if isinstance(value, str) else value

    @property
    def primitives(self) -> Primitives:
        return Primitives(forward_m=self.forward_m, turn_deg=self.turn_deg)


@dataclass
class SimRobot:
    """Moves a pose through free space given by ``is_free(x, y)``.

    ``pose`` is where the robot truly is; :attr:`odom` where its wheels say it is. With ``ideal``
    odometry errors (the config's) the two are one; else the true motion is the slip's perturbation
    of the nominal one (:mod:`ovamos.services.sim.odometry`), and a bump knocks the robot unseen."""

    pose: Pose
    is_free: Callable[[float, float], bool]
    config: MotionConfig = field(default_factory=MotionConfig)
    slip: WheelSlip | None = None
    blocked: int = 0
    distance: float = 0.0
    _odom: Pose = field(init=False, repr=False)
    _pushing: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        self._odom = self.pose
        if self.slip is None:
            self.slip = WheelSlip.of(self.config.odometry, self.config.odometry_seed)

    @property
    def odom(self) -> Pose:
        """The pose the wheels report, integrated from the start pose with the nominal geometry."""
        return self.pose if self.slip is None else self._odom

    def apply(self, action: Action) -> bool:
        """Execute one primitive; False when a move was blocked (and not executed)."""
        p, c = self.pose, self.config
        if self.slip is not None:
            return self._apply_slipping(action)
        if action is Action.MOVE_FORWARD:
            x = p.x + c.forward_m * math.cos(p.yaw)
            y = p.y + c.forward_m * math.sin(p.yaw)
            if not self._clear(p.x, p.y, x, y):
                self.blocked += 1
                return False
            self.pose = Pose(x=x, y=y, yaw=p.yaw)
            self.distance += c.forward_m
        elif action.turn_sign:
            self.pose = Pose(x=p.x, y=p.y, yaw=wrap_angle(p.yaw + action.turn_sign * math.radians(c.turn_deg)))
        return True

    def _apply_slipping(self, action: Action) -> bool:
        """:meth:`apply` with odometry errors: the wheels turn as commanded, the robot goes where
        their true size and slip take it; a blocked move is a bump (the encoders saw it stall)."""
        c, slip = self.config, self.slip
        assert slip is not None
        if action is Action.MOVE_FORWARD:
            left = right = c.forward_m
        elif action.turn_sign:
            half = action.turn_sign * math.radians(c.turn_deg) * c.track_width_m / 2
            left, right = -half, half
        else:
            return True
        p = self.pose
        true = integrate_arc(p, *slip.wheels(left, right), slip.track(c.track_width_m))
        if not self._clear(p.x, p.y, true.x, true.y):
            if action is Action.MOVE_FORWARD:
                self.blocked += 1
                self._knock()
                return False
            true = Pose(x=p.x, y=p.y, yaw=true.yaw)  # a turn's drift into a wall: it turns in place
        self.distance += math.hypot(true.x - p.x, true.y - p.y)
        self.pose = true
        self._odom = integrate_arc(self._odom, left, right, c.track_width_m)
        return True

    def drive(self, left_rad_s: float, right_rad_s: float, dt: float, *, stall: bool = False) -> bool:
        """Integrate wheel angular velocities for ``dt`` seconds (exact arc); False if blocked.
        Blocked, the robot stays where it was: turned by the wheels, or not at all when they
        ``stall`` (a motor controller that stops them, as the simulated devices do)."""
        c, p = self.config, self.pose
        left, right = c.wheel_radius_m * left_rad_s * dt, c.wheel_radius_m * right_rad_s * dt
        if self.slip is None:
            true = self._ideal_arc(left_rad_s, right_rad_s, dt)
        else:
            true = integrate_arc(p, *self.slip.wheels(left, right), self.slip.track(c.track_width_m))
        if not self._clear(p.x, p.y, true.x, true.y):
            self.blocked += 1
            self.pose = p if stall else Pose(x=p.x, y=p.y, yaw=true.yaw)
            if not self._pushing:
                self._knock()
            self._pushing = True
            return False
        if self.slip is not None:
            self._odom = integrate_arc(self._odom, left, right, c.track_width_m)
        self._pushing = False
        self.distance += math.hypot(true.x - p.x, true.y - p.y)
        self.pose = true
        return True

    def _ideal_arc(self, left_rad_s: float, right_rad_s: float, dt: float) -> Pose:
        """The exact arc from body velocities, as every run before odometry errors computed it
        (:func:`integrate_arc` from wheel travel differs in the last bits, and would change them)."""
        c, p = self.config, self.pose
        v = c.wheel_radius_m * (left_rad_s + right_rad_s) / 2
        w = c.wheel_radius_m * (right_rad_s - left_rad_s) / c.track_width_m
        yaw = p.yaw + w * dt
        if abs(w) < 1e-9:
            return Pose(x=p.x + v * dt * math.cos(p.yaw), y=p.y + v * dt * math.sin(p.yaw), yaw=wrap_angle(yaw))
        return Pose(x=p.x + v / w * (math.sin(yaw) - math.sin(p.yaw)),
                    y=p.y - v / w * (math.cos(yaw) - math.cos(p.yaw)), yaw=wrap_angle(yaw))

    def _knock(self) -> None:
        """A bump's unseen turn and shift (where the shift lands free)."""
        if self.slip is None:
            return
        forward, left, turn = self.slip.bump()
        p = self.pose
        knocked = p.compose(Pose(x=forward, y=left, yaw=turn))
        self.pose = knocked if self._clear(p.x, p.y, knocked.x, knocked.y) else Pose(x=p.x, y=p.y, yaw=knocked.yaw)

    def _clear(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        n = max(1, math.ceil(math.hypot(x1 - x0, y1 - y0) / self.config.collision_step_m))
        return all(self.is_free(x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n)
                   for i in range(1, n + 1))

