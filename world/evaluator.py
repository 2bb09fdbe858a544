"""Ground truth for scoring searches: geodesic distances, STOP success, MSPL.

Distances are shortest paths of the robot's centre over the true free space
(occupancy inflated by the robot radius), 8-connected without cutting corners.
The distance to an object is the path to a cell next to the object's support
(itself, or the furniture it stands on) plus the straight line from there to
the object: a cup in the middle of a table is reached at the table's edge.
Only cells that see the support without a wall in between count as next to
it, so a cell behind a wall is never near.

MSPL's shortest length l runs from the start through one instance of every
target, each reached at its viewpoint (the nearest reachable cell to it).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ovamos.shared.grid import inflate
from ovamos.shared.gridpaths import FreeSpaceGraph
from ovamos.world.occupancy import (
    RESOLUTION,
    ROBOT_RADIUS,
    closest_point_on_box,
    distance_to_box,
    grid_for,
    rasterize,
    rasterize_walls,
)
from ovamos.world.scene import Scene, SceneObject

SUCCESS_DISTANCE = 1.0
SUPPORT_REACH_CELLS = 4  # beyond the robot radius: how far from its support an object is "reached"


@dataclass(frozen=True)
class StopResult:
    cls: str
    success: bool
    distance: float  # geodesic distance to the nearest instance of ``cls`` (inf if unreachable)


class GroundTruth:
    """Geodesic queries on one scene; per-object distance fields are cached."""

    def __init__(self, scene: Scene, resolution: float = RESOLUTION,
                 robot_radius: float = ROBOT_RADIUS) -> None:
        self.scene = scene
        self.grid = grid_for(scene, resolution)
        self.occupied = rasterize(scene, self.grid)
        self.walls = rasterize_walls(scene, self.grid)
        self.free = ~inflate(self.occupied, robot_radius, resolution)
        self.robot_radius = robot_radius
        self._graph = FreeSpaceGraph(self.free, resolution)
        self._fields: dict[int, np.ndarray] = {}

    # -- distance fields --------------------------------------------------------------------
    def object_field(self, object_id: int) -> np.ndarray:
        """Geodesic distance (m) from every cell to one object; inf where unreachable or blocked."""
        if object_id not in self._fields:
            self._fields[object_id] = self._object_field(self.scene.object(object_id))
        return self._fields[object_id]

    def _object_field(self, obj: SceneObject) -> np.ndarray:
        support = self.scene.object(obj.on) if obj.on is not None else obj
        xs, ys = self.grid.cell_centres()
        reach = self.robot_radius + SUPPORT_REACH_CELLS * self.grid.resolution
        near = self.free & (distance_to_box(support, xs, ys) <= reach)
        cx, cy = xs[near], ys[near]
        visible = self._wall_free(cx, cy, *closest_point_on_box(support, cx, cy))
        seeds = np.argwhere(near)[visible]
        return self._graph.field(seeds, distance_to_box(obj, cx[visible], cy[visible]))

    def _wall_free(self, x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray
                   ) -> np.ndarray:
        """Per segment: True when no wall cell lies on it (sampled at half-cell steps)."""
        steps = int(np.ceil(np.max(np.hypot(x1 - x0, y1 - y0), initial=0) / self.grid.resolution * 2))
        clear = np.ones(x0.shape, bool)
        for t in np.linspace(0.0, 1.0, steps + 1):
            rows, cols = self.grid.to_cell(x0 + (x1 - x0) * t, y0 + (y1 - y0) * t)
            clear &= ~self.walls[np.clip(rows, 0, self.grid.rows - 1), np.clip(cols, 0, self.grid.cols - 1)]
        return clear

    def class_field(self, cls: str) -> np.ndarray:
        """Distance to the nearest instance of a class."""
        instances = self.scene.instances(cls)
        if not instances:
            raise KeyError(f"the scene has no {cls!r}")
        return np.minimum.reduce([self.object_field(o.id) for o in instances])

    def _at(self, field: np.ndarray, x: float, y: float) -> float:
        row, col = self.grid.to_cell(x, y)
        return float(field[row, col]) if self.grid.contains(row, col) else math.inf

    # -- queries ----------------------------------------------------------------------------
    def is_free(self, x: float, y: float) -> bool:
        row, col = self.grid.to_cell(x, y)
        return self.grid.contains(row, col) and bool(self.free[row, col])

    def distance_to_class(self, cls: str, x: float, y: float) -> float:
        return self._at(self.class_field(cls), x, y)

    def stop(self, cls: str, x: float, y: float) -> StopResult:
        """Score a STOP for ``cls`` at (x, y): success when an instance is within 1 m (geodesic)."""
        d = self.distance_to_class(cls, x, y)
        return StopResult(cls, d <= SUCCESS_DISTANCE, d)

    def stoppable_classes(self, x: float, y: float) -> list[str]:
        """The classes a STOP can succeed for somewhere reachable from (x, y). An object in the
        middle of a large bed or table is more than 1 m from every free cell: an episode that
        asks for it cannot succeed (the paper's protocol, like Habitat's, only asks for objects
        with a viewpoint within the success distance)."""
        row, col = self.grid.to_cell(x, y)
        from_here = self._graph.from_cells([(row, col)])[0]
        return [c for c in self.scene.classes()
                if np.isfinite(from_here[self.class_field(c) <= SUCCESS_DISTANCE]).any()]

    def viewpoint(self, obj: SceneObject) -> tuple[float, float]:
        """The reachable cell nearest to an object: where a shortest tour visits it."""
        field = self.object_field(obj.id)
        row, col = np.unravel_index(int(np.argmin(field)), field.shape)
        return self.grid.to_world(row, col)

    def shortest_tour(self, start: tuple[float, float], classes: Sequence[str]) -> float:
        """Length of the shortest path from ``start`` visiting one instance of every class.

        Exact over class orders and instance choices (dynamic programming over
        the chosen instances' viewpoints); inf if some class is unreachable.
        """
        best = math.inf
        options = [self.scene.instances(c) for c in classes]
        for order in itertools.permutations(range(len(classes))):
            for choice in itertools.product(*(options[i] for i in order)):
                best = min(best, self._tour_length(start, choice))
        return best

    def _tour_length(self, start: tuple[float, float], objects: Iterable[SceneObject]) -> float:
        total, here = 0.0, start
        for obj in objects:
            field = self.object_field(obj.id)
            total += self._at(field, *here) - float(field.min())  # to the viewpoint
            here = self.viewpoint(obj)
        return total


def spl(success: bool, shortest: float, travelled: float) -> float:
    """Success weighted by path length: S * l / max(l, p) (1 for an optimal successful path)."""
    if not success or not math.isfinite(shortest):
        return 0.0
    return shortest / max(shortest, travelled, 1e-9)
