"""Localization in the map: each frame's obstacle points matched against the map built so far.

Wheel odometry drifts, and a map fused at odometry poses doubles its walls. So the map lives in a
``map`` frame and the localizer keeps ``map_T_odom``: a frame arrives posed by odometry, is placed
in the map by the current ``map_T_odom``, and its 2D scan (the depth points in the obstacle band,
which the map marks anyway) is matched against the map's obstacles; the match corrects
``map_T_odom`` and the frame is fused where it was taken.

The matcher is a scan-to-map Gauss-Newton on a distance field (Hector SLAM's and Cartographer's
way): the map is a grid already, so the field is one ``cv2.distanceTransform`` of a window
around the scan, and a match costs well under a millisecond of numpy. Two passes: the field
truncated far (a wide basin, for a drift of a decimetre or more) and then near (precision;
points that meet nothing mapped are left out). A match is refused, and odometry kept, when it
cannot be trusted: too few points (no depth, a wall closer than the camera's minimum range),
too few of them on mapped obstacles (a new room), or a scan that constrains the pose in one
direction only (a blank wall, a featureless corridor): the smallest eigenvalue of its
normal equations, per point, says so. An accepted correction moves the map by at most
``max_step_m`` / ``max_step_deg`` a frame, so one bad match cannot throw the map away.
Why this and not Open3D's ICP or KISS-ICP: docs/method.md (#localization).
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
from ovamos.shared.motion import IDENTITY, Pose

__all__ = ["LocalizationConfig", "Localizer", "Match"]

Verdict = Literal["matched", "no_map", "few_points", "few_inliers", "degenerate"]


class LocalizationConfig(BaseModel):
    """When a scan-to-map match is made and trusted."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(default=False, description="match each frame against the map (off: the map is "
                          "built at odometry poses, as before localization existed)")
    max_points: int = Field(default=600, ge=10, description="the scan is thinned to this many points")
    min_points: int = Field(default=60, ge=3, description="fewer scan points: refused (no depth, a wall "
                            "closer than the camera's range)")
    min_map_cells: int = Field(default=40, ge=1, description="fewer mapped obstacle cells: nothing to match")
    coarse_m: float = Field(default=0.3, gt=0, description="first pass: points this far from a mapped "
                            "obstacle still pull (the basin of the match)")
    fine_m: float = Field(default=0.1, gt=0, description="second pass and inliers: points within this "
                          "of a mapped obstacle")
    iterations: int = Field(default=8, ge=1, description="Gauss-Newton iterations per pass")
    min_inlier_ratio: float = Field(default=0.7, ge=0, le=1, description="fewer scan points on mapped "
                                    "obstacles after the match: refused (a place not mapped yet)")
    min_constraint: float = Field(default=0.05, ge=0, description="the smallest eigenvalue of the match's "
                                  "normal equations per inlier (rotation over a 1 m lever): below it, "
                                  "the scan fixes the pose in one direction only (a blank wall)")
    max_step_m: float = Field(default=0.05, gt=0, description="an accepted correction moves the map by "
                              "at most this a frame")
    max_step_deg: float = Field(default=2.0, gt=0)


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

    def to_map(self, odom: Pose) -> Pose:
        return self.map_T_odom.compose(odom)

    def match(self, points: np.ndarray, camera: tuple[float, float], obstacle: np.ndarray,
              grid: GridGeometry) -> Match:
        """Match ``points`` (N x 2 map xy of the scan, placed by the current ``map_T_odom``) seen
        from ``camera`` against ``obstacle`` (the map's grid, before this frame is fused), and on
        success move ``map_T_odom`` by the correction (bounded). Counted by verdict."""
        m = self._match(points, camera, obstacle, grid)
        if m.accepted:
            self.map_T_odom = m.correction.compose(self.map_T_odom)
            self.counters["clamped"] += m.clamped
        self.counters[m.verdict] += 1
        self.last = m
        return m

    def _match(self, points: np.ndarray, camera: tuple[float, float], obstacle: np.ndarray,
               grid: GridGeometry) -> Match:
        c = self.config
        scan = _thin(points, grid.resolution / 2, c.max_points)
        if len(scan) < c.min_points:
            return Match("few_points", points=len(scan))
        window = _window(scan, c.coarse_m + 2 * grid.resolution, grid)
        if window is None or np.count_nonzero(obstacle[window]) < c.min_map_cells:
            return Match("no_map", points=len(scan))
        fields = _Fields(obstacle, window, grid, c.coarse_m)
        centre = np.asarray(camera, dtype=np.float64)
        delta = np.zeros(3)  # (tx, ty, theta): p' = R(theta) (p - centre) + centre + t
        for fine, cap in ((False, c.coarse_m), (True, c.fine_m)):
            use = fields.sample(_moved(scan, centre, delta), False)[0] < cap
            if np.count_nonzero(use) < c.min_points:
                return Match("few_inliers", points=len(scan), inlier_ratio=float(np.mean(use)))
            delta = _descend(fields, scan[use], centre, delta, fine, c.iterations)
        moved = _moved(scan, centre, delta)
        near = fields.sample(moved, False)[0] < c.fine_m
        ratio = float(np.mean(near))
        constraint = _constraint(fields.sample(moved[near], True)[1], moved[near] - centre - delta[:2])
        if ratio < c.min_inlier_ratio:
            return Match("few_inliers", points=len(scan), inlier_ratio=ratio, constraint=constraint)
        if constraint < c.min_constraint:
            return Match("degenerate", points=len(scan), inlier_ratio=ratio, constraint=constraint)
        delta, clamped = _bounded(delta, c.max_step_m, math.radians(c.max_step_deg))
        return Match("matched", _as_pose(delta, centre), len(scan), ratio, constraint, clamped)


def _descend(fields: _Fields, points: np.ndarray, centre: np.ndarray, delta: np.ndarray, fine: bool,
             iterations: int) -> np.ndarray:
    """Gauss-Newton on one field from ``delta``, each step halved until the cost falls (the field
    is bilinear between cells, so a full step can overshoot); stops when no step helps."""
    def cost(d: np.ndarray) -> float:
        value = fields.sample(_moved(points, centre, d), fine)[0]
        return float(value @ value)

    current = cost(delta)
    for _ in range(iterations):
        moved = _moved(points, centre, delta)
        value, grad = fields.sample(moved, fine)
        jac = _jacobian(grad, moved - centre - delta[:2])
        step = np.linalg.lstsq(jac.T @ jac, -jac.T @ value, rcond=None)[0]
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
    """Two fields over a window of the map, sampled bilinearly with their gradients at any point:
    the distance to the nearest mapped obstacle (metres, truncated at ``far``: the coarse pass and
    the inlier test) and one minus the obstacle grid blurred by a cell over its largest value two
    cells round (the fine pass: zero on the middle of a wall's cells however thick they are, where
    the distance is flat zero, so Gauss-Newton meets a zero residual there)."""

    def __init__(self, obstacle: np.ndarray, window: tuple[slice, slice], grid: GridGeometry,
                 far: float) -> None:
        rows, cols = window
        occupied = obstacle[rows, cols]
        dist = cv2.distanceTransform((~occupied).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        self.coarse = np.minimum(dist.astype(np.float64) * grid.resolution, far)
        blurred = cv2.GaussianBlur(occupied.astype(np.float64), (0, 0), 1.0)
        ridge = cv2.dilate(blurred, np.ones((5, 5), np.uint8))  # the nearest wall's middle, two cells round
        self.fine = 1.0 - blurred / np.maximum(ridge, 1e-6)
        self.gradients = {False: np.gradient(self.coarse, grid.resolution),
                          True: np.gradient(self.fine, grid.resolution)}
        self.x0 = grid.x0 + (cols.start + 0.5) * grid.resolution  # the first cell's centre
        self.y0 = grid.y0 + (rows.start + 0.5) * grid.resolution
        self.resolution = grid.resolution

    def sample(self, points: np.ndarray, fine: bool) -> tuple[np.ndarray, np.ndarray]:
        """The field (N) and its gradient (N x 2, d/dx, d/dy) at ``points``; points off the
        window read as far, with no gradient."""
        field = self.fine if fine else self.coarse
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

        gy, gx = self.gradients[fine]
        value = np.where(inside, bilinear(field), np.inf)
        grad = np.stack([bilinear(gx), bilinear(gy)], axis=1)
        grad[~inside] = 0.0
        return value, grad


def _constraint(grad: np.ndarray, rel: np.ndarray) -> float:
    """How well points on walls with these gradients fix the pose: the smallest eigenvalue of
    the normal equations of their unit normals (rotation over a 1 m lever), per point; a blank
    wall fixes nothing along itself and gives about zero."""
    norm = np.linalg.norm(grad, axis=1)
    ok = norm > 1e-9
    if np.count_nonzero(ok) < 3:
        return 0.0
    jac = _jacobian(grad[ok] / norm[ok, None], rel[ok])
    return float(np.linalg.eigvalsh(jac.T @ jac)[0] / np.count_nonzero(ok))


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
