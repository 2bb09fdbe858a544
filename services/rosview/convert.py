"""The search as ROS 2 sees it, without ROS: cell values of ``nav_msgs/OccupancyGrid`` and the
marks of the ``visualization_msgs/MarkerArray``, computed from our messages.

The grid's layout is ours as it is (:mod:`ovamos.shared.grid`: row index grows with y, column with x,
cell (0, 0) at ``origin``), which is ``OccupancyGrid``'s too. Occupancy: -1 never seen, 0 free,
100 obstacle. A value layer: -1 never seen, else the value map the planner decides on for that
target (:func:`ovamos.services.mapping.render.value_image`, decayed and normalised) as 0-100.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ovamos.services.mapping.render import value_image
from ovamos.shared.messages import DecisionTrace, MapSnapshot

__all__ = ["Mark", "occupancy", "value_cells", "marks"]

UNKNOWN, FREE, OCCUPIED = -1, 0, 100


def occupancy(snapshot: MapSnapshot) -> np.ndarray:
    """H x W int8: -1 never seen, 0 free, 100 obstacle."""
    cells = np.full(snapshot.obstacle.shape, UNKNOWN, np.int8)
    cells[snapshot.explored] = FREE
    cells[snapshot.obstacle] = OCCUPIED
    return cells


def value_cells(snapshot: MapSnapshot, layer: str) -> np.ndarray:
    """H x W int8 of one target's value layer: -1 never seen, else 0-100."""
    cells = np.rint(value_image(snapshot, layer) * 100).astype(np.int8)
    cells[~snapshot.explored] = UNKNOWN
    return cells


@dataclass(frozen=True)
class Mark:
    """One marker: what it shows, where (world metres, the odometry frame), and its label."""

    kind: Literal["frontier", "candidate", "goal", "object", "confirmed"]
    x: float
    y: float
    label: str = ""


def marks(snapshot: MapSnapshot | None, trace: DecisionTrace | None) -> list[Mark]:
    """The map's frontiers and objects (confirmed apart), the latest decision's candidates and its
    goal, in that order."""
    out: list[Mark] = []
    if snapshot is not None:
        out += [Mark("frontier", float(x), float(y)) for x, y in snapshot.frontiers]
        out += [Mark("confirmed" if o.confirmed else "object", o.x, o.y, o.label) for o in snapshot.objects]
    if trace is not None:
        out += [Mark("candidate", o.x, o.y) for o in trace.options if o.kind == "candidate"]
        if trace.goal is not None:
            out.append(Mark("goal", trace.goal.x, trace.goal.y, trace.goal.label or trace.goal.kind))
    return out
