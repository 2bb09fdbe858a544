"""True occupancy of a scene at map resolution, and where the robot's centre may be."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ovamos.shared.grid import GridGeometry
from ovamos.shared.robot import ROBOT
from ovamos.world.scene import WALL_THICKNESS, Scene, SceneObject

RESOLUTION = 0.05
ROBOT_RADIUS = ROBOT.radius_m  # the robot's footprint as a disc (ovamos.shared.robot)
MARGIN = 0.5  # the grid extends this far past the house so the outside is represented
FLOOR_OBJECT_MAX_Z = 0.05  # objects whose bottom is lower than this block the robot


def box_corners(x: float, y: float, sx: float, sy: float, yaw: float) -> np.ndarray:
    """4 x 2 corners of an oriented rectangle."""
    c, s = math.cos(yaw), math.sin(yaw)
    half = np.array([[sx, sy], [-sx, sy], [-sx, -sy], [sx, -sy]]) / 2
    return half @ np.array([[c, s], [-s, c]]) + (x, y)


def wall_corners(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    length = math.hypot(x1 - x0, y1 - y0)
    yaw = math.atan2(y1 - y0, x1 - x0)
    return box_corners((x0 + x1) / 2, (y0 + y1) / 2, length + WALL_THICKNESS, WALL_THICKNESS, yaw)


def closest_point_on_box(obj: SceneObject, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The point of an object's footprint nearest to each of the points (x, y)."""
    c, s = math.cos(obj.yaw), math.sin(obj.yaw)
    dx, dy = x - obj.x, y - obj.y
    u = np.clip(c * dx + s * dy, -obj.sx / 2, obj.sx / 2)
    v = np.clip(-s * dx + c * dy, -obj.sy / 2, obj.sy / 2)
    return obj.x + c * u - s * v, obj.y + s * u + c * v


def distance_to_box(obj: SceneObject, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Horizontal distance from points to an object's footprint (0 inside)."""
    px, py = closest_point_on_box(obj, x, y)
    return np.hypot(x - px, y - py)


def grid_for(scene: Scene, resolution: float = RESOLUTION) -> GridGeometry:
    return GridGeometry.covering(-MARGIN, -MARGIN, scene.width + MARGIN, scene.depth + MARGIN,
                                 resolution)


def _fill(mask: np.ndarray, grid: GridGeometry, corners: np.ndarray) -> None:
    cells = (corners - (grid.x0, grid.y0)) / grid.resolution - 0.5  # cv2 pixel centres
    cv2.fillPoly(mask, [np.round(cells * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)


def rasterize_walls(scene: Scene, grid: GridGeometry) -> np.ndarray:
    mask = np.zeros(grid.shape, np.uint8)
    for wall in scene.walls:
        _fill(mask, grid, wall_corners(wall.x0, wall.y0, wall.x1, wall.y1))
    return mask.astype(bool)


def rasterize(scene: Scene, grid: GridGeometry) -> np.ndarray:
    """Cells occupied by walls, floor-standing objects and everything outside the house."""
    mask = rasterize_walls(scene, grid).astype(np.uint8)
    for obj in scene.objects:
        if obj.z < FLOOR_OBJECT_MAX_Z:
            _fill(mask, grid, box_corners(obj.x, obj.y, obj.sx, obj.sy, obj.yaw))
    xs, ys = grid.cell_centres()
    outside = (xs < 0) | (xs > scene.width) | (ys < 0) | (ys > scene.depth)
    return mask.astype(bool) | outside
