"""Navigation controller: a shortest path on the inflated map, followed with discrete primitives.

Paper: "path on the inflated obstacle map -> discrete commands MOVE_FORWARD 0.25 m,
TURN_LEFT 30 deg, TURN_RIGHT 30 deg, STOP". The executor asks, once per primitive, what the
robot should do next to reach the chosen goal (:meth:`Navigator.next_command`).

The grid searches are :mod:`ovamos.shared.gridpaths` (8-connected without corner cutting).
Obstacles are grown by the robot radius with :func:`ovamos.shared.grid.inflate`, the function the
mapping service uses for its frontiers, so a frontier waypoint is a traversable cell here.

Nothing here talks to Zenoh; the planner service wraps it.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ovamos.shared.grid import GridGeometry
from ovamos.shared.gridpaths import Window, auto_window, gather, shortest_paths, traversable
from ovamos.shared.messages import MapSnapshot
from ovamos.shared.motion import Action, Pose, wrap_angle
from ovamos.shared.robot import PRIMITIVES, ROBOT

__all__ = ["Unreachable", "NavigationConfig", "NavMap", "segment_cells", "Navigator"]

_SQRT2 = math.sqrt(2.0)


class Unreachable(RuntimeError):
    """The goal cannot be reached; the message says why, so the planner can log it and move on."""


class NavigationConfig(BaseModel):
    """Every navigation parameter; primitive sizes and radius are the paper's."""

    model_config = ConfigDict(extra="forbid")
    robot_radius: float = Field(
        default=ROBOT.navigation_radius_m, ge=0,
        description="obstacles grow by this much (see RobotGeometry.navigation_radius_m: below the "
                    "footprint on purpose)")
    forward_m: float = Field(default=PRIMITIVES.forward_m, gt=0, description="length of MOVE_FORWARD")
    turn_deg: float = Field(default=PRIMITIVES.turn_deg, gt=0, le=180,
                            description="angle of TURN_LEFT/RIGHT")
    goal_tolerance_m: float = Field(
        default=0.25, gt=0,
        description="STOP this close to the goal; must exceed forward_m / (2 cos(turn/2)) or the "
                    "robot can step over the goal back and forth forever")
    unknown_is_free: bool = Field(
        default=True,
        description="plan through unexplored cells (optimistic, like VLFM); only seen obstacles "
                    "block. False: only explored cells are traversable")
    snap_radius_m: float = Field(
        default=0.5, ge=0,
        description="a goal in an obstacle (an object on furniture, a value peak on a wall) is "
                    "moved to the nearest reachable cell within this distance")
    max_replans: int = Field(
        default=30, ge=0,
        description="re-plans for one goal (the map invalidated the path, the robot left it) "
                    "before it is reported unreachable: a goal revealed to be walled off bit "
                    "by bit must not keep the robot busy forever")
    same_goal_m: float = Field(
        default=0.25, ge=0,
        description="a goal this close to the one being pursued is the same goal (plan and counters "
                    "kept): an object's estimate moves by centimetres as detections refine it, and "
                    "starting afresh on each move reset the stall and re-plan counters, so an "
                    "unreachable object was chased for hundreds of commands")
    stall_commands: int = Field(
        default=40, ge=1,
        description="commands in a row without getting closer to the goal (by path length) "
                    "before it is reported unreachable; turning on the spot counts")
    heading_slack_deg: float = Field(
        default=0.0, ge=0,
        description="keep driving straight while the heading error is within turn_deg / 2 plus "
                    "this; 0 turns as soon as another heading is closer (the paper's rule)")
    lookahead_m: float = Field(
        default=2.0, gt=0,
        description="the robot heads for the farthest path point in sight up to this far along "
                    "the path: farther saves nothing and costs line-of-sight checks")
    search_budget: int = Field(
        default=3000, ge=1,
        description="expansions of the primitive-lattice search used when the step ahead is "
                    "blocked (bounds its time to ~0.1 s)")
    detour_progress_m: float = Field(
        default=1.0, gt=0,
        description="the lattice search stops once its detour gets this much closer to the goal")
    detour_tolerance_m: float = Field(
        default=0.05, ge=0,
        description="a detour is followed while the robot is this close to where it expects "
                    "(a wheeled base lands within a centimetre of each primitive, not exactly); "
                    "farther, or a step blocked, and the path is followed afresh")
    detour_tolerance_deg: float = Field(
        default=5.0, ge=0, description="the same for the heading")

    @model_validator(mode="after")
    def _tolerance_reachable(self) -> NavigationConfig:
        # With the heading within turn/2 of the goal, a step of f from distance d lands at
        # sqrt(d^2 + f^2 - 2 d f cos e), which is < d only for d > f / (2 cos e).
        error = math.radians(self.turn_deg / 2 + self.heading_slack_deg)
        if error >= math.pi / 2:
            raise ValueError("turn_deg / 2 + heading_slack_deg must stay below 90 deg")
        bound = self.forward_m / (2 * math.cos(error))
        if self.goal_tolerance_m <= bound:
            raise ValueError(f"goal_tolerance_m must exceed {bound:.3f} m (forward_m / "
                             f"(2 cos(turn_deg / 2))): a smaller one cannot always be hit")
        return self


@dataclass(frozen=True)
class NavMap:
    """The two map layers navigation reads, with the grid they live on."""

    obstacle: np.ndarray  # bool H x W
    explored: np.ndarray  # bool H x W
    grid: GridGeometry

    @classmethod
    def from_snapshot(cls, snapshot: MapSnapshot) -> NavMap:
        rows, cols = snapshot.obstacle.shape
        grid = GridGeometry(snapshot.resolution, snapshot.origin[0], snapshot.origin[1], rows, cols)
        return cls(snapshot.obstacle, snapshot.explored, grid)

    @classmethod
    def of(cls, source: NavMap | MapSnapshot) -> NavMap:
        return source if isinstance(source, NavMap) else cls.from_snapshot(source)


# ---------------------------------------------------------------------------------------------
# Segments on the grid
# ---------------------------------------------------------------------------------------------


def segment_cells(grid: GridGeometry, p0: tuple[float, float], p1: tuple[float, float]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of every cell the segment p0-p1 passes through (exact, not sampled).

    The segment is cut where it crosses grid lines; each piece lies in one cell, found from its
    midpoint. A cell touched only at a corner point is not included, except at the end point.
    Rows/cols may repeat or fall outside the grid.
    """
    res = grid.resolution
    u0, v0 = (p0[0] - grid.x0) / res, (p0[1] - grid.y0) / res
    u1, v1 = (p1[0] - grid.x0) / res, (p1[1] - grid.y0) / res
    cuts = [np.array([0.0, 1.0])]
    for a, b in ((u0, u1), (v0, v1)):
        if a != b:
            lines = np.arange(math.floor(min(a, b)) + 1, math.ceil(max(a, b)))
            cuts.append((lines - a) / (b - a))
    t = np.unique(np.concatenate(cuts))
    t = np.concatenate([[0.0], (t[:-1] + t[1:]) / 2])
    # The end point, with a hair either side: an end exactly on a grid line (common: 0.25 m is
    # 5 cells) claims both cells, so a rounding difference in whoever executes the step
    # cannot land it in the other one.
    eps = 1e-9
    u = np.concatenate([u0 + t * (u1 - u0), [u1 - eps, u1 + eps, u1 - eps, u1 + eps]])
    v = np.concatenate([v0 + t * (v1 - v0), [v1 - eps, v1 - eps, v1 + eps, v1 + eps]])
    return np.floor(v).astype(np.int64), np.floor(u).astype(np.int64)


def _segment_free(trav: np.ndarray, grid: GridGeometry, p0: tuple[float, float],
                  p1: tuple[float, float]) -> bool:
    rows, cols = segment_cells(grid, p0, p1)
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= grid.rows or cols.max() >= grid.cols:
        return False
    return bool(trav[rows, cols].all())


def _snap_offsets(radius_cells: int) -> np.ndarray:
    """Cell offsets within a disc, nearest first: the order goals are snapped in."""
    r = radius_cells
    dr, dc = np.mgrid[-r:r + 1, -r:r + 1]
    d2 = dr ** 2 + dc ** 2
    keep = d2 <= r * r
    order = np.argsort(d2[keep], kind="stable")
    return np.stack([dr[keep][order], dc[keep][order]], axis=1).astype(np.int64)


# ---------------------------------------------------------------------------------------------
# The controller
# ---------------------------------------------------------------------------------------------


@dataclass
class _Plan:
    """A cost-to-go field towards one goal: any robot cell in it has a path, no re-plan needed."""

    goal: tuple[float, float]
    target: tuple[float, float]  # the point driven to: the goal, or the cell it was snapped to
    target_cell: tuple[int, int]
    grid: GridGeometry
    window: Window
    dist: np.ndarray  # metres to the target, window-shaped
    pred: np.ndarray  # flat window index of the next cell towards the target, -1 at the end

    def cost(self, cell: tuple[int, int]) -> float:
        r, c = cell[0] - self.window[0], cell[1] - self.window[2]
        if 0 <= r < self.dist.shape[0] and 0 <= c < self.dist.shape[1]:
            return float(self.dist[r, c])
        return math.inf

    def estimate(self, cell: tuple[int, int]) -> float:
        """:meth:`cost` inside the window; outside it (but on the grid), the cost of the nearest
        window cell (the cell clamped into the window) plus the 8-connected length to it.

        The window is only as large as exact path lengths need (:func:`auto_window`: typically
        the obstacles' box plus a free ring of two cells), but a robot moving in exact 0.25 m /
        30 deg primitives swings wider than a cell path and may need to pass outside it. There
        everything was free when the plan was made, so this is an upper bound of the true cost
        (at least the clamped cell's, since clamping a path never lengthens it): a guide for
        the lattice search, where :meth:`cost` (inf outside) would wall the robot in.
        """
        h, w = self.dist.shape
        r, c = cell[0] - self.window[0], cell[1] - self.window[2]
        if 0 <= r < h and 0 <= c < w:
            return float(self.dist[r, c])
        if not (self.grid.contains(*cell) and h and w):
            return math.inf
        dr = abs(r - min(max(r, 0), h - 1))
        dc = abs(c - min(max(c, 0), w - 1))
        near = float(self.dist[min(max(r, 0), h - 1), min(max(c, 0), w - 1)])
        return near + self.grid.resolution * (abs(dr - dc) + _SQRT2 * min(dr, dc))

    def chain(self, cell: tuple[int, int]) -> np.ndarray:
        """Grid cells (K x 2) from ``cell`` to the target, following the predecessors."""
        w = self.dist.shape[1]
        node = (cell[0] - self.window[0]) * w + cell[1] - self.window[2]
        pred = self.pred.ravel()
        nodes = [node]
        while (node := int(pred[node])) >= 0:
            nodes.append(node)
        flat = np.array(nodes, dtype=np.int64)
        return np.stack([flat // w + self.window[0], flat % w + self.window[2]], axis=1)


@dataclass
class _Step:
    """A primitive the robot should execute from a pose (a lattice-search detour)."""

    x: float
    y: float
    yaw: float
    action: Action


@dataclass
class _Last:
    """What the last call saw, for :attr:`Navigator.path` (computed only when asked)."""

    pos: tuple[float, float]
    chain: np.ndarray
    target: tuple[float, float]
    trav: np.ndarray
    grid: GridGeometry


@dataclass
class Navigator:
    """Drives one robot to a goal, one discrete primitive per call.

    The caller calls :meth:`next_command` once per executed primitive with the newest map, the
    robot's pose and its current goal. The navigator keeps a cost-to-go field to the goal (one
    Dijkstra from the goal) and re-plans only when the goal changes, the remaining path crosses
    a cell the new map blocks, or the robot is outside the field; a robot knocked off the path
    needs no re-plan, since every cell of the field knows its way. It returns STOP within
    ``goal_tolerance_m`` and raises :class:`Unreachable` (with the reason) when the goal cannot
    be reached, after a bounded number of calls in every case. A goal moved farther than
    ``same_goal_m`` starts afresh (plan and counters); a nearer one is the goal being pursued.

    MOVE_FORWARD is only returned when every cell the 0.25 m segment crosses is traversable on
    the inflated map. The one exception is a robot that is already inside the inflation (the
    map grew an obstacle next to it): it may then move through cells that are no closer to an
    obstacle than it is, so that it can escape instead of freezing.
    """

    config: NavigationConfig = field(default_factory=NavigationConfig)
    _goal: tuple[float, float] | None = field(default=None, init=False, repr=False)
    _snap: float = field(default=0.0, init=False, repr=False)
    _plan: _Plan | None = field(default=None, init=False, repr=False)
    _replans: int = field(default=0, init=False, repr=False)
    _detour: list[_Step] = field(default_factory=list, init=False, repr=False)
    _best: float = field(default=math.inf, init=False, repr=False)
    _stall: int = field(default=0, init=False, repr=False)
    _last: _Last | None = field(default=None, init=False, repr=False)

    def reset(self) -> None:
        """Forget the goal, path and counters (a new task)."""
        self._goal, self._plan, self._replans, self._detour = None, None, 0, []
        self._best, self._stall, self._last = math.inf, 0, None

    @property
    def replans(self) -> int:
        """Re-plans for the current goal so far (the first plan is not one)."""
        return self._replans

    @property
    def target(self) -> tuple[float, float] | None:
        """The point actually driven to: the goal, or where it was snapped to."""
        return self._plan.target if self._plan else None

    @property
    def path(self) -> np.ndarray:
        """The simplified remaining path (K x 2 world xy, ending at :attr:`target`) as of the
        last call; empty before the first plan or at the goal."""
        last = self._last
        if last is None or len(last.chain) < 2:
            return np.zeros((0, 2))
        points = self._chain_points(last.chain, last.target, last.grid)
        out, pos = [], last.pos
        i = 0
        while i < len(points):
            j = self._visible(pos, points, i, len(points), last.trav, last.grid)
            out.append(points[j])
            pos, i = tuple(points[j]), j + 1
        return np.array(out)

    # -- the call --------------------------------------------------------------------------------

    def next_command(self, nav_map: NavMap | MapSnapshot, pose: Pose | Sequence[float],
                     goal: Sequence[float], snap_radius_m: float | None = None) -> Action:
        """The primitive to execute now to get to ``goal`` (world x, y).

        ``snap_radius_m`` overrides the configured one for this goal: an object on a bed is
        reached from beside the bed, farther than a value peak on a wall is snapped.
        Raises :class:`Unreachable` when the goal is outside the map, walled off, in an
        obstacle with no reachable cell within the snap radius, or when the robot's
        primitives cannot make progress towards it.
        """
        cfg, m = self.config, NavMap.of(nav_map)
        x, y, yaw = (pose.x, pose.y, pose.yaw) if isinstance(pose, Pose) else map(float, pose)
        goal = (float(goal[0]), float(goal[1]))
        snap = cfg.snap_radius_m if snap_radius_m is None else snap_radius_m
        if self._goal is None or snap != self._snap or math.dist(goal, self._goal) > cfg.same_goal_m:
            self.reset()
            self._goal, self._snap = goal, snap
        goal = self._goal
        tol = cfg.goal_tolerance_m
        if math.hypot(goal[0] - x, goal[1] - y) <= tol:
            return Action.STOP
        cell = m.grid.to_cell(x, y)
        if not m.grid.contains(*cell):
            raise Unreachable(f"the robot ({x:.2f}, {y:.2f}) is outside the map")
        trav = self._traversable(m, cell)

        chain = self._valid_chain(m, trav, cell)
        if chain is None:
            if self._plan is not None:
                self._replans += 1
                if self._replans > cfg.max_replans:
                    raise Unreachable(f"goal ({goal[0]:.2f}, {goal[1]:.2f}): gave up after "
                                      f"{cfg.max_replans} re-plans (the map keeps blocking "
                                      f"the path)")
            self._plan = self._make_plan(m, trav, cell, goal)
            self._best, self._stall, self._detour = math.inf, 0, []
            chain = self._plan.chain(cell)
        plan = self._plan
        self._last = _Last((x, y), chain, plan.target, trav, m.grid)
        if math.hypot(plan.target[0] - x, plan.target[1] - y) <= tol:
            return Action.STOP

        if (action := self._follow_detour(x, y, yaw, trav, m.grid)) is not None:
            return action
        self._watch_progress(plan.cost(cell))
        return self._follow_path(x, y, yaw, chain, trav, m.grid)

    def reachable_share(self, nav_map: NavMap | MapSnapshot, pose: Pose) -> float:
        """The share of the explored cells the robot could stand on that it can reach from where
        it is (1.0 when nothing is explored). Well under 1, the robot is boxed in: it drove
        through the space it is now cut off from, so what cuts it off is newer than that."""
        m = NavMap.of(nav_map)
        cell = m.grid.to_cell(pose.x, pose.y)
        if not m.grid.contains(*cell):
            return 0.0
        trav = self._traversable(m, cell)
        standing = trav & m.explored
        total = int(standing.sum())
        if total == 0:
            return 1.0
        labels = cv2.connectedComponents(trav.astype(np.uint8), connectivity=4)[1]
        return float((standing & (labels == labels[cell])).sum()) / total

    # -- map and plan ----------------------------------------------------------------------------

    def _traversable(self, m: NavMap, cell: tuple[int, int]) -> np.ndarray:
        cfg = self.config
        trav = traversable(m.obstacle, m.explored, m.grid.resolution, cfg.robot_radius,
                           cfg.unknown_is_free)
        if not trav[cell]:
            self._open_escape(trav, m.obstacle, cell, m.grid.resolution)
        return trav

    def _open_escape(self, trav: np.ndarray, obstacle: np.ndarray, cell: tuple[int, int],
                     res: float) -> None:
        """Let a robot inside the inflation leave it: around it (one step plus a radius), cells
        no closer to an obstacle than its own become traversable, and its own cell too."""
        cfg = self.config
        reach = int(math.ceil((cfg.robot_radius + cfg.forward_m) / res)) + 1
        pad = reach + int(math.ceil(cfg.robot_radius / res)) + 1  # obstacles that shape the zone
        r, c = cell
        r0, r1 = max(r - pad, 0), min(r + pad + 1, obstacle.shape[0])
        c0, c1 = max(c - pad, 0), min(c + pad + 1, obstacle.shape[1])
        sub = obstacle[r0:r1, c0:c1]
        clearance = cv2.distanceTransform((~sub).astype(np.uint8), cv2.DIST_L2,
                                          cv2.DIST_MASK_PRECISE)
        own = clearance[r - r0, c - c0]
        rr, cc = np.mgrid[r0:r1, c0:c1]
        zone = (clearance >= own) & ~sub & ((rr - r) ** 2 + (cc - c) ** 2 <= reach * reach)
        trav[r0:r1, c0:c1] |= zone
        trav[r, c] = True

    def _valid_chain(self, m: NavMap, trav: np.ndarray, cell: tuple[int, int]) -> np.ndarray | None:
        """The cached path from the robot's cell, if the plan is for this map and still clear."""
        plan = self._plan
        if plan is None or plan.grid != m.grid or not math.isfinite(plan.cost(cell)):
            return None
        chain = plan.chain(cell)
        return chain if trav[chain[:, 0], chain[:, 1]].all() else None

    @staticmethod
    def _clamped_extent(cells: np.ndarray, offsets: np.ndarray, grid: GridGeometry) -> np.ndarray:
        """Corners of each cell's snap disc, clamped into the grid, for the search window."""
        r = int(np.abs(offsets).max()) if offsets.size else 0
        lo = np.clip(cells - r, 0, (grid.rows - 1, grid.cols - 1))
        hi = np.clip(cells + r, 0, (grid.rows - 1, grid.cols - 1))
        return np.vstack([lo, hi])

    def _make_plan(self, m: NavMap, trav: np.ndarray, cell: tuple[int, int],
                   goal: tuple[float, float]) -> _Plan:
        grid = m.grid
        name = f"goal ({goal[0]:.2f}, {goal[1]:.2f})"
        goal_cell = np.array([grid.to_cell(*goal)])
        offsets = _snap_offsets(round(self._snap / grid.resolution))
        candidates = goal_cell + offsets
        inside = ((candidates[:, 0] >= 0) & (candidates[:, 0] < grid.rows) & (candidates[:, 1] >= 0)
                  & (candidates[:, 1] < grid.cols))
        if not inside.any():
            raise Unreachable(f"{name} is outside the map")
        extent = self._clamped_extent(goal_cell, offsets, grid)
        window = auto_window(trav, np.vstack([[cell], extent]))
        r0, r1, c0, c1 = window
        sub = trav[r0:r1, c0:c1]
        # 8-connected without corner cutting = 4-connected: labels say what the robot can reach.
        labels = cv2.connectedComponents(sub.astype(np.uint8), connectivity=4)[1]
        own = labels[cell[0] - r0, cell[1] - c0]
        reachable = gather(labels, candidates - (r0, c0), fill=-1) == own
        if not reachable.any():
            blocked = not trav[tuple(goal_cell[0])] if inside[0] else True
            why = ("is in or next to an obstacle" if blocked else "is walled off from the robot")
            raise Unreachable(f"{name} {why}, with no cell reachable from the robot within "
                              f"{self._snap} m")
        i = int(np.argmax(reachable))
        target_cell = (int(candidates[i, 0]), int(candidates[i, 1]))
        target = goal if i == 0 else grid.to_world(*target_cell)
        local = np.array([[target_cell[0] - r0, target_cell[1] - c0]])
        dist, pred = shortest_paths(sub, local, grid.resolution, predecessors=True)
        return _Plan(goal, target, target_cell, grid, window, dist, pred)

    # -- following -------------------------------------------------------------------------------

    def _watch_progress(self, cost: float) -> None:
        """Count commands that bring the robot no closer; give up past ``stall_commands``."""
        if cost < self._best - 1e-9:
            self._best, self._stall = cost, 0
            return
        self._stall += 1
        if self._stall > self.config.stall_commands:
            g = self._goal
            raise Unreachable(f"goal ({g[0]:.2f}, {g[1]:.2f}): no progress in "
                              f"{self.config.stall_commands} commands")

    def _step_end(self, x: float, y: float, yaw: float) -> tuple[float, float]:
        f = self.config.forward_m
        return x + f * math.cos(yaw), y + f * math.sin(yaw)

    def _follow_detour(self, x: float, y: float, yaw: float, trav: np.ndarray,
                       grid: GridGeometry) -> Action | None:
        """The next primitive of a lattice detour, while the robot is where the detour expects."""
        if not self._detour:
            return None
        step, cfg = self._detour[0], self.config
        if (math.hypot(step.x - x, step.y - y) > cfg.detour_tolerance_m + 1e-9
                or abs(wrap_angle(step.yaw - yaw)) > math.radians(cfg.detour_tolerance_deg) + 1e-9):
            self._detour = []
            return None
        if step.action is Action.MOVE_FORWARD and not _segment_free(
                trav, grid, (x, y), self._step_end(x, y, yaw)):
            self._detour = []  # the map changed under the detour
            return None
        self._detour.pop(0)
        return step.action

    @staticmethod
    def _chain_points(chain: np.ndarray, target: tuple[float, float], grid: GridGeometry
                      ) -> np.ndarray:
        """World points of the path after the robot's own cell, ending exactly at the target."""
        xs, ys = grid.to_world(chain[1:, 0], chain[1:, 1])
        points = np.stack([np.atleast_1d(xs), np.atleast_1d(ys)], axis=1)
        if len(points):
            points[-1] = target
        return points

    @staticmethod
    def _visible(pos: tuple[float, float], points: np.ndarray, start: int, stop: int,
                 trav: np.ndarray, grid: GridGeometry) -> int:
        """Index of the last of points[start:stop] in sight before the first one that is not
        (``start`` itself when none is: the path's next cell is always a legal straight move)."""
        j = start
        for i in range(start + 1, stop):
            if not _segment_free(trav, grid, pos, tuple(points[i])):
                break
            j = i
        return j

    def _follow_path(self, x: float, y: float, yaw: float, chain: np.ndarray, trav: np.ndarray,
                     grid: GridGeometry) -> Action:
        """Turn towards the farthest path point in sight, else step forward, else detour."""
        cfg, plan = self.config, self._plan
        points = self._chain_points(chain, plan.target, grid)
        if len(points) == 0:
            points = np.array([plan.target])
        stop = min(len(points), int(cfg.lookahead_m / grid.resolution) + 1)
        wx, wy = points[self._visible((x, y), points, 0, stop, trav, grid)]
        error = wrap_angle(math.atan2(wy - y, wx - x) - yaw)
        if abs(error) > math.radians(cfg.turn_deg / 2 + cfg.heading_slack_deg) + 1e-9:
            return Action.TURN_LEFT if error > 0 else Action.TURN_RIGHT
        if _segment_free(trav, grid, (x, y), self._step_end(x, y, yaw)):
            return Action.MOVE_FORWARD
        # Facing the path but the exact 0.25 m step clips the inflation (a door jamb, a corner
        # cut by the 30 deg heading set): plan primitives directly, then resume following.
        detour = self._lattice_search(x, y, yaw, trav, grid)
        if not detour:
            g = self._goal
            raise Unreachable(f"goal ({g[0]:.2f}, {g[1]:.2f}): no sequence of "
                              f"{cfg.forward_m} m / {cfg.turn_deg} deg primitives gets closer "
                              f"(passage too narrow for them)")
        self._detour = detour
        return self._detour.pop(0).action

    def _lattice_search(self, x: float, y: float, yaw: float, trav: np.ndarray,
                        grid: GridGeometry) -> list[_Step]:
        """A* over the robot's own primitives (hybrid-A* style: poses hashed per cell and
        heading), guided by the cost-to-go field.

        Returns the primitives to the first pose within tolerance of the target or
        ``detour_progress_m`` closer to it, else to the closest pose found within the budget;
        empty when no pose is closer than the start.
        """
        cfg, plan = self.config, self._plan
        f_m, turn = cfg.forward_m, math.radians(cfg.turn_deg)
        n_headings = max(1, round(2 * math.pi / turn))
        res, tol = grid.resolution, cfg.goal_tolerance_m
        tx, ty = plan.target

        def h(px: float, py: float) -> float:  # finite outside the plan's window too
            return plan.estimate(grid.to_cell(px, py))

        def key(px: float, py: float, k: int) -> tuple[int, int, int]:
            return math.floor(px / res), math.floor(py / res), k % n_headings

        h0 = h(x, y)
        start = key(x, y, 0)
        states: dict[tuple[int, int, int], tuple[float, float, int]] = {start: (x, y, 0)}
        best_g = {start: 0.0}
        parent: dict[tuple[int, int, int], tuple[tuple[int, int, int], Action]] = {}
        heap = [(1.5 * h0, 0.0, 0, start)]
        closed: set[tuple[int, int, int]] = set()
        best, best_h, counter, found = start, h0, 0, False
        while heap and len(closed) < cfg.search_budget:
            _, g_cost, _, k0 = heapq.heappop(heap)
            if k0 in closed or g_cost > best_g[k0]:
                continue
            closed.add(k0)
            px, py, k = states[k0]
            hp = h(px, py)
            if hp < best_h:
                best, best_h = k0, hp
            if math.hypot(tx - px, ty - py) <= tol or hp <= h0 - cfg.detour_progress_m:
                best, found = k0, True
                break
            heading = yaw + k * turn
            moves = [(Action.TURN_LEFT, px, py, k + 1, 0.5 * f_m),
                     (Action.TURN_RIGHT, px, py, k - 1, 0.5 * f_m)]
            nx, ny = px + f_m * math.cos(heading), py + f_m * math.sin(heading)
            if _segment_free(trav, grid, (px, py), (nx, ny)):
                moves.append((Action.MOVE_FORWARD, nx, ny, k, f_m))
            for action, qx, qy, qk, cost in moves:
                nkey = key(qx, qy, qk)
                ng = g_cost + cost
                if nkey in closed or ng >= best_g.get(nkey, math.inf):
                    continue
                hq = h(qx, qy)
                if not math.isfinite(hq):
                    continue
                best_g[nkey], states[nkey], parent[nkey] = ng, (qx, qy, qk), (k0, action)
                counter += 1
                heapq.heappush(heap, (ng + 1.5 * hq, ng, counter, nkey))
        if best == start or not (found or best_h < h0):
            return []
        steps: list[_Step] = []
        node = best
        while node != start:
            prev, action = parent[node]
            px, py, k = states[prev]
            steps.append(_Step(px, py, wrap_angle(yaw + k * turn), action))
            node = prev
        return steps[::-1]
