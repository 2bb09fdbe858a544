"""Differential-drive kinematics and wheel odometry (pure functions of the geometry).

Odometry integrates wheel travel with the exact arc (the same model as the
simulator's ``SimRobot.drive``), so a simulated run and its odometry agree up
to encoder sampling, not up to an integration scheme.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ovamos.shared.motion import Pose, wrap_angle


def toward(value: float, target: float, step: float) -> float:
    """``value`` moved toward ``target`` by at most ``step`` (a rate limiter's one step)."""
    return min(target, value + step) if target > value else max(target, value - step)


@dataclass(frozen=True)
class Geometry:
    wheel_radius_m: float
    track_width_m: float

    def wheels_rev_s(self, linear: float, angular: float) -> tuple[float, float]:
        """Body velocity (m/s, rad/s) -> (left, right) wheel speeds in rev/s."""
        half = angular * self.track_width_m / 2
        per_rev = 2 * math.pi * self.wheel_radius_m
        return (linear - half) / per_rev, (linear + half) / per_rev

    def body(self, left_rev_s: float, right_rev_s: float) -> tuple[float, float]:
        """(left, right) wheel speeds in rev/s -> body velocity (m/s, rad/s)."""
        per_rev = 2 * math.pi * self.wheel_radius_m
        vl, vr = left_rev_s * per_rev, right_rev_s * per_rev
        return (vl + vr) / 2, (vr - vl) / self.track_width_m


def integrate_arc(pose: Pose, ds_left: float, ds_right: float, track_width_m: float) -> Pose:
    """The pose after the wheels travelled ``ds_left`` / ``ds_right`` metres along one arc."""
    ds = (ds_left + ds_right) / 2
    dyaw = (ds_right - ds_left) / track_width_m
    yaw = pose.yaw + dyaw
    if abs(dyaw) < 1e-9:
        x, y = pose.x + ds * math.cos(pose.yaw), pose.y + ds * math.sin(pose.yaw)
    else:
        radius = ds / dyaw
        x = pose.x + radius * (math.sin(yaw) - math.sin(pose.yaw))
        y = pose.y - radius * (math.cos(yaw) - math.cos(pose.yaw))
    return Pose(x=x, y=y, yaw=wrap_angle(yaw))


class WheelOdometry:
    """Pose from successive wheel positions (revolutions, already in the wheel's direction)."""

    def __init__(self, geometry: Geometry, start: Pose) -> None:
        self.geometry = geometry
        self.pose = start
        self._last: tuple[float, float] | None = None

    def update(self, left_rev: float, right_rev: float) -> Pose:
        if self._last is not None:
            per_rev = 2 * math.pi * self.geometry.wheel_radius_m
            dl, dr = (left_rev - self._last[0]) * per_rev, (right_rev - self._last[1]) * per_rev
            self.pose = integrate_arc(self.pose, dl, dr, self.geometry.track_width_m)
        self._last = (left_rev, right_rev)
        return self.pose
