"""Hand-made map snapshots for the planner's tests: a 10 x 10 m explored room with value blobs."""

from __future__ import annotations

import numpy as np

from ovamos.shared.messages import MapSnapshot

N = 200  # 10 x 10 m at 5 cm


def snapshot(values: dict[tuple[float, float], float], frontiers: list[tuple[float, float]],
             obstacles: list[tuple[slice, slice]] = (), objects=()) -> MapSnapshot:
    layer = np.zeros((N, N), np.float32)
    for (x, y), v in values.items():
        r, c = int(y / 0.05), int(x / 0.05)
        layer[r - 2:r + 3, c - 2:c + 3] = v
    obstacle = np.zeros((N, N), bool)
    for rows, cols in obstacles:
        obstacle[rows, cols] = True
    return MapSnapshot(seq=0, stamp=0.0, resolution=0.05, origin=(0.0, 0.0), layers=("cup",),
                       objects=tuple(objects), obstacle=obstacle, explored=np.ones((N, N), bool),
                       counts=np.zeros((1, N, N), np.uint16), values=layer[None],
                       frontiers=np.array(frontiers, float).reshape(-1, 2))
