"""A ROS 2 robot's own localization (AMCL, slam_toolbox) as where its odometry frame lies in its map.

Such a localizer publishes the robot's pose in its map (``geometry_msgs/PoseWithCovarianceStamped``)
seldom (AMCL: after the robot has moved far enough) and late (stamped with the scan it matched).
What the map needs is ``map_T_odom``, which holds between two poses (the drift between them is
odometry's): the pose composed with the inverse of the odometry the base reported at the pose's
stamp, read from a short history of odometry by its own stamps (one clock: the robot's).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from typing import Any

from ovamos.shared.motion import Pose, wrap_angle

__all__ = ["OdomHistory", "map_T_odom", "planar", "std_of"]


class OdomHistory:
    """The base's odometry of the last ``keep_s`` seconds, by stamp (seconds, the robot's clock)."""

    def __init__(self, keep_s: float = 2.0) -> None:
        self.keep_s = keep_s
        self._stamps: deque[float] = deque()
        self._poses: deque[Pose] = deque()

    def add(self, stamp: float, pose: Pose) -> None:
        """One odometry message; one older than the newest kept (a reordered sample) is dropped."""
        if self._stamps and stamp <= self._stamps[-1]:
            return
        self._stamps.append(stamp)
        self._poses.append(pose)
        while self._stamps[0] < stamp - self.keep_s:
            self._stamps.popleft()
            self._poses.popleft()

    def at(self, stamp: float, tolerance_s: float = 0.05) -> Pose | None:
        """The odometry at ``stamp``, interpolated between the two messages around it; ``None`` when
        the history does not reach it (older than kept, or newer than the newest by more than
        ``tolerance_s``)."""
        if not self._stamps or stamp < self._stamps[0] or stamp > self._stamps[-1] + tolerance_s:
            return None
        i = bisect.bisect_left(self._stamps, stamp)
        if i == len(self._stamps):
            return self._poses[-1]
        if self._stamps[i] == stamp or i == 0:
            return self._poses[i]
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        a, b = self._poses[i - 1], self._poses[i]
        f = (stamp - t0) / (t1 - t0)
        return Pose(x=a.x + f * (b.x - a.x), y=a.y + f * (b.y - a.y), yaw=wrap_angle(a.yaw + f * wrap_angle(b.yaw - a.yaw)))


def map_T_odom(map_pose: Pose, odom_pose: Pose) -> Pose:
    """Where the odometry frame lies in the map, given the robot's pose in both at one instant."""
    return map_pose.compose(odom_pose.inverse())


def std_of(variance: float) -> float:
    """A covariance diagonal entry as a standard deviation (a negative one, as some publishers send
    for "unknown", is infinitely uncertain)."""
    return math.sqrt(variance) if variance >= 0 else math.inf


def planar(pose: Any) -> Pose | None:
    """A ``geometry_msgs/Pose`` as a planar pose; ``None`` when not finite or its quaternion is null."""
    p, q = pose.position, pose.orientation
    if not all(math.isfinite(v) for v in (p.x, p.y, q.x, q.y, q.z, q.w)) or q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w < 1e-6:
        return None
    return Pose(x=p.x, y=p.y, yaw=math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))
