"""The robot's body and its motion primitives, defined once for every service.

The mapping service keeps frontiers clear of obstacles by the robot's radius,
the planner plans paths for it and moves it in primitives, the base driver
(real or simulated) executes those primitives, and the simulator checks the
robot's collisions and draws it. Every one of their configs takes its default
from :data:`ROBOT` and :data:`PRIMITIVES` here, so changing a number below
changes it everywhere; a config file may still override it for one service.

Primitive sizes must match between the planner and the driver that executes
them (a planner that believes a step is 0.25 m while the base drives 0.30 m
plans on a robot it does not have): the driver advertises its sizes in
``driver/state`` (:class:`ovamos.shared.messages.DriverState`) and the planner
refuses to plan when they differ from its own.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["Primitives", "RobotGeometry", "PRIMITIVES", "ROBOT"]


class Primitives(BaseModel):
    """The sizes of the discrete commands MOVE_FORWARD and TURN_LEFT / TURN_RIGHT.

    The paper's: "MOVE_FORWARD 0.25 m, TURN_LEFT 30 deg, TURN_RIGHT 30 deg". 30 deg
    makes a look around twelve turns; 0.25 m is five cells of the 5 cm map, small
    enough to pass a 0.9 m doorway with a few heading corrections.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # on the wire in DriverState
    forward_m: float = Field(default=0.25, gt=0, description="length of MOVE_FORWARD")
    turn_deg: float = Field(default=30.0, gt=0, le=180, description="angle of TURN_LEFT/RIGHT")

    def matches(self, other: Primitives) -> bool:
        """The same sizes (to a micrometre and a microdegree: they travel as JSON floats)."""
        return (math.isclose(self.forward_m, other.forward_m, abs_tol=1e-6)
                and math.isclose(self.turn_deg, other.turn_deg, abs_tol=1e-6))

    def __str__(self) -> str:
        return f"move {self.forward_m:.2f} m, turn {self.turn_deg:g} deg"


class RobotGeometry(BaseModel):
    """The robot seen from above: a disc on two drive wheels (TurtleBot3 Waffle-like)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    radius_m: float = Field(
        default=0.18, ge=0,
        description="the robot's footprint as a disc: a TurtleBot3 Waffle is about 0.28 x 0.31 m "
                    "(0.155 m to its sides, 0.21 m to its corners). Mapping keeps frontiers this far "
                    "from obstacles, the decision step's path lengths and the simulator's collision "
                    "checks use it, pictures draw it")
    navigation_radius_m: float = Field(
        default=0.15, ge=0,
        description="what the navigator grows obstacles by. Below the footprint on purpose: mapped "
                    "obstacles are up to a cell thicker than the real ones (depth points land in "
                    "cells), which with the full radius narrows a 0.9 m doorway until no sequence "
                    "of 0.25 m / 30 deg primitives fits through; a bump is mapped if it was too "
                    "optimistic")
    wheel_radius_m: float = Field(default=0.033, gt=0, description="drive wheels (TurtleBot3 Waffle)")
    track_width_m: float = Field(default=0.287, gt=0, description="distance between the drive wheels")


PRIMITIVES = Primitives()
"""The primitive sizes every config defaults to."""

ROBOT = RobotGeometry()
"""The robot geometry every config defaults to."""
