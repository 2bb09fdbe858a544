"""Where the target may be: candidate points from the value map, the best frontier, the belief.

Paper, Sec. III-B: the decayed value map is thresholded, DBSCAN groups the
remaining cells (eps 0.1 m, min_samples 1, on cell coordinates in metres),
and each cluster's best cell is a candidate; the belief over candidates is
their values normalised to sum 1. The best frontier is the one with the
highest value within 0.5 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ovamos.shared.grid import GridGeometry


class CandidateConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    value_threshold: float = Field(default=0.05, ge=0)
    dbscan_eps_m: float = Field(default=0.1, gt=0)
    dbscan_min_samples: int = Field(default=1, ge=1)
    frontier_radius_m: float = Field(default=0.5, ge=0)
    max_candidates: int = Field(default=20, ge=1, description="keep the best ones (planning cost)")


@dataclass(frozen=True)
class Candidates:
    points: np.ndarray  # N x 2 world xy
    values: np.ndarray  # N, value of each cluster's best cell
    belief: np.ndarray  # N, sums to 1 (empty when N = 0)


def grid_clusters(rows: np.ndarray, cols: np.ndarray, eps_cells: float) -> np.ndarray:
    """DBSCAN with min_samples 1 on grid cells, exactly, in milliseconds.

    With min_samples 1 every point is a core point, so DBSCAN's clusters are the connected
    components of the graph joining cells at most eps apart. On a grid those pairs are a
    handful of fixed offsets, found by one sorted lookup per offset; sklearn's DBSCAN
    spends ~0.1 s per decision on the tens of thousands of cells a value map passes.
    """
    n = rows.size
    r = int(np.floor(eps_cells + 1e-9))
    offsets = [(dr, dc) for dr in range(0, r + 1) for dc in range(-r, r + 1)
               if (dr, dc) > (0, 0) and dr * dr + dc * dc <= eps_cells * eps_cells + 1e-9]
    width = int(cols.max()) + 2 * r + 2
    codes = (rows.astype(np.int64) + r) * width + (cols.astype(np.int64) + r)
    order = np.argsort(codes)
    sorted_codes = codes[order]
    src, dst = [np.arange(n)], [np.arange(n)]
    for dr, dc in offsets:
        wanted = codes + dr * width + dc
        at = np.minimum(np.searchsorted(sorted_codes, wanted), n - 1)
        hit = sorted_codes[at] == wanted
        src.append(np.flatnonzero(hit))
        dst.append(order[at[hit]])
    i, j = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(i.size, np.int8), (i, j)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def find_candidates(value_map: np.ndarray, grid: GridGeometry, config: CandidateConfig
                    ) -> Candidates:
    rows, cols = np.nonzero(value_map > config.value_threshold)
    if rows.size == 0:
        empty = np.zeros(0)
        return Candidates(np.zeros((0, 2)), empty, empty)
    xs, ys = grid.to_world(rows, cols)
    if config.dbscan_min_samples == 1:
        labels = grid_clusters(rows, cols, config.dbscan_eps_m / grid.resolution)
    else:
        from sklearn.cluster import DBSCAN  # not at the top: ~1 s of every planner start, for a non-default path

        labels = DBSCAN(eps=config.dbscan_eps_m, min_samples=config.dbscan_min_samples).fit_predict(
            np.stack([xs, ys], axis=1))
    values = value_map[rows, cols]
    order = np.lexsort((-values, labels))  # per cluster, best value first
    _, first = np.unique(labels[order], return_index=True)
    best = order[first]
    best = best[np.argsort(-values[best], kind="stable")][:config.max_candidates]
    points = np.stack([xs[best], ys[best]], axis=1)
    v = values[best].astype(np.float64)
    return Candidates(points, v, v / v.sum())


def frontier_scores(frontiers: np.ndarray, value_map: np.ndarray, grid: GridGeometry,
                    radius_m: float) -> np.ndarray:
    """Each frontier's highest value within ``radius_m`` (what ranks frontiers)."""
    r = int(np.ceil(radius_m / grid.resolution))
    offsets = np.array([(dr, dc) for dr in range(-r, r + 1) for dc in range(-r, r + 1)
                        if (dr * dr + dc * dc) * grid.resolution ** 2 <= radius_m ** 2 + 1e-12])
    rows, cols = grid.to_cell(frontiers[:, 0], frontiers[:, 1])
    rr = np.clip(rows[:, None] + offsets[None, :, 0], 0, grid.rows - 1)
    cc = np.clip(cols[:, None] + offsets[None, :, 1], 0, grid.cols - 1)
    return value_map[rr, cc].max(axis=1)


def best_frontier(frontiers: np.ndarray, value_map: np.ndarray, grid: GridGeometry,
                  radius_m: float) -> int | None:
    """Index of the frontier whose highest value within ``radius_m`` is the largest."""
    if len(frontiers) == 0:
        return None
    return int(np.argmax(frontier_scores(frontiers, value_map, grid, radius_m)))
