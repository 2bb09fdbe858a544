"""Continuous motion: the agent's navigation steps become path commands the robot drives without stopping.

Stepwise (the paper's, the default) every step is one primitive and the robot stands still while
the frame taken after it is perceived, fused and decided on. Continuous, a navigation step sends
the navigator's remaining path to the goal instead; the robot follows it closed-loop on odometry
while frames free-run into the map, and the agent is asked again (the step booked with the ground
covered so far) when one of :meth:`Redecision.due`'s events happens (a target confirmed, at the
object, the path walled off, a much better frontier) or ``decide_every_s`` has passed, never
waiting for the robot to stop. The path goes with the mapped obstacles near it
(:func:`obstacles_near`): the robot has no map, and its follower slows near them. Within
``careful_steps`` of a bump a step is a primitive, which the navigator checks against the bump
cell by cell, or, with ``careful_path_m`` set, a careful path (:func:`careful_path`: short, slow,
the bumps named, and only where it keeps the footprint off every bump). Every other step (the
look-around, a turn with nowhere to go, ovamos-plus's check turns, the STOP beside a found object)
stays a primitive, so a found target still ends with the robot within its STOP distance and a STOP;
but a turn's next step is decided before the turn ends (:func:`turn_ahead`), so a look-around or a
run of idle turns is one rotation the base chains turn by turn while frames free-run, and no step
after a turn waits for a decision with the robot standing.

A step is then a decision tick: ``decide_every_s`` defaults to about the time a MOVE_FORWARD's
0.25 m takes at a TurtleBot's top speed, so the agent's step-counted rules (re-decide every 4,
stuck after 10, the task's step limit) keep roughly their stepwise meaning in ground covered.
Both the planner's executive (over Zenoh) and the benchmark's simulated-time episodes use this
module, so they drive the same way.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ovamos.services.planner.agent import AgentConfig, Reason, SearchAgent, Step
from ovamos.services.planner.candidates import frontier_scores
from ovamos.services.planner.decide import GoalKind, decision_values, explored_window
from ovamos.services.planner.navigator import NavMap
from ovamos.shared.grid import GridGeometry, disc
from ovamos.shared.messages import MAX_PATH_OBSTACLES, MAX_PATH_POINTS, MapSnapshot
from ovamos.shared.motion import Action, Pose, wrap_angle
from ovamos.shared.robot import ROBOT

Point = tuple[float, float]

CLEARANCE_SAMPLE_M = 0.025
"""How finely a path is sampled where its distance to a point is checked (half a map cell)."""

PERIOD = "period"
""":meth:`Redecision.due`'s answer when only ``decide_every_s`` has passed (no event)."""


@dataclass(frozen=True)
class PathStep:
    """A navigation step as a path command's content (in the map frame), and when it is to be
    decided on again."""

    path: tuple[Point, ...]
    obstacles: tuple[Point, ...]
    redecision: Redecision
    speed_m_s: float | None = None  # a careful path's top speed (None: the base's)

    @property
    def careful(self) -> bool:
        return self.speed_m_s is not None

    def in_odom(self, to_odom: Callable[[tuple[Point, ...]], tuple[Point, ...]]) -> dict[str, Any]:
        """The :class:`PlanCommand` fields of this path in the base's odometry frame (``to_odom``
        converts map points: the base follows in its own frame)."""
        return {"path": to_odom(self.path), "obstacles": to_odom(self.obstacles), "speed_m_s": self.speed_m_s}


def path_step(agent: SearchAgent, step: Step, snapshot: MapSnapshot, pose: Pose, now: float) -> PathStep | None:
    """``step`` as a path to send (None: it stays a primitive, see :func:`path_for`), with the mapped
    obstacles near it (``tell_obstacles_m``; a careful path's bumps first) and its :class:`Redecision`."""
    planned = path_for(agent, step, pose)
    if planned is None:
        return None
    path, careful = planned
    config, remaining = agent.config, agent.task.remaining
    obstacles = obstacles_near(snapshot, path, pose, config.tell_obstacles_m)
    if careful:
        bumps = _near(agent.bumps.points(agent.task.steps), path, pose, config.tell_obstacles_m + ROBOT.radius_m)
        obstacles = (*bumps, *obstacles)[:MAX_PATH_OBSTACLES]
    return PathStep(path, obstacles, Redecision.start(step, now, snapshot, pose, path, remaining, config),
                    config.careful_m_s if careful else None)


def path_for(agent: SearchAgent, step: Step, pose: Pose) -> tuple[tuple[Point, ...], bool] | None:
    """The path to send for ``step`` (the navigator's remaining path, as of the decision just made)
    and whether it is a careful one (within ``careful_steps`` of a bump: :func:`careful_path`), or
    None when the step stays a primitive (anything but navigating towards a goal, and a careful
    step whose path would come too close to a bump)."""
    if step.reason is not Reason.NAVIGATE:
        return None
    points = agent.navigator.path
    if len(points) == 0:
        return None
    path = _rounded(points[:MAX_PATH_POINTS])
    since = agent.bumps.since(agent.task.steps)
    if since is None or since >= agent.config.careful_steps:
        return path, False
    careful = careful_path(path, pose, agent.bumps.points(agent.task.steps), agent.config)
    return None if careful is None else (careful, True)


def careful_path(path: Sequence[Point], pose: Pose, bumps: Sequence[Point], config: AgentConfig
                 ) -> tuple[Point, ...] | None:
    """The first ``careful_path_m`` of ``path``, from the robot's place on, or None where driving it would bring the
    footprint within ``careful_clearance_m`` of a bump (or nearer one than the robot stands now; the
    navigator's map grows bumps for this, :meth:`SearchAgent._nav_map`) or careful paths are off
    (``careful_path_m`` 0, the default)."""
    if config.careful_path_m == 0:
        return None
    cut = _cut(np.array([(pose.x, pose.y), *path], float), config.careful_path_m)
    if bumps:
        xy = np.array(bumps, float)
        # a bump the robot already stands nearer to (it marks a point of the obstacle, not its face)
        # may not come nearer; half a cell for the grid the navigator keeps the clearance on
        now = np.hypot(xy[:, 0] - pose.x, xy[:, 1] - pose.y)
        keep = np.minimum(ROBOT.radius_m + config.careful_clearance_m - CLEARANCE_SAMPLE_M, now - 1e-3)
        if (_gaps(xy, _sampled(cut, CLEARANCE_SAMPLE_M)) < keep).any():
            return None
    # from where the robot stands: its follower then drives the first leg as planned (turning in
    # place first where it heads elsewhere) rather than an arc to a point further on, which cuts
    # toward what it bumped
    return _rounded(cut)


def _rounded(points: Sequence[Sequence[float]] | np.ndarray) -> tuple[Point, ...]:
    """Waypoints as a command carries them: to 0.1 mm."""
    return tuple((round(float(x), 4), round(float(y), 4)) for x, y in points)


def _cut(polyline: np.ndarray, length: float) -> np.ndarray:
    """``polyline`` (K x 2) up to ``length`` along it (its last vertex where it is shorter)."""
    out, left = [polyline[0]], length
    for a, b in zip(polyline[:-1], polyline[1:]):
        step = float(np.hypot(*(b - a)))
        if step >= left:
            out.append(a + (b - a) * (left / step if step else 0.0))
            break
        out.append(b)
        left -= step
    return np.array(out)


def _gaps(points: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Each of ``points``' (N x 2) distance to the nearest of ``samples`` (M x 2)."""
    return np.hypot(points[:, None, 0] - samples[None, :, 0], points[:, None, 1] - samples[None, :, 1]).min(axis=1)


def _near(points: Sequence[Point], path: Sequence[Point], pose: Pose, within_m: float) -> tuple[Point, ...]:
    """``points`` within ``within_m`` of the path from the robot on, nearest the robot first."""
    if not points:
        return ()
    xy = np.array(points, float)
    gaps = _gaps(xy, _sampled(np.array([(pose.x, pose.y), *path], float), CLEARANCE_SAMPLE_M))
    order = np.argsort(np.hypot(xy[:, 0] - pose.x, xy[:, 1] - pose.y), kind="stable")
    return tuple((round(float(xy[i, 0]), 3), round(float(xy[i, 1]), 3)) for i in order if gaps[i] <= within_m)


def obstacles_near(snapshot: MapSnapshot, path: Sequence[Point], pose: Pose, within_m: float
                   ) -> tuple[Point, ...]:
    """The mapped obstacles within ``within_m`` (and a cell: ``GridGeometry.band``) of the path
    from the robot on, one point per ``2 x 2`` cells that hold one (their obstacle cells' mean),
    nearest the robot first, at most :data:`MAX_PATH_OBSTACLES` (the near ones matter first: the
    path is sent again within a second)."""
    if within_m <= 0 or not path:
        return ()
    res, (ox, oy), obstacle = snapshot.resolution, snapshot.origin, snapshot.obstacle
    points = np.array([(pose.x, pose.y), *path], float)
    lo = np.floor((points.min(axis=0) - within_m - (ox, oy)) / res).astype(int)
    hi = np.ceil((points.max(axis=0) + within_m - (ox, oy)) / res).astype(int) + 1
    c0, r0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
    c1, r1 = min(int(hi[0]), obstacle.shape[1]), min(int(hi[1]), obstacle.shape[0])
    if c1 <= c0 or r1 <= r0:
        return ()
    crop = obstacle[r0:r1, c0:c1]
    if not crop.any():
        return ()
    window = GridGeometry(res, ox + c0 * res, oy + r0 * res, r1 - r0, c1 - c0)
    rows, cols = np.nonzero(crop & window.band(points, math.ceil(within_m / res)))
    if not len(rows):
        return ()
    blocks = (rows // 2) * (crop.shape[1] // 2 + 1) + cols // 2
    _, inverse = np.unique(blocks, return_inverse=True)
    x = np.bincount(inverse, ox + (c0 + cols + 0.5) * res) / np.bincount(inverse)
    y = np.bincount(inverse, oy + (r0 + rows + 0.5) * res) / np.bincount(inverse)
    order = np.argsort(np.hypot(x - pose.x, y - pose.y), kind="stable")[:MAX_PATH_OBSTACLES]
    return tuple((round(float(x[i]), 3), round(float(y[i]), 3)) for i in order)


def turn_ahead(sent: Action | None, decided_at: Pose, pose: Pose, config: AgentConfig) -> Pose | None:
    """Where the turn primitive ``sent`` (decided at ``decided_at``, the robot at ``pose`` now) will
    end, once it is within ``turn_ahead_deg`` of its heading; None before, or for a command that is no
    turn (a path, even one that begins by turning). The next step is decided then, for that pose, on
    the newest map: a further turn the same way goes at once (the base chains it, turning on without
    stopping), anything else when the turn ends (:func:`chains`)."""
    if sent is None or not sent.turn_sign or config.turn_ahead_deg == 0:
        return None
    goal = wrap_angle(decided_at.yaw + sent.turn_sign * math.radians(config.primitives.turn_deg))
    if abs(wrap_angle(goal - pose.yaw)) > math.radians(config.turn_ahead_deg):
        return None
    return Pose(x=pose.x, y=pose.y, yaw=goal)


def chains(sent: Action | None, step: Step, drive: PathStep | None) -> bool:
    """Whether ``step``, decided ahead of the end of the turn ``sent``, goes at once: a turn the same
    way, sent as a primitive, which the base chains onto the running one."""
    return drive is None and sent is not None and bool(sent.turn_sign) and step.action is sent


def booked_step(step: Step, path: bool, blocked: bool, decided_at: Pose, now: Pose) -> tuple[Step, Pose]:
    """What the agent books for ``step`` and from where: a blocked path as a blocked MOVE_FORWARD
    from where the robot stopped (the bump is ahead of it there, not of where the path began)."""
    if path and blocked:
        return Step(Action.MOVE_FORWARD, Reason.NAVIGATE, step.goal), now
    return step, decided_at


@dataclass(frozen=True)
class PathWatch:
    """The path sent, sampled every half cell, and which samples lay clear of the map's obstacles
    (by the navigator's radius: where its plans may go) at the decision: a sample ahead of the
    robot that a newer map blocks means the path has been walled off (the goal may have become
    unreachable)."""

    samples: np.ndarray  # N x 2 world xy, from the robot on
    clear: np.ndarray    # N bool, at the decision

    @classmethod
    def start(cls, path: Sequence[Point], pose: Pose, snapshot: MapSnapshot, radius: float) -> PathWatch:
        samples = _sampled(np.array([(pose.x, pose.y), *path], float), snapshot.resolution / 2)
        return cls(samples, ~_blocked(snapshot, samples, radius))

    def walled_off(self, snapshot: MapSnapshot, pose: Pose, radius: float) -> bool:
        """Whether a sample from the one nearest the robot on, clear at the decision, is blocked now."""
        here = int(np.argmin(np.hypot(self.samples[:, 0] - pose.x, self.samples[:, 1] - pose.y)))
        ahead = self.samples[here:]
        return bool((self.clear[here:] & _blocked(snapshot, ahead, radius)).any())


def _sampled(polyline: np.ndarray, spacing: float) -> np.ndarray:
    """Points along ``polyline`` (K x 2) at most ``spacing`` apart, its vertices included."""
    out = [polyline[:1]]
    for a, b in zip(polyline[:-1], polyline[1:]):
        n = max(1, math.ceil(float(np.hypot(*(b - a))) / spacing))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.vstack(out)


def _blocked(snapshot: MapSnapshot, xy: np.ndarray, radius: float) -> np.ndarray:
    """For each point, whether an obstacle cell lies within ``radius`` of it (off the grid: no): the
    footprint disc the navigator inflates obstacles by, so a point is clear where it may plan."""
    nav = NavMap.from_snapshot(snapshot)
    grid = nav.grid
    kernel = disc(radius, grid.resolution)
    dr, dc = np.nonzero(kernel)
    r = kernel.shape[0] // 2
    centre_rows, centre_cols = grid.to_cell(xy[:, 0], xy[:, 1])
    rows, cols = centre_rows[:, None] + (dr - r), centre_cols[:, None] + (dc - r)
    inside = (rows >= 0) & (rows < grid.rows) & (cols >= 0) & (cols < grid.cols)
    hit = np.zeros(rows.shape, bool)
    hit[inside] = nav.obstacle[rows[inside], cols[inside]]
    return hit.any(axis=1)


def best_frontier_score(snapshot: MapSnapshot, remaining: list[str], config: AgentConfig) -> float:
    """The highest frontier score (the value map's best within the frontier radius) of the map for
    the policy's targets, as the decision step ranks frontiers; 0 with no frontier or no values."""
    if not len(snapshot.frontiers):
        return 0.0
    rows, cols, grid = explored_window(snapshot)
    decision = config.decision
    values = decision_values(snapshot, decision.chosen.targets(remaining), decision, (rows, cols))
    if values is None:
        return 0.0
    return float(frontier_scores(snapshot.frontiers, values, grid, decision.candidates.frontier_radius_m).max())


@dataclass
class Redecision:
    """When a path in flight is decided on again: what the map and the robot showed at the decision,
    compared with now."""

    step: Step
    decided_at: float
    confirmed: Counter[str]  # the remaining targets' confirmed objects, by label
    watch: PathWatch
    frontier_then: float | None  # the best frontier's score at the decision (a frontier goal's only)

    @classmethod
    def start(cls, step: Step, now: float, snapshot: MapSnapshot, pose: Pose, path: Sequence[Point],
              remaining: list[str], config: AgentConfig) -> Redecision:
        goal = step.goal
        frontier = goal is not None and goal.kind is GoalKind.FRONTIER
        return cls(step, now, _confirmed(snapshot, remaining),
                   PathWatch.start(path, pose, snapshot, config.navigation.robot_radius),
                   best_frontier_score(snapshot, remaining, config) if frontier else None)

    def due(self, now: float, snapshot: MapSnapshot, pose: Pose, remaining: list[str], config: AgentConfig
            ) -> str | None:
        """Why to decide again now (None: keep following): a remaining target confirmed since (it
        may be worth a detour), within STOP distance of the object the path goes to (STOP there,
        not at the path's end), the decision period passed (the map has grown), the path ahead
        walled off by what the map has seen since (re-planned or given up at once, not driven
        into), or, going to a frontier, a frontier scoring ``better_frontier`` above the best one
        at the decision (the cheap events first)."""
        if _confirmed(snapshot, remaining) - self.confirmed:  # (positions are refined: counted, not compared)
            return "a target confirmed"
        goal = self.step.goal
        if goal is not None and goal.kind is GoalKind.OBJECT \
                and math.hypot(goal.x - pose.x, goal.y - pose.y) <= config.object_stop_m:
            return "at the object"
        if now - self.decided_at >= config.decide_every_s:
            return PERIOD
        if self.watch.walled_off(snapshot, pose, config.navigation.robot_radius):
            return "the path walled off"
        if self.frontier_then is not None \
                and best_frontier_score(snapshot, remaining, config) >= self.frontier_then + config.better_frontier:
            return "a better frontier"
        return None


def _confirmed(snapshot: MapSnapshot, remaining: list[str]) -> Counter[str]:
    return Counter(o.label for o in snapshot.objects if o.confirmed and o.label in remaining)
