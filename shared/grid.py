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


def inflate(occupied: np.ndarray, radius: float, resolution: float) -> np.ndarray:
    """Occupied cells grown by ``radius``: where a disc of that radius cannot be centred."""
    r = int(math.ceil(radius / resolution))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(occupied.astype(np.uint8), kernel).astype(bool)
