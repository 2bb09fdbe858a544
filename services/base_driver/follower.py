"""Following a path command closed-loop on odometry: a regulated pure pursuit.

Each tick the follower finds where along the path the robot is (never going back along it),
steers toward the point ``lookahead_m`` further on with the arc through it (curvature
``2 y / L^2`` in the robot's frame), drives curves tighter than ``min_radius_m`` proportionally
slower, drives slower as the gap between its footprint and the nearest obstacle the command names
(``PlanCommand.obstacles``: the robot has no map of its own) narrows below ``slow_clearance_m``
(down to ``near_obstacle_m_s``), never faster than the command's ``speed_m_s`` (a careful path), and brakes for the last point on the same curve as a primitive's
approach. A corner (the
path turning by more than ``corner_rad`` at a waypoint) is driven to and braked for like the last
point, the lookahead not passing it, rather than cut. A heading error to the lookahead point larger
than ``rotate_in_place_rad`` (the path starts behind the robot, a corner gone round) turns the base
in place first. Within ``goal_tolerance_m`` of the last point it asks
for zero, and the controller reports the path done once the wheels are at rest.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.primitives import approach
from ovamos.shared.motion import Pose

Point = tuple[float, float]


def _closest_on_segment(a: Point, b: Point, p: Point) -> tuple[float, float]:
    """(fraction along a->b of the point nearest ``p``, its distance to ``p``)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2))
    return t, math.hypot(a[0] + t * dx - p[0], a[1] + t * dy - p[1])


@dataclass
class PathFollower:
    """Follows ``path`` (odometry frame) from wherever the robot is, slowing near ``obstacles`` (the
    same frame); :meth:`request` gives (linear, angular) or None once the last point is reached."""

    path: Sequence[Point]
    config: DriverConfig
    obstacles: Sequence[Point] = ()
    speed_m_s: float | None = None  # the command's top speed (None: the base's)
    _segment: int = field(default=0, init=False)  # the segment the robot was last nearest to
    _along: float = field(default=0.0, init=False)
    _passed: int = field(default=0, init=False)  # the last corner (waypoint index) the robot went round

    def __post_init__(self) -> None:
        if not self.path:
            raise ValueError("a path command needs at least one waypoint")
        self._top = self.config.max_linear_m_s if self.speed_m_s is None else min(self.speed_m_s,
                                                                                   self.config.max_linear_m_s)

    def _points(self, pose: Pose) -> list[Point]:
        """The robot's position then the path's waypoints (a one-point path starts at the robot)."""
        return [(pose.x, pose.y), *self.path] if len(self.path) == 1 else list(self.path)

    def _progress(self, points: list[Point], here: Point) -> None:
        """Advance to the nearest point on the path from the last one on (a few segments ahead)."""
        best = (math.inf, self._segment, self._along)
        for i in range(self._segment, min(len(points) - 1, self._segment + 8)):
            t, d = _closest_on_segment(points[i], points[i + 1], here)
            if i == self._segment:
                t = max(t, self._along)
            if d < best[0] - 1e-9:
                best = (d, i, t)
        _, self._segment, self._along = best

    def _corner(self, points: list[Point], j: int) -> bool:
        """Whether the path turns at waypoint ``j`` by more than ``corner_rad``."""
        if not 0 < j < len(points) - 1:
            return False
        (ax, ay), (bx, by), (cx, cy) = points[j - 1], points[j], points[j + 1]
        turn = math.atan2(cy - by, cx - bx) - math.atan2(by - ay, bx - ax)
        return abs(math.remainder(turn, 2 * math.pi)) > self.config.follow.corner_rad

    def _ahead(self, points: list[Point], distance: float, here: Point) -> tuple[Point, float]:
        """The point ``distance`` along the path from the robot's place on it, and how far the path's
        end, or the next corner not yet gone round, is from that place (along the path): the
        lookahead stops at a corner (pure pursuit would cut it by about a third of its lookahead,
        more than the clearance a planned path leaves) until the robot is within ``corner_pass_m``."""
        i, t = self._segment, self._along
        a, b = points[i], points[i + 1]
        start = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))
        remaining, target, left = 0.0, None, distance
        prev = start
        for j in range(i + 1, len(points)):
            step = math.hypot(points[j][0] - prev[0], points[j][1] - prev[1])
            if target is None and step >= left:
                f = left / step if step else 0.0
                target = (prev[0] + f * (points[j][0] - prev[0]), prev[1] + f * (points[j][1] - prev[1]))
            left -= step
            remaining += step
            prev = points[j]
            if j > self._passed and self._corner(points, j):
                if math.hypot(points[j][0] - here[0], points[j][1] - here[1]) > self.config.follow.corner_pass_m:
                    return (target if target is not None else points[j]), remaining
                self._passed = j
        return (target if target is not None else points[-1]), remaining

    def request(self, pose: Pose) -> tuple[float, float] | None:
        c, f = self.config, self.config.follow
        points, here = self._points(pose), (pose.x, pose.y)
        goal = points[-1]
        if math.hypot(goal[0] - here[0], goal[1] - here[1]) <= f.goal_tolerance_m:
            return None
        self._progress(points, here)
        target, remaining = self._ahead(points, f.lookahead_m, here)
        dx, dy = target[0] - pose.x, target[1] - pose.y
        cos, sin = math.cos(pose.yaw), math.sin(pose.yaw)
        x, y = cos * dx + sin * dy, -sin * dx + cos * dy  # the target in the robot's frame
        heading = math.atan2(y, x)
        if abs(heading) > f.rotate_in_place_rad:
            return 0.0, approach(heading, c.max_angular_rad_s, c.max_angular_accel_rad_s2, c.approach_gain,
                                 c.creep_rad_s)
        curvature = 2.0 * y / max(x * x + y * y, 1e-9)
        tight = f.min_radius_m * abs(curvature)  # > 1: a curve tighter than min_radius_m
        to_goal = remaining  # to the path's end or the next corner, where it slows
        speed = min(self._top / max(1.0, tight), self._near_obstacle_speed(here),
                    approach(to_goal, self._top, c.max_linear_accel_m_s2, c.approach_gain, f.min_speed_m_s))
        speed = max(f.min_speed_m_s, speed)
        return speed, speed * curvature

    def _near_obstacle_speed(self, here: Point) -> float:
        """The top speed (the command's or the base's) scaled by the gap to the nearest named obstacle over ``slow_clearance_m``, no
        slower than ``near_obstacle_m_s``."""
        f = self.config.follow
        if not self.obstacles or f.slow_clearance_m == 0:
            return self._top
        gap = min(math.hypot(ox - here[0], oy - here[1]) for ox, oy in self.obstacles) - f.footprint_m
        return max(min(f.near_obstacle_m_s, self._top), self._top * min(1.0, gap / f.slow_clearance_m))
