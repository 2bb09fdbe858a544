"""Localization in the map: each frame's obstacle points matched against the map built so far.

Wheel odometry drifts, and a map fused at odometry poses doubles its walls. So the map lives in a
``map`` frame and the localizer keeps ``map_T_odom``: a frame arrives posed by odometry, is placed
in the map by the current ``map_T_odom``, and its 2D scan (the depth points in the obstacle band,
which the map marks anyway) is matched against the map's obstacles; the match corrects
``map_T_odom`` and the frame is fused where it was taken.

The matcher is a scan-to-map Gauss-Newton over (x, y, yaw) about the camera, with odometry's
word in the cost (a prior whose spread grows with the ground and turns covered since the last
accepted match). Two passes: on the distance transform of the obstacle grid in a window round the
scan (a basin as wide as odometry may have drifted), then point-to-plane against where the map's
points fell in each obstacle cell (:class:`ObstaclePoints`), with the wall's normal from the grid's
structure tensor. A match is refused, and odometry kept, when it cannot be trusted: too few points
(no depth, a wall closer than the camera's minimum range), too few of them on mapped obstacles (a
new room), or a scan that constrains the pose in one direction only (a blank wall, a featureless
corridor): the smallest eigenvalue of its normal equations, per point, says so. An accepted
correction moves the map by at most ``max_step_m`` / ``max_step_deg`` a frame, so one bad match
cannot throw the map away. Why this and not Open3D's ICP or KISS-ICP: docs/method.md (#localization).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ovamos.shared.grid import GridGeometry
from ovamos.shared.motion import IDENTITY, Pose, wrap_angle

__all__ = ["LocalizationConfig", "Localizer", "Match", "ObstaclePoints", "mark_obstacles"]

Verdict = Literal["matched", "no_map", "few_points", "few_inliers", "degenerate"]


class LocalizationConfig(BaseModel):
    """When a scan-to-map match is made and trusted."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(default=False, description="match each frame against the map (off: the map is "
                          "built at odometry poses, as before localization existed)")
    source: Literal["scan", "base"] = Field(default="scan", description="where corrections come from: 'scan', "
                                           "each frame's depth matched against the map (below); 'base', the "
                                           "robot's own localization passed on with its odometry (AMCL or "
                                           "slam_toolbox on a ros2 base: [driver.ros2] localization)")
    max_points: int = Field(default=600, ge=10, description="the scan is thinned to this many points")
    min_points: int = Field(default=60, ge=3, description="fewer scan points: refused (no depth, a wall "
                            "closer than the camera's range)")
    min_map_cells: int = Field(default=40, ge=1, description="fewer mapped obstacle cells: nothing to match")
    coarse_m: float = Field(default=0.3, gt=0, description="first pass: points this far from a mapped "
                            "obstacle still pull (the basin of the match)")
    fine_m: float = Field(default=0.1, gt=0, description="second pass and inliers: points within this "
                          "of a mapped obstacle")
    iterations: int = Field(default=8, ge=1, description="Gauss-Newton iterations per pass")
    yaw_starts_deg: tuple[float, ...] = Field(default=(4.0, 8.0), description="the first pass starts from "
                                              "odometry's heading or one turned this many degrees either way, "
                                              "whichever scan lies nearer the map's walls (a bump turns the "
                                              "robot by degrees odometry never sees; empty: odometry's only)")
    min_inlier_ratio: float = Field(default=0.4, ge=0, le=1, description="fewer scan points on mapped "
                                    "obstacles after the match: refused (a place not mapped yet)")
    min_constraint: float = Field(default=0.02, ge=0, description="the smallest eigenvalue of the match's "
                                  "normal equations per inlier (rotation over a 1 m lever): below it, "
                                  "the scan fixes the pose in one direction only (a blank wall)")
    max_step_m: float = Field(default=0.10, gt=0, description="an accepted correction moves the map by "
                              "at most this a frame")
    max_step_deg: float = Field(default=5.0, gt=0)
    scan_sigma_m: float = Field(default=0.02, gt=0, description="how far a scan point may lie from where the "
                                "map has its wall (a cell's rasterization, depth noise)")
    scan_independent_points: int = Field(default=20, ge=1, description="how many of a scan's points count as "
                                         "independent evidence (the rest sample the same walls)")
    odometry_sigma_m: float = Field(default=0.01, gt=0, description="odometry's error since the last accepted "
                                    "match, at the least; grows by odometry_sigma_per_m of the ground covered")
    odometry_sigma_per_m: float = Field(default=0.05, ge=0)
    odometry_sigma_deg: float = Field(default=1.0, gt=0, description="its heading error at the least; grows by "
                                      "odometry_sigma_deg_per_turn_deg of the turns and _per_m of the ground")
    odometry_sigma_deg_per_turn_deg: float = Field(default=0.03, ge=0)
    odometry_sigma_deg_per_m: float = Field(default=4.0, ge=0)


class ObstaclePoints:
    """Where the points that made each obstacle cell fell in it: the map marks whole cells, and
    a wall whose face lies on a cell's edge would otherwise pull every scan half a cell to the
    cells' middles. Kept beside the obstacle grid while the map localizes (a checkpoint does not
    keep it: a resumed map matches against cell centres until its cells are seen again)."""

    def __init__(self, grid: GridGeometry) -> None:
        self.grid = grid
        self.offsets = np.zeros((*grid.shape, 2), np.float32)  # sums of offsets from the cells' corners
        self.hits = np.zeros(grid.shape, np.uint32)

    def add(self, points: np.ndarray, rows: np.ndarray, cols: np.ndarray, limit: int = 4000) -> None:
        """``points`` (N x 2 world xy) that fell in the cells (``rows``, ``cols``), all on the grid;
        an even sample of ``limit`` of them (a frame has tens of thousands: a mean needs fewer)."""
        if len(points) > limit:
            pick = np.linspace(0, len(points) - 1, limit).astype(np.int64)
            points, rows, cols = points[pick], rows[pick], cols[pick]
        g = self.grid
        offsets = points - np.stack([g.x0 + cols * g.resolution, g.y0 + rows * g.resolution], axis=1)
        cells, which = np.unique(rows * g.cols + cols, return_inverse=True)
        sums = np.stack([np.bincount(which, offsets[:, k], len(cells)) for k in (0, 1)], axis=1)
        self.offsets.reshape(-1, 2)[cells] += sums.astype(np.float32)
        self.hits.reshape(-1)[cells] += np.bincount(which, minlength=len(cells)).astype(np.uint32)

    def centres(self, window: tuple[slice, slice], occupied: np.ndarray) -> np.ndarray:
        """World xy (N x 2, raster order) of the mean point of each ``occupied`` cell of ``window``
        (its middle where none fell)."""
        g = self.grid
        rows, cols = np.nonzero(occupied)
        rows, cols = rows + window[0].start, cols + window[1].start
        hits = self.hits[rows, cols]
        mean = np.where(hits[:, None] > 0, self.offsets[rows, cols] / np.maximum(hits, 1)[:, None],
                        g.resolution / 2)
        return np.stack([mean[:, 0] + (g.x0 + cols * g.resolution), mean[:, 1] + (g.y0 + rows * g.resolution)],
                        axis=1)


def mark_obstacles(points: np.ndarray, grid: GridGeometry, obstacle: np.ndarray,
                   cells: ObstaclePoints | None) -> None:
    """``points`` (N x 2 world xy) marked in ``obstacle`` (on ``grid``) and, where the map keeps
    them, in ``cells``; points off the grid are dropped."""
    rows, cols = grid.to_cell(points[:, 0], points[:, 1])
    inside = (rows >= 0) & (rows < grid.rows) & (cols >= 0) & (cols < grid.cols)
    obstacle[rows[inside], cols[inside]] = True
    if cells is not None:
        cells.add(points[inside], rows[inside], cols[inside])


@dataclass(frozen=True)
class Match:
    """One frame's match: what it found and whether it was applied."""

    verdict: Verdict
    correction: Pose = IDENTITY  # applied in the map frame: corrected = correction * predicted
    points: int = 0
    inlier_ratio: float = 0.0
    constraint: float = 0.0  # smallest eigenvalue per inlier (see LocalizationConfig.min_constraint)
    clamped: bool = False

    @property
    def accepted(self) -> bool:
        return self.verdict == "matched"


class Localizer:
    """``map_T_odom`` and the matches that moved it; one per map (a new odometry session or a new
    map starts a new one)."""

    def __init__(self, config: LocalizationConfig | None = None) -> None:
        self.config = config or LocalizationConfig()
        self.map_T_odom = IDENTITY
        self.counters: Counter[str] = Counter()
        self.last: Match | None = None
        self._odom: Pose | None = None  # the odometry of the last frame matched
        self._moved_m = self._turned_rad = 0.0  # odometry's motion since the last accepted match
        self.base: Pose | None = None  # source 'base': the newest map_T_odom the base's odometry carried
        self._anchor: Pose | None = None  # the base's map placed in this one

    def follow(self, odom: Pose) -> None:
        """Source 'base': move ``map_T_odom`` toward the base's own (:attr:`base`), by at most the
        per-frame bound at ``odom`` (where odometry has the camera). The base's map is placed in this
        one where its first pose finds this map's ``map_T_odom`` (identity for a new map, the
        checkpoint's for a resumed one), so the map is not thrown to wherever the base's map has
        its origin. Counted: ``base``, ``clamped``, ``no_base_pose``."""
        if self.base is None:
            self.counters["no_base_pose"] += 1
            return
        if self._anchor is None:
            self._anchor = self.map_T_odom.compose(self.base.inverse())
        c = self.config
        now, wanted = self.map_T_odom.compose(odom), self._anchor.compose(self.base).compose(odom)
        step = np.array([wanted.x - now.x, wanted.y - now.y, wrap_angle(wanted.yaw - now.yaw)])
        step, clamped = _bounded(step, c.max_step_m, math.radians(c.max_step_deg))
        self.map_T_odom = _as_pose(step, np.array([now.x, now.y])).compose(self.map_T_odom)
        self.counters["base"] += 1
        self.counters["clamped"] += clamped

    def match(self, points: np.ndarray, camera: tuple[float, float], obstacle: np.ndarray,
              explored: np.ndarray, cells: ObstaclePoints, odom: Pose) -> Match:
        """Match ``points`` (N x 2 map xy of the scan, placed by the current ``map_T_odom``) seen
        from ``camera`` against ``obstacle`` (the map's grid, before this frame is fused; only the
        points by ``explored`` floor count, the rest were never seen from where they could be
        compared; ``cells``: where in its obstacle cells the map's points fell), and on
        success move ``map_T_odom`` by the correction (bounded). ``odom``: where odometry has the
        camera, which says how far odometry has gone since the last accepted match (how much it
        may have drifted). Counted by verdict."""
        if self._odom is not None:
            self._moved_m += math.hypot(odom.x - self._odom.x, odom.y - self._odom.y)
            self._turned_rad += abs(wrap_angle(odom.yaw - self._odom.yaw))
        self._odom = odom
        m = self._match(points, camera, obstacle, explored, cells)
        if m.accepted:
            self.map_T_odom = m.correction.compose(self.map_T_odom)
            self.counters["clamped"] += m.clamped
            self._moved_m = self._turned_rad = 0.0
        self.counters[m.verdict] += 1
        self.last = m
        return m

    def _match(self, points: np.ndarray, camera: tuple[float, float], obstacle: np.ndarray,
               explored: np.ndarray, cells: ObstaclePoints) -> Match:
        c, grid = self.config, cells.grid
        scan = _thin(points, grid.resolution / 2, c.max_points)
        if len(scan) < c.min_points:
            return Match("few_points", points=len(scan))
        window = _window(scan, c.coarse_m + 2 * grid.resolution, grid)
        if window is None or np.count_nonzero(obstacle[window]) < c.min_map_cells:
            return Match("no_map", points=len(scan))
        fields = _Fields(obstacle, window, grid, c.coarse_m, cells)
        total = len(scan)
        # a wall seen for the first time, beside a mapped one, would pull the scan along that one
        scan = scan[fields.seen(scan, explored[window])]
        if len(scan) < c.min_points:
            return Match("few_inliers", points=total, inlier_ratio=len(scan) / total)
        centre = np.asarray(camera, dtype=np.float64)
        prior = self._prior()
        # the first pass reaches as far as odometry may have drifted, no farther: points beyond
        # what it can explain (a wall seen for the first time beside a mapped one) must not pull
        reach = float(np.clip(3 / math.sqrt(prior[0]), c.fine_m, c.coarse_m))
        # (tx, ty, theta): p' = R(theta) (p - centre) + centre + t
        delta = _start(fields, scan, centre, reach, prior, c)
        for fine, cap in ((False, reach), (True, c.fine_m)):
            use = fields.value(_moved(scan, centre, delta), False) < cap
            if np.count_nonzero(use) < c.min_points:
                return Match("few_inliers", points=len(scan), inlier_ratio=float(np.mean(use)))
            weight = c.scan_independent_points / (np.count_nonzero(use) * c.scan_sigma_m ** 2)
            delta = _descend(fields, scan[use], centre, delta, fine, c.iterations, weight, prior)
        moved = _moved(scan, centre, delta)
        near = fields.value(moved, False) < c.fine_m
        ratio = float(np.mean(near))
        normals = _normal_equations(fields.normals(moved[near]), moved[near] - centre - delta[:2])
        constraint = float(np.linalg.eigvalsh(normals)[0])
        if ratio < c.min_inlier_ratio:
            return Match("few_inliers", points=len(scan), inlier_ratio=ratio, constraint=constraint)
        if constraint < c.min_constraint:
            return Match("degenerate", points=len(scan), inlier_ratio=ratio, constraint=constraint)
        delta, clamped = _bounded(delta, c.max_step_m, math.radians(c.max_step_deg))
        return Match("matched", _as_pose(delta, centre), len(scan), ratio, constraint, clamped)

    def _prior(self) -> np.ndarray:
        """Odometry's word as the information (1 / variance) of (tx, ty, theta) about its pose:
        how far it may have drifted since the last accepted match."""
        c = self.config
        sigma_m = c.odometry_sigma_m + c.odometry_sigma_per_m * self._moved_m
        sigma_rad = math.radians(c.odometry_sigma_deg + c.odometry_sigma_deg_per_turn_deg * math.degrees(
            self._turned_rad) + c.odometry_sigma_deg_per_m * self._moved_m)
        return np.array([sigma_m ** -2, sigma_m ** -2, sigma_rad ** -2])


def _start(fields: _Fields, scan: np.ndarray, centre: np.ndarray, reach: float, prior: np.ndarray,
           config: LocalizationConfig) -> np.ndarray:
    """Where the first pass starts: odometry's pose, or turned by one of ``yaw_starts_deg`` either
    way, whichever costs least (distances capped at ``reach``, odometry's word included). From
    odometry's heading alone, a scan a bump turned by 5 degrees slides into the nearest wrong
    alignment of parallel walls and stays there."""
    weight = config.scan_independent_points / (len(scan) * config.scan_sigma_m ** 2)
    yaws = [0.0, *(sign * math.radians(a) for a in config.yaw_starts_deg for sign in (-1.0, 1.0))]
    return min((np.array([0.0, 0.0, yaw]) for yaw in yaws),
               key=lambda d: _cost(fields, scan, centre, d, False, weight, prior, reach))


def _cost(fields: _Fields, points: np.ndarray, centre: np.ndarray, delta: np.ndarray, fine: bool,
          weight: float, prior: np.ndarray, cap: float = math.inf) -> float:
    """``weight`` * (the moved points' distances to the walls, each at most ``cap``)^2 + odometry's
    word against moving at all."""
    value = fields.value(_moved(points, centre, delta), fine)
    if cap < math.inf:
        value = np.minimum(value, cap)
    return float(weight * (value @ value) + delta @ (prior * delta))


def _descend(fields: _Fields, points: np.ndarray, centre: np.ndarray, delta: np.ndarray, fine: bool,
             iterations: int, weight: float, prior: np.ndarray) -> np.ndarray:
    """Gauss-Newton on ``weight`` * (the points' distances to the walls)^2 + delta' diag(prior) delta
    (odometry's word against moving at all), each step halved until the cost falls (the field is
    bilinear between cells, so a full step can overshoot); stops when no step helps."""
    def cost(d: np.ndarray) -> float:
        return _cost(fields, points, centre, d, fine, weight, prior)

    current = cost(delta)
    for _ in range(iterations):
        moved = _moved(points, centre, delta)
        value, grad = fields.sample(moved, fine)
        jac = _jacobian(grad, moved - centre - delta[:2])
        step = np.linalg.solve(weight * (jac.T @ jac) + np.diag(prior), -(weight * (jac.T @ value) + prior * delta))
        for scale in (1.0, 0.5, 0.25, 0.125):
            trial = delta + scale * step
            trial_cost = cost(trial)
            if trial_cost < current:
                delta, current = trial, trial_cost
                break
        else:
            return delta
        if scale * (math.hypot(step[0], step[1]) + abs(step[2])) < 1e-4:
            return delta
    return delta


class _Fields:
    """What a scan is matched against, over a window of the map. Coarse: the distance to the
    nearest mapped obstacle cell (metres, truncated at ``far``), sampled bilinearly with its
    gradient (a wide basin; also the inlier test). Fine: each point's distance along the wall's
    normal to the mean point of its nearest obstacle cell (point-to-plane, as ICP's; the normal
    from the structure tensor of the obstacle grid), so the match is not held to cell middles."""

    def __init__(self, obstacle: np.ndarray, window: tuple[slice, slice], grid: GridGeometry,
                 far: float, cells: ObstaclePoints) -> None:
        rows, cols = window
        occupied = obstacle[rows, cols]
        free = (~occupied).astype(np.uint8)
        dist, labels = cv2.distanceTransformWithLabels(free, cv2.DIST_L2, cv2.DIST_MASK_5,
                                                       labelType=cv2.DIST_LABEL_PIXEL)
        self.coarse = np.minimum(dist.astype(np.float64) * grid.resolution, far)
        self.gradient = np.gradient(self.coarse, grid.resolution)
        # labels number the obstacle cells in raster order: the nearest one's mean point and normal
        self.labels = labels
        blurred = cv2.GaussianBlur(occupied.astype(np.float64), (0, 0), 1.0)
        gy, gx = np.gradient(blurred)
        tensor = [cv2.GaussianBlur(g, (0, 0), 1.5)[occupied] for g in (gx * gx, gx * gy, gy * gy)]
        self.targets = np.vstack([np.zeros((1, 2)), cells.centres(window, occupied)])  # label 0: none
        self.wall_normals = np.vstack([np.zeros((1, 2)), _principal_axis(*tensor)])
        self.x0 = grid.x0 + (cols.start + 0.5) * grid.resolution  # the first cell's centre
        self.y0 = grid.y0 + (rows.start + 0.5) * grid.resolution
        self.resolution = grid.resolution

    def sample(self, points: np.ndarray, fine: bool) -> tuple[np.ndarray, np.ndarray]:
        """The residual (N) and its gradient (N x 2, d/dx, d/dy) at ``points``: the coarse field,
        or the fine point-to-plane distance; points off the window read as far, with no gradient."""
        if fine:
            return self._to_walls(points)
        value, grad = self._coarse(points, True)
        assert grad is not None
        return value, grad

    def value(self, points: np.ndarray, fine: bool) -> np.ndarray:
        """:meth:`sample`'s residual alone (a cost, an inlier test: no gradient to interpolate)."""
        return self._to_walls(points)[0] if fine else self._coarse(points, False)[0]

    def _coarse(self, points: np.ndarray, gradient: bool) -> tuple[np.ndarray, np.ndarray | None]:
        field = self.coarse
        h, w = field.shape
        fx = (points[:, 0] - self.x0) / self.resolution
        fy = (points[:, 1] - self.y0) / self.resolution
        inside = (fx >= 0) & (fx <= w - 1) & (fy >= 0) & (fy <= h - 1)
        fx, fy = np.clip(fx, 0, w - 1.000001), np.clip(fy, 0, h - 1.000001)
        c0, r0 = fx.astype(np.int64), fy.astype(np.int64)
        ax, ay = fx - c0, fy - r0

        def bilinear(grid: np.ndarray) -> np.ndarray:
            top = grid[r0, c0] * (1 - ax) + grid[r0, c0 + 1] * ax
            bottom = grid[r0 + 1, c0] * (1 - ax) + grid[r0 + 1, c0 + 1] * ax
            return top * (1 - ay) + bottom * ay

        value = np.where(inside, bilinear(field), np.inf)
        if not gradient:
            return value, None
        gy, gx = self.gradient
        grad = np.stack([bilinear(gx), bilinear(gy)], axis=1)
        grad[~inside] = 0.0
        return value, grad

    def _cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The label of each point's nearest obstacle cell (0 off the window)."""
        h, w = self.labels.shape
        col = np.rint((points[:, 0] - self.x0) / self.resolution).astype(np.int64)
        row = np.rint((points[:, 1] - self.y0) / self.resolution).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        label = np.zeros(len(points), np.int64)
        label[inside] = self.labels[row[inside], col[inside]]
        return label, inside

    def _to_walls(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        label, inside = self._cells(points)
        normal = self.wall_normals[label]
        value = np.einsum("ij,ij->i", points - self.targets[label], normal)
        return np.where(inside, value, np.inf), np.where(inside[:, None], normal, 0.0)

    def seen(self, points: np.ndarray, explored: np.ndarray) -> np.ndarray:
        """Which points lie by floor the map has seen (within two cells), where a map would have
        its walls: a point elsewhere was out of every earlier view."""
        near = cv2.dilate(explored.astype(np.uint8), np.ones((5, 5), np.uint8))
        h, w = near.shape
        col = np.rint((points[:, 0] - self.x0) / self.resolution).astype(np.int64)
        row = np.rint((points[:, 1] - self.y0) / self.resolution).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        seen = np.zeros(len(points), bool)
        seen[inside] = near[row[inside], col[inside]].astype(bool)
        return seen

    def normals(self, points: np.ndarray) -> np.ndarray:
        """The unit normal (N x 2) of the wall nearest each point (zero where the map is flat:
        nothing there fixes the pose)."""
        label, inside = self._cells(points)
        return np.where(inside[:, None], self.wall_normals[label], 0.0)


def _principal_axis(jxx: np.ndarray, jxy: np.ndarray, jyy: np.ndarray) -> np.ndarray:
    """The unit main axis of each 2 x 2 structure tensor (zero where it is flat)."""
    angle = 0.5 * np.arctan2(2 * jxy, jxx - jyy)
    strength = np.hypot(jxx - jyy, 2 * jxy) > 1e-9
    return np.stack([np.cos(angle), np.sin(angle)], axis=1) * strength[:, None]


def _normal_equations(normals: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """How well points on walls with these unit normals fix the pose: their normal equations
    (rotation over a 1 m lever), per point. Its smallest eigenvalue is about zero for a blank
    wall, which fixes nothing along itself."""
    if len(normals) < 3:
        return np.zeros((3, 3))
    jac = _jacobian(normals, rel)
    return np.asarray(jac.T @ jac / len(normals))


def _thin(points: np.ndarray, cell: float, limit: int) -> np.ndarray:
    """One point per ``cell``-sized square (the nearest walls would outvote the rest), at most
    ``limit`` of them, evenly picked (a stride first: a frame has tens of thousands)."""
    if len(points) == 0:
        return np.zeros((0, 2))
    points = points[::max(1, len(points) // (8 * limit))].astype(np.float64)
    keys = np.floor(points / cell).astype(np.int64)
    _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
    kept = points[np.sort(first)]
    if len(kept) > limit:
        kept = kept[np.linspace(0, len(kept) - 1, limit).astype(np.int64)]
    return kept


def _window(points: np.ndarray, margin: float, grid: GridGeometry) -> tuple[slice, slice] | None:
    lo = points.min(axis=0) - margin
    hi = points.max(axis=0) + margin
    r0, c0 = grid.to_cell(lo[0], lo[1])
    r1, c1 = grid.to_cell(hi[0], hi[1])
    r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1 + 1, grid.rows), min(c1 + 1, grid.cols)
    if r1 - r0 < 2 or c1 - c0 < 2:
        return None
    return slice(r0, r1), slice(c0, c1)


def _moved(points: np.ndarray, centre: np.ndarray, delta: np.ndarray) -> np.ndarray:
    c, s = math.cos(delta[2]), math.sin(delta[2])
    rel = points - centre
    return np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]], axis=1) + centre + delta[:2]


def _jacobian(grad: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """d distance / d (tx, ty, theta) per point (``rel``: the moved point from the centre)."""
    return np.stack([grad[:, 0], grad[:, 1], grad[:, 1] * rel[:, 0] - grad[:, 0] * rel[:, 1]], axis=1)


def _bounded(delta: np.ndarray, max_m: float, max_rad: float) -> tuple[np.ndarray, bool]:
    scale = min(1.0, max_m / max(math.hypot(delta[0], delta[1]), 1e-12), max_rad / max(abs(delta[2]), 1e-12))
    return delta * scale, scale < 1.0


def _as_pose(delta: np.ndarray, centre: np.ndarray) -> Pose:
    """The correction as a map-frame transform: rotate by theta about ``centre``, then shift."""
    theta = float(delta[2])
    c, s = math.cos(theta), math.sin(theta)
    x = centre[0] - (c * centre[0] - s * centre[1]) + delta[0]
    y = centre[1] - (s * centre[0] + c * centre[1]) + delta[1]
    return Pose(x=float(x), y=float(y), yaw=theta)
