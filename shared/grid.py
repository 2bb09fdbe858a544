"""Square-cell grid geometry: the one place where world metres become cells and back.

Row index grows with y, column index with x (a top-down map drawn with row 0 at
the bottom); cell (r, c) covers ``[x0 + c*res, x0 + (c+1)*res) x [y0 + r*res, ...)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class GridGeometry:
    resolution: float
    x0: float
    y0: float
    rows: int
    cols: int

    @classmethod
    def covering(cls, x_min: float, y_min: float, x_max: float, y_max: float,
                 resolution: float) -> GridGeometry:
        cols = int(np.ceil((x_max - x_min) / resolution))
        rows = int(np.ceil((y_max - y_min) / resolution))
        return cls(resolution, x_min, y_min, rows, cols)

    @property
    def shape(self) -> tuple[int, int]:
        return self.rows, self.cols

    def to_cell(self, x: float | np.ndarray, y: float | np.ndarray) -> tuple:
        """(row, col) of the cell holding (x, y); may be outside the grid (see ``contains``)."""
        col = np.floor((np.asarray(x) - self.x0) / self.resolution).astype(np.int64)
        row = np.floor((np.asarray(y) - self.y0) / self.resolution).astype(np.int64)
        return (int(row), int(col)) if row.ndim == 0 else (row, col)

    def to_world(self, row: int | np.ndarray, col: int | np.ndarray) -> tuple:
        """Centre of a cell in world metres."""
        x = self.x0 + (np.asarray(col) + 0.5) * self.resolution
        y = self.y0 + (np.asarray(row) + 0.5) * self.resolution
        return (float(x), float(y)) if x.ndim == 0 else (x, y)

    def contains(self, row: int, col: int) -> bool:
        return 0 <= row < self.rows and 0 <= col < self.cols

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """World x and y of every cell centre, each shaped like the grid."""
        cols, rows = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return self.to_world(rows, cols)

    def band(self, points: np.ndarray, half_width: int) -> np.ndarray:
        """The cells of a line ``2 * half_width + 1`` cells thick along the polyline through
        ``points`` (K x 2 world x, y; parts off the grid clipped), as a bool mask of the grid. cv2
        draws a thick line out to its outer edge, so it reaches ``half_width + 1`` cells to either
        side of the polyline's cells."""
        rows, cols = self.to_cell(points[:, 0], points[:, 1])
        mask = np.zeros(self.shape, np.uint8)
        cv2.polylines(mask, [np.stack([cols, rows], axis=1).astype(np.int32).reshape(-1, 1, 2)], False, 1,
                      thickness=2 * half_width + 1)
        return mask.astype(bool)


def disc(radius: float, resolution: float) -> np.ndarray:
    """The cells a disc of ``radius`` covers around a centre cell, a (2r + 1)-square bool kernel
    (r = radius in cells, rounded up): the one robot footprint on the grid."""
    r = int(math.ceil(radius / resolution))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)).astype(bool)


def inflate(occupied: np.ndarray, radius: float, resolution: float) -> np.ndarray:
    """Occupied cells grown by ``radius``: where a disc of that radius cannot be centred."""
    return cv2.dilate(occupied.astype(np.uint8), disc(radius, resolution).astype(np.uint8)).astype(bool)
