"""Closed-loop execution of the discrete primitives on odometry.

Each tick the tracker turns the remaining distance (or angle) into a speed
request: the top speed, capped by the braking curve ``sqrt(2 a d)`` so the
base can stop in time, by ``gain * d`` near the goal so that a late control
tick (a slow host) overshoots by millimetres, and never below a creep speed so
the goal is reached rather than approached forever. Within tolerance it asks
for zero; the driver reports the primitive done once the wheels are at rest
there, so the reported pose is final. An overshoot past the tolerance is
driven back. A forward move's goal may be another distance along its start heading (0: back to
the start, for a blocked move that backs off).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ovamos.services.base_driver.config import DriverConfig
from ovamos.shared.motion import Action, Pose, wrap_angle

BRAKING_MARGIN = 0.8  # plan braking at 80 % of the acceleration limit: the ramp lags a tick


def approach(remaining: float, top: float, accel: float, gain: float, creep: float) -> float:
    """Signed speed toward a goal ``remaining`` away (positive: ahead)."""
    d = abs(remaining)
    speed = max(creep, min(top, math.sqrt(2 * accel * BRAKING_MARGIN * d), gain * d))
    return math.copysign(speed, remaining)


@dataclass(frozen=True)
class PrimitiveTracker:
    """Drives one primitive from ``start``; :meth:`request` gives (linear, angular) or None at goal."""

    action: Action
    start: Pose
    config: DriverConfig
    distance_m: float | None = None  # MOVE_FORWARD's goal along the start heading; None: forward_m

    @property
    def goal_yaw(self) -> float:
        return wrap_angle(self.start.yaw + self.action.turn_sign * math.radians(self.config.turn_deg))

    def remaining(self, pose: Pose) -> float:
        """Metres (forward) or radians (turns) still to go; 0 for STOP."""
        if self.action is Action.MOVE_FORWARD:
            done = ((pose.x - self.start.x) * math.cos(self.start.yaw)
                    + (pose.y - self.start.y) * math.sin(self.start.yaw))
            return (self.config.forward_m if self.distance_m is None else self.distance_m) - done
        if self.action.turn_sign:
            return wrap_angle(self.goal_yaw - pose.yaw)
        return 0.0

    def request(self, pose: Pose) -> tuple[float, float] | None:
        c, r = self.config, self.remaining(pose)
        if self.action is Action.MOVE_FORWARD:
            if abs(r) <= c.linear_tolerance_m:
                return None
            heading = c.heading_gain * wrap_angle(self.start.yaw - pose.yaw)
            return approach(r, c.max_linear_m_s, c.max_linear_accel_m_s2, c.approach_gain,
                             c.creep_m_s), heading
        if self.action.turn_sign:
            if abs(r) <= c.angular_tolerance_rad:
                return None
            return 0.0, approach(r, c.max_angular_rad_s, c.max_angular_accel_rad_s2,
                                  c.approach_gain, c.creep_rad_s)
        return None  # STOP: stand still
