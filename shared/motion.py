"""Robot motion vocabulary shared by the planner, the drivers and the simulator.

Kept out of any one service so the planner and a base driver on another host
agree on what a command means without importing each other.
"""

from __future__ import annotations

import math
from enum import Enum

from pydantic import BaseModel, ConfigDict


class Action(str, Enum):
    """The paper's discrete commands (sizes live in the executor's config)."""

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
