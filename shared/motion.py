"""Robot motion vocabulary shared by the planner, the drivers and the simulator.

Kept out of any one service so the planner and a base driver on another host
agree on what a command means without importing each other.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Literal, get_args

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


class Pose(BaseModel):
    """Planar pose in REP-103: yaw 0 along +x, counter-clockwise positive (radians)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    x: float
    y: float
    yaw: float = 0.0


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
