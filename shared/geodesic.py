"""Shortest paths over a grid's free cells (8-connected, never cutting a blocked corner).

One graph, built once per map, answers many distance queries: the simulator's
ground truth (distance fields to objects) and the planner (path lengths
between the robot and every action point of a decision step).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

_NEIGHBOURS = ((0, 1), (1, 0), (1, 1), (1, -1))  # the other four are the same edges reversed


class FreeSpaceGraph:
    def __init__(self, free: np.ndarray, resolution: float) -> None:
        self.free = free
        self.shape = free.shape
        self.index = np.full(free.shape, -1, np.int64)
        self.nodes = int(free.sum())
        self.index[free] = np.arange(self.nodes)
        self._edges = self._build(resolution)

    def _build(self, res: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        free, idx = self.free, self.index
        rows, cols = free.shape
        src, dst, w = [], [], []
        for dr, dc in _NEIGHBOURS:
            r0, r1 = max(0, -dr), rows - max(0, dr)
            c0, c1 = max(0, -dc), cols - max(0, dc)
            ok = free[r0:r1, c0:c1] & free[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
            if dr and dc:  # diagonal: both orthogonal neighbours free, so no corner is cut
                ok &= free[r0 + dr:r1 + dr, c0:c1] & free[r0:r1, c0 + dc:c1 + dc]
            src.append(idx[r0:r1, c0:c1][ok])
            dst.append(idx[r0 + dr:r1 + dr, c0 + dc:c1 + dc][ok])
            w.append(np.full(int(ok.sum()), res * math.hypot(dr, dc)))
        s, d, ww = np.concatenate(src), np.concatenate(dst), np.concatenate(w)
        return np.concatenate([s, d]), np.concatenate([d, s]), np.concatenate([ww, ww])

    def _matrix(self, extra: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> csr_matrix:
        """The graph, optionally with extra (src, dst, weight) edges from one virtual node."""
        src, dst, w = self._edges
        n = self.nodes
        if extra is not None:
            src, dst, w = (np.concatenate([a, b]) for a, b in zip((src, dst, w), extra))
            n += 1
        return csr_matrix((w, (src, dst)), shape=(n, n))

    def _to_grid(self, dist: np.ndarray) -> np.ndarray:
        out = np.full(dist.shape[:-1] + self.shape, np.inf)
        out[..., self.free] = dist[..., :self.nodes]
        return out

    def field(self, seeds: np.ndarray, seed_cost: np.ndarray) -> np.ndarray:
        """Distance from every cell to the nearest seed node, each seed starting at its cost
        (a virtual source node joined to every seed by an edge of that cost)."""
        if seeds.size == 0:
            return np.full(self.shape, np.inf)
        virtual = np.full(seeds.size, self.nodes)
        graph = self._matrix((virtual, seeds, np.maximum(seed_cost, 1e-9)))  # csgraph drops zeros
        return self._to_grid(dijkstra(graph, directed=True, indices=self.nodes))

    def from_cells(self, cells: Sequence[tuple[int, int]]) -> np.ndarray:
        """S x H x W distances from each source cell; inf from a blocked or outside cell."""
        out = np.full((len(cells), *self.shape), np.inf)
        ok = [i for i, (r, c) in enumerate(cells)
              if 0 <= r < self.shape[0] and 0 <= c < self.shape[1] and self.free[r, c]]
        if ok:
            nodes = [int(self.index[cells[i]]) for i in ok]
            out[ok] = self._to_grid(np.atleast_2d(dijkstra(self._matrix(), directed=True,
                                                           indices=nodes)))
        return out
