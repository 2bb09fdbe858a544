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

from pydantic import BaseModel, ConfigDict, Field

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

    @property
    def primitives(self) -> Primitives:
        return Primitives(forward_m=self.forward_m, turn_deg=self.turn_deg)


@dataclass
class SimRobot:
    """Moves a pose through free space given by ``is_free(x, y)``."""

    pose: Pose
    is_free: Callable[[float, float], bool]
    config: MotionConfig = field(default_factory=MotionConfig)
    blocked: int = 0
    distance: float = 0.0

    def apply(self, action: Action) -> bool:
        """Execute one primitive; False when a move was blocked (and not executed)."""
        p, c = self.pose, self.config
        if action is Action.MOVE_FORWARD:
            x = p.x + c.forward_m * math.cos(p.yaw)
            y = p.y + c.forward_m * math.sin(p.yaw)
            if not self._clear(p.x, p.y, x, y):
                self.blocked += 1
                return False
            self.pose = Pose(x=x, y=y, yaw=p.yaw)
            self.distance += c.forward_m
        elif action in (Action.TURN_LEFT, Action.TURN_RIGHT):
            sign = 1.0 if action is Action.TURN_LEFT else -1.0
            self.pose = Pose(x=p.x, y=p.y, yaw=wrap_angle(p.yaw + sign * math.radians(c.turn_deg)))
        return True

    def drive(self, left_rad_s: float, right_rad_s: float, dt: float) -> bool:
        """Integrate wheel angular velocities for ``dt`` seconds (exact arc); False if blocked."""
        c, p = self.config, self.pose
        v = c.wheel_radius_m * (left_rad_s + right_rad_s) / 2
        w = c.wheel_radius_m * (right_rad_s - left_rad_s) / c.track_width_m
        yaw = p.yaw + w * dt
        if abs(w) < 1e-9:
            x, y = p.x + v * dt * math.cos(p.yaw), p.y + v * dt * math.sin(p.yaw)
        else:
            x = p.x + v / w * (math.sin(yaw) - math.sin(p.yaw))
            y = p.y - v / w * (math.cos(yaw) - math.cos(p.yaw))
        if not self._clear(p.x, p.y, x, y):
            self.blocked += 1
            self.pose = Pose(x=p.x, y=p.y, yaw=wrap_angle(yaw))
            return False
        self.distance += math.hypot(x - p.x, y - p.y)
        self.pose = Pose(x=x, y=y, yaw=wrap_angle(yaw))
        return True

    def _clear(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        n = max(1, math.ceil(math.hypot(x1 - x0, y1 - y0) / self.config.collision_step_m))
        return all(self.is_free(x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n)
                   for i in range(1, n + 1))
