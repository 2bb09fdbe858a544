"""One decision step: from a map snapshot and the robot pose to the next goal.

Order of business (paper, Sec. III): a confirmed object of a remaining target
wins (go there and STOP; which one: :func:`_object_goal`); otherwise candidates and the best frontier are
taken from the (decayed, aggregated) value map, path lengths between the robot
and every action point are computed once, and the policy picks the goal. What
sets the policies apart (the targets searched at once, decay, how the goal is
chosen) is their :class:`ovamos.services.planner.policies.Policy`: the full
method, its ablations and the baselines (finder, vlfm, random) all run here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ovamos.services.mapping.layers import DECAY_KAPPA, DECAY_TAU, WHOLE, Window, value_map
from ovamos.services.planner.candidates import (
    CandidateConfig,
    Candidates,
    best_frontier,
    find_candidates,
    frontier_scores,
)
from ovamos.services.planner.plus import ManyFrontierPOMDP, PlusConfig, detection_candidates, frontier_bonuses
from ovamos.services.planner.policies import OVAMOS, POLICIES, Choice, Policy, PolicyName
from ovamos.services.planner.pomdp import POMDPConfig, SearchPOMDP, root_particles
from ovamos.services.planner.pouct import POUCT
from ovamos.shared.grid import GridGeometry, inflate
from ovamos.shared.gridpaths import FreeSpaceGraph
from ovamos.shared.messages import MapSnapshot, ObjectInstance, TraceOption
from ovamos.shared.robot import ROBOT


class DecisionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    policy: PolicyName = Field(default=OVAMOS.name, description="how the next goal is chosen: one of "
                               + ", ".join(POLICIES) + " (services/planner/policies.py)")
    candidates: CandidateConfig = Field(default_factory=CandidateConfig)
    pomdp: POMDPConfig = Field(default_factory=POMDPConfig)
    plus: PlusConfig = Field(default_factory=PlusConfig, description="ovamos-plus only")
    decay_tau: float = Field(default=DECAY_TAU, description="update count at which a value halves")
    decay_kappa: float = Field(default=DECAY_KAPPA, gt=0, description="how sharply it fades around tau")
    robot_radius: float = Field(default=ROBOT.radius_m, ge=0, description="path lengths keep this far from obstacles")
    distance_coarsening: int = Field(default=4, ge=1, description="path lengths on cells this many times larger")
    window_margin_m: float = Field(default=1.0, ge=0, description="path search beyond the explored area")
    snap_radius_m: float = Field(default=0.5, ge=0, description="action points in obstacles move this far at most")
    avoid_radius_m: float = Field(default=0.5, ge=0, description="unreachable goals block this much")
    seed: int = 0

    @property
    def chosen(self) -> Policy:
        """The policy :attr:`policy` names (validated when the config was read): the one lookup of a
        policy by name, where the config enters; the planner passes the object on."""
        return POLICIES[self.policy]


class GoalKind(str, Enum):
    OBJECT = "object"        # a confirmed instance: go there and STOP
    CANDIDATE = "candidate"
    FRONTIER = "frontier"


@dataclass(frozen=True)
class Decision:
    kind: GoalKind
    x: float
    y: float
    label: str | None = None   # the target, for OBJECT goals
    candidates: int = 0        # how many candidates the step considered
    reason: str = ""           # why this goal, in words (the planner's decision trace)
    options: tuple[TraceOption, ...] = ()  # what the step weighed (the decision trace)


def explored_window(snapshot: MapSnapshot) -> tuple[slice, slice, GridGeometry]:
    """The bounding box of the explored area (the whole grid before anything is explored),
    and its geometry: value maps are only ever non-zero inside it."""
    explored = snapshot.explored
    rows = np.flatnonzero(explored.any(axis=1))
    cols = np.flatnonzero(explored.any(axis=0))
    r0, r1 = (int(rows[0]), int(rows[-1]) + 1) if rows.size else (0, explored.shape[0])
    c0, c1 = (int(cols[0]), int(cols[-1]) + 1) if cols.size else (0, explored.shape[1])
    res = snapshot.resolution
    grid = GridGeometry(res, snapshot.origin[0] + c0 * res, snapshot.origin[1] + r0 * res, r1 - r0, c1 - c0)
    return slice(r0, r1), slice(c0, c1), grid


def decision_values(snapshot: MapSnapshot, remaining: Sequence[str], config: DecisionConfig,
                    window: Window = WHOLE) -> np.ndarray | None:
    """The value map ``config.policy`` decides on: :func:`ovamos.services.mapping.layers.value_map`
    of the remaining targets, decayed unless the policy's values do not decay."""
    return value_map(snapshot, remaining, config.decay_tau, config.decay_kappa,
                     decayed=config.chosen.decays, window=window)


class ActionDistances:
    """The distances of a decision step's POMDP: path lengths between its action points (the
    robot, candidates, the frontier) on one map (robot-radius-inflated obstacles, unexplored
    space optimistic), on a coarsened window around the explored area so a decision step
    stays cheap."""

    def __init__(self, snapshot: MapSnapshot, config: DecisionConfig,
                 include: np.ndarray | None = None) -> None:
        k = config.distance_coarsening
        res = snapshot.resolution
        explored = snapshot.explored
        rows, cols, _ = explored_window(snapshot)
        fine = GridGeometry(res, snapshot.origin[0], snapshot.origin[1], *explored.shape)
        r_lo, r_hi, c_lo, c_hi = rows.start, rows.stop, cols.start, cols.stop
        if include is not None and len(include):  # points (e.g. the robot) outside the explored box
            pr, pc = fine.to_cell(include[:, 0], include[:, 1])
            r_lo, r_hi = min(r_lo, pr.min()), max(r_hi, pr.max() + 1)
            c_lo, c_hi = min(c_lo, pc.min()), max(c_hi, pc.max() + 1)
        margin = int(np.ceil(config.window_margin_m / res))
        r0, c0 = max(int(r_lo) - margin, 0), max(int(c_lo) - margin, 0)
        r1, c1 = min(int(r_hi) + margin, explored.shape[0]), min(int(c_hi) + margin, explored.shape[1])
        r1, c1 = r0 + (r1 - r0) // k * k, c0 + (c1 - c0) // k * k
        blocked = inflate(snapshot.obstacle[r0:r1, c0:c1], config.robot_radius, res)
        h, w = blocked.shape
        # a coarse cell is free when any of its fine cells is: doorways stay open, and walls
        # (blocked over their thickness plus twice the robot radius) stay closed
        coarse = blocked.reshape(h // k, k, w // k, k).all(axis=(1, 3))
        self.grid = GridGeometry(res * k, fine.x0 + c0 * res, fine.y0 + r0 * res, h // k, w // k)
        self.graph = FreeSpaceGraph(~coarse, self.grid.resolution)
        self.snap_cells = int(np.ceil(config.snap_radius_m / self.grid.resolution))

    def _snap(self, x: float, y: float) -> tuple[int, int]:
        """The free coarse cell nearest to (x, y), within the snap radius (else the cell itself)."""
        r, c = self.grid.to_cell(x, y)
        free, s = self.graph.free, self.snap_cells
        r0, c0 = max(r - s, 0), max(c - s, 0)
        window = free[r0:r + s + 1, c0:c + s + 1]
        if not window.any():
            return r, c
        rr, cc = np.nonzero(window)
        i = int(np.argmin((rr + r0 - r) ** 2 + (cc + c0 - c) ** 2))
        return int(rr[i] + r0), int(cc[i] + c0)

    def matrix(self, points: np.ndarray) -> np.ndarray:
        """P x P path lengths (inf when unreachable)."""
        cells = [self._snap(x, y) for x, y in points]
        fields = self.graph.from_cells(cells)
        rows = np.array([r for r, _ in cells])
        cols = np.array([c for _, c in cells])
        inside = (rows >= 0) & (rows < self.grid.rows) & (cols >= 0) & (cols < self.grid.cols)
        out = np.full((len(cells), len(cells)), np.inf)
        out[:, inside] = fields[:, rows[inside], cols[inside]]
        return np.minimum(out, out.T)


def away(points: np.ndarray, avoid: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the points farther than ``radius`` from every avoided point."""
    if len(avoid) == 0 or len(points) == 0:
        return np.ones(len(points), bool)
    d2 = ((points[:, None, :] - avoid[None, :, :]) ** 2).sum(axis=2)
    return (d2 > radius * radius).all(axis=1)


def _object_goal(objects: Sequence[ObjectInstance], robot_xy: tuple[float, float], remaining: Sequence[str],
                 avoid: np.ndarray, radius: float) -> ObjectInstance | None:
    """The confirmed object to go to: of each remaining target, the instance with the most hits (ties:
    the older), not avoided; of those, the nearest in a straight line.

    Not simply the first confirmed: the map outlives a task, so a repeated task starts with its
    targets confirmed, the last found beside the robot, and taking them in the order the map
    confirmed them crossed the house and came back. Not simply the nearest instance either: a look-alike
    confirmed on two lucky frames is often nearer than the object the robot stopped at before.
    """
    picks = [o for o in objects if o.confirmed and o.label in remaining]
    allowed = away(np.array([(o.x, o.y) for o in picks]).reshape(-1, 2), avoid, radius)
    best: dict[str, ObjectInstance] = {}
    for obj, ok in zip(picks, allowed):  # the map's order, oldest first: a tie keeps the older
        if ok and (obj.label not in best or obj.hits > best[obj.label].hits):
            best[obj.label] = obj
    return min(best.values(), key=lambda o: math.hypot(o.x - robot_xy[0], o.y - robot_xy[1]), default=None)


def decide(snapshot: MapSnapshot, robot_xy: tuple[float, float], remaining: Sequence[str],
           config: DecisionConfig, avoid: np.ndarray | None = None,
           visited: np.ndarray | None = None) -> Decision | None:
    """The next goal, or None when there is nothing left to go to.

    ``avoid`` (K x 2 world xy) are goals that proved unreachable: objects, candidates and
    frontiers within ``config.avoid_radius_m`` of one are not chosen again. ``visited`` are
    places already looked at from close by: candidates and frontiers there are not chosen
    again, but an object confirmed there is (a value peak is where objects get confirmed).
    """
    policy = config.chosen
    avoid = _points(avoid)
    radius = config.avoid_radius_m
    remaining = policy.targets(remaining)
    if (obj := _object_goal(snapshot.objects, robot_xy, remaining, avoid, radius)) is not None:
        return Decision(GoalKind.OBJECT, obj.x, obj.y, obj.label,
                        reason=f"a confirmed {obj.label}, a remaining target: go beside it and stop")
    avoid = np.vstack([avoid, _points(visited)])
    frontiers = snapshot.frontiers[away(snapshot.frontiers, avoid, radius)]
    if policy.wanders:
        return None  # the agent walks at random between confirmed objects
    rows, cols, grid = explored_window(snapshot)
    values = decision_values(snapshot, remaining, config, (rows, cols))
    if values is None:
        values = np.zeros(grid.shape, np.float32)
    cands = find_candidates(values, grid, config.candidates)
    keep = away(cands.points, avoid, radius)
    if not keep.all():
        cands = Candidates(cands.points[keep], cands.values[keep],
                           cands.belief[keep] / max(cands.belief[keep].sum(), 1e-12))
    if policy.choice is Choice.PLUS:
        return _plus(snapshot, robot_xy, remaining, config, values, grid, frontiers, cands,
                     lambda points: away(points, avoid, radius))
    f = best_frontier(frontiers, values, grid, config.candidates.frontier_radius_m)
    frontier = None if f is None else frontiers[f]
    frontier_value = 0.0 if frontier is None else _value_at(values, grid, frontier)
    frontier_only = policy.choice is Choice.BEST_FRONTIER
    if frontier_only or len(cands.points) == 0:
        why = (f"{policy.name} always takes the best frontier" if frontier_only
               else "no candidate above the value threshold: the best frontier")
        return None if frontier is None else Decision(
            GoalKind.FRONTIER, *map(float, frontier), reason=why,
            options=_options(cands, *_one(frontier, frontier_value)))
    if policy.choice is Choice.GREEDY:
        return _greedy(cands, frontier, frontier_value)
    return _pouct(cands, *_one(frontier, frontier_value), robot_xy, snapshot, config)


def _points(xy: np.ndarray | None) -> np.ndarray:
    return np.zeros((0, 2)) if xy is None else np.asarray(xy, float).reshape(-1, 2)


def _value_at(values: np.ndarray, grid: GridGeometry, xy: np.ndarray) -> float:
    """The value map at a world point (its nearest cell of the window)."""
    row, col = grid.to_cell(*xy)
    return float(values[int(np.clip(row, 0, grid.rows - 1)), int(np.clip(col, 0, grid.cols - 1))])


def _options(cands: Candidates, frontiers: np.ndarray, frontier_values: np.ndarray,
             distances: np.ndarray | None = None, q: dict[int, tuple[float, int]] | None = None
             ) -> tuple[TraceOption, ...]:
    """The decision trace's options: the candidates (action i + 1) and the frontiers (the last
    actions), with path lengths from the robot (row 0 of ``distances``) and POUCT's ``q``."""
    def option(kind: Literal["candidate", "frontier"], i: int, xy: np.ndarray, value: float,
               belief: float | None) -> TraceOption:
        path = None if distances is None or not np.isfinite(distances[0, i]) else float(distances[0, i])
        qi, visits = (q or {}).get(i, (None, None))
        return TraceOption(kind=kind, x=float(xy[0]), y=float(xy[1]), value=value, belief=belief,
                           path_m=path, q=qi, visits=visits)

    n = len(cands.points)
    out = [option("candidate", i + 1, xy, float(v), float(b))
           for i, (xy, v, b) in enumerate(zip(cands.points, cands.values, cands.belief))]
    out += [option("frontier", n + 1 + j, xy, float(v), None)
            for j, (xy, v) in enumerate(zip(frontiers, frontier_values))]
    return tuple(out)


def _one(frontier: np.ndarray | None, value: float) -> tuple[np.ndarray, np.ndarray]:
    """The paper's single best frontier as the (F x 2 points, F values) the functions below take."""
    return (np.zeros((0, 2)), np.zeros(0)) if frontier is None else (frontier[None], np.array([value]))


def _greedy(cands: Candidates, frontier: np.ndarray | None, frontier_value: float) -> Decision:
    best = int(np.argmax(cands.values))
    options = _options(cands, *_one(frontier, frontier_value))
    if frontier is not None and frontier_value > cands.values[best]:
        return Decision(GoalKind.FRONTIER, *map(float, frontier), candidates=len(cands.points),
                        reason="greedy: the frontier's value beats every candidate's", options=options)
    return Decision(GoalKind.CANDIDATE, *map(float, cands.points[best]), candidates=len(cands.points),
                    reason="greedy: the highest-valued candidate", options=options)


def _plus(snapshot: MapSnapshot, robot_xy: tuple[float, float], remaining: Sequence[str],
          config: DecisionConfig, values: np.ndarray, grid: GridGeometry, frontiers: np.ndarray,
          cands: Candidates, allowed: Callable[[np.ndarray], np.ndarray]) -> Decision | None:
    """``ovamos-plus``'s step (services/planner/plus.py): the best ``plus.frontiers`` frontiers,
    each with a value-scaled bonus, and unconfirmed detections as candidates, into POUCT."""
    plus = config.plus
    if plus.verify_detections:
        cands = detection_candidates(snapshot.objects, remaining, cands, allowed, plus)
    scores = frontier_scores(frontiers, values, grid, config.candidates.frontier_radius_m) \
        if len(frontiers) else np.zeros(0)
    best = np.argsort(-scores, kind="stable")[:plus.frontiers]
    offered, offered_values = frontiers[best], scores[best]
    if len(cands.points) == 0 and not len(offered):
        return None
    bonuses = frontier_bonuses(offered_values, cands, plus, config.pomdp.lambda_frontier)
    return _pouct(cands, offered, offered_values, robot_xy, snapshot, config, bonuses)


def _pouct(cands: Candidates, frontiers: np.ndarray, frontier_values: np.ndarray,
           robot_xy: tuple[float, float], snapshot: MapSnapshot, config: DecisionConfig,
           bonuses: np.ndarray | None = None) -> Decision:
    """POUCT over the candidates and ``frontiers`` (the paper: at most one, with the fixed
    frontier bonus; ``bonuses``: one per frontier, ovamos-plus's many-frontier model)."""
    points = np.vstack([np.asarray(robot_xy, float)[None], cands.points.reshape(-1, 2), frontiers.reshape(-1, 2)])
    distances = ActionDistances(snapshot, config, include=points).matrix(points)
    n = len(cands.points)
    options = _options(cands, frontiers, frontier_values, distances)
    reachable = [i for i in range(1, n + 1) if np.isfinite(distances[0, i])]
    open_frontiers = [n + 1 + j for j in range(len(frontiers)) if np.isfinite(distances[0, n + 1 + j])]
    if not reachable and not open_frontiers:
        why = "no candidate and no frontier has a path: trying the "
        return Decision(GoalKind.FRONTIER, *map(float, frontiers[0]), reason=why + "frontier",
                        options=options) if len(frontiers) \
            else Decision(GoalKind.CANDIDATE, *map(float, cands.points[0]), candidates=n,
                          reason=why + "best candidate", options=options)
    if not reachable and bonuses is None:
        return Decision(GoalKind.FRONTIER, *map(float, points[open_frontiers[0]]), candidates=n,
                        reason="no candidate has a path: the frontier", options=options)
    c = config.pomdp
    finite = np.where(np.isfinite(distances), distances, 1e6)
    if bonuses is None:
        model: SearchPOMDP = SearchPOMDP(finite, reachable, open_frontiers[0] if open_frontiers else None, c)
    else:
        model = ManyFrontierPOMDP(finite, reachable, None, c,
                                  frontier_rewards={i: float(bonuses[i - n - 1]) for i in open_frontiers})
    # with no reachable candidate (ovamos-plus only) the target is nowhere the model knows of
    belief = cands.belief[[i - 1 for i in reachable]] if reachable else np.ones(1)
    planner = POUCT(model, num_sims=c.num_sims, max_depth=c.max_depth, discount=c.gamma,
                    exploration=c.exploration, seed=config.seed)
    action = planner.plan(root_particles(reachable or [0], belief / belief.sum(), c.particles, config.seed))
    kind = GoalKind.FRONTIER if action > n else GoalKind.CANDIDATE
    q = planner.action_values()
    value, visits = q[action]
    sims = planner.last_stats.sims if planner.last_stats else 0
    return Decision(kind, float(points[action][0]), float(points[action][1]), candidates=n,
                    reason=f"POUCT: the highest mean return (Q {value:.1f}, {visits} of {sims} simulations)",
                    options=_options(cands, frontiers, frontier_values, distances, q))
