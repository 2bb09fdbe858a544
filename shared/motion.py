"""Robot motion vocabulary shared by the planner, the drivers and the simulator.

Kept out of any one service so the planner and a base driver on another host
agree on what a command means without importing each other.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict

DriveMode = Literal["stepwise", "continuous"]
"""How the planner drives the robot (``[agent] motion``): a primitive, then the frame after it
(the paper's), or paths driven while frames free-run."""
MOTIONS: tuple[str, ...] = get_args(DriveMode)


class Action(str, Enum):
    """The paper's discrete commands (sizes: :class:`ovamos.shared.robot.Primitives`)."""

    MOVE_FORWARD = "MOVE_FORWARD"
    TURN_LEFT = "TURN_LEFT"
    TURN_RIGHT = "TURN_RIGHT"
    STOP = "STOP"

    @property
    def turn_sign(self) -> float:
        """Which way it turns the heading: +1 TURN_LEFT (counter-clockwise in REP-103), -1 TURN_RIGHT,
        0 for anything else (so it also says whether the action is a turn)."""
        return 1.0 if self is Action.TURN_LEFT else -1.0 if self is Action.TURN_RIGHT else 0.0


class Pose(BaseModel):
    """Planar pose in REP-103: yaw 0 along +x, counter-clockwise positive (radians); finite, as it
    travels in messages (a map's ``map_T_odom``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    x: float
    y: float
    yaw: float = 0.0

    def compose(self, other: Pose) -> Pose:
        """``self`` * ``other``: ``other`` (a pose in the frame ``self`` places) in ``self``'s parent
        frame; map_T_odom.compose(odom pose) is the pose in the map."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose(x=self.x + c * other.x - s * other.y, y=self.y + s * other.x + c * other.y,
                    yaw=wrap_angle(self.yaw + other.yaw))

    def inverse(self) -> Pose:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose(x=-c * self.x - s * self.y, y=s * self.x - c * self.y, yaw=wrap_angle(-self.yaw))

    def apply(self, x: float, y: float) -> tuple[float, float]:
        """The point (``x``, ``y``) of the frame this pose places, in the parent frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return self.x + c * x - s * y, self.y + s * x + c * y

    def apply_points(self, points: np.ndarray) -> np.ndarray:
        """:meth:`apply` for N x 2 points at once (their dtype kept)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.stack([c * points[:, 0] - s * points[:, 1] + self.x,
                         s * points[:, 0] + c * points[:, 1] + self.y], axis=1).astype(points.dtype, copy=False)

    @property
    def identity(self) -> bool:
        return self.x == 0.0 and self.y == 0.0 and self.yaw == 0.0


IDENTITY = Pose(x=0.0, y=0.0, yaw=0.0)
"""The transform that changes nothing (map_T_odom before any correction)."""


def to_odom(map_T_odom: Pose, points: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
    """Map-frame points (a path, its obstacles) in the odometry frame, where the base follows them."""
    if map_T_odom.identity:
        return points
    odom_T_map = map_T_odom.inverse()
    return tuple(odom_T_map.apply(x, y) for x, y in points)


def wrap_angle(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class ActionIds:
    """A base's side of the command contract: action ids grow within a session and each is
    executed at most once. The planner re-sends a command until the base reports it active
    or completed (a put can be lost), so a copy of an id already taken is a duplicate."""

    def __init__(self) -> None:
        self.highest = 0

    def take(self, action_id: int) -> bool:
        """True for a new id (now taken); False for a duplicate (an id not above the highest)."""
        if action_id <= self.highest:
            return False
        self.highest = action_id
        return True
