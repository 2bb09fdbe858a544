"""Loop closure: a pose graph over keyframes that re-places the map when an old place is seen again.

Scan-to-map matching (:mod:`.localization`) keeps an error it once made: a run of frames it could
not trust (a wall closer than the camera's range while bumps turn the robot, a corridor) extends
the map in a turned frame, and later scans agree with that. So every ``keyframe_m`` or
``keyframe_deg`` of the camera's travel in the map, the frame's obstacle points, in the camera's
own frame, are kept with its pose as a node of a pose graph (GTSAM's ``Pose2``). Consecutive
keyframes are tied by the motion the localizer gave them. A keyframe that stands within
``radius_m`` of keyframes at least ``gap`` keyframes older is matched against a map drawn from
those old keyframes alone, which the recent error has not touched; an accepted match ties it to
the nearest of them, under a Cauchy kernel so that a wrong tie is outvoted by the right ones. When
the tie disagrees with where the keyframe stands, the graph is solved (Levenberg-Marquardt) and the
map's obstacles are drawn again from every keyframe at its solved pose. A solution that would move
the robot by more than ``max_shift_m`` / ``max_shift_deg`` is refused and its tie dropped: one match
never throws the map away. Why GTSAM: docs/method.md (#loop-closure).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ovamos.services.mapping.localization import LocalizationConfig, Localizer, ObstaclePoints, mark_obstacles
from ovamos.shared.grid import GridGeometry
from ovamos.shared.motion import Pose, wrap_angle

__all__ = ["Keyframe", "LoopCloser", "LoopConfig"]


class LoopConfig(BaseModel):
    """When a keyframe is kept, when an old place counts as seen again, how far a closure may move
    the map. Applies while the map localizes by scan (``[localization] enabled``, ``source = "scan"``)."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(default=False, description="close loops while the map localizes by scan (needs "
                          "ovamos[slam]; off: scan-to-map matching alone, which measured as well: "
                          "docs/method.md#loop-closure)")
    keyframe_m: float = Field(default=0.3, gt=0, description="a keyframe every this much of the camera's "
                              "travel in the map ...")
    keyframe_deg: float = Field(default=25.0, gt=0, description="... or of its turning")
    keyframe_points: int = Field(default=1500, ge=10, description="obstacle points kept per keyframe (an "
                                 "even sample)")
    max_keyframes: int = Field(default=3000, ge=2, description="no keyframe beyond this many (counted "
                               "keyframes_full): about 12 kB each")
    gap: int = Field(default=20, ge=2, description="keyframes this many or more older count as an old place")
    radius_m: float = Field(default=2.0, gt=0, description="a keyframe this near an old one is matched "
                            "against the old ones")
    submap_m: float = Field(default=4.0, gt=0, description="the old keyframes within this of it make the "
                            "map it is matched against")
    submap_keyframes: int = Field(default=40, ge=1, description="at most this many of them, the nearest (what "
                                  "a check costs)")
    min_inlier_ratio: float = Field(default=0.7, ge=0, le=1, description="fewer of its points on the old "
                                    "map's obstacles: no tie")
    search_m: float = Field(default=0.3, gt=0, description="how far from where the keyframe stands the match "
                            "looks (odometry's spread in its prior) ...")
    search_deg: float = Field(default=8.0, gt=0, description="... and how far turned")
    sequence_sigma_m: float = Field(default=0.02, gt=0, description="how far the localizer's motion between "
                                    "two keyframes may be off when it matched every frame between them ...")
    sequence_sigma_deg: float = Field(default=0.5, gt=0)
    unmatched_sigma_m: float = Field(default=0.1, gt=0, description="... and when it refused one (odometry's "
                                     "word alone: a bump may have turned the robot unseen)")
    unmatched_sigma_deg: float = Field(default=5.0, gt=0)
    loop_sigma_m: float = Field(default=0.03, gt=0, description="how far a tie to an old keyframe may be off ...")
    loop_sigma_deg: float = Field(default=1.0, gt=0)
    agree_m: float = Field(default=0.05, ge=0, description="a tie within this of where the keyframe stands "
                           "agrees: kept in the graph, nothing solved ...")
    agree_deg: float = Field(default=1.5, ge=0)
    confirmations: int = Field(default=2, ge=1, description="ties of this many consecutive keyframes, each "
                               "within agree_m / agree_deg of the one before, before the map is moved")
    max_shift_m: float = Field(default=0.5, gt=0, description="a solution moving the robot farther than this "
                               "is refused and its tie dropped ...")
    max_shift_deg: float = Field(default=15.0, gt=0)


@dataclass(frozen=True)
class _Tie:
    """A keyframe's match against the old keyframes: how far (map xy, m) and by how much (rad) it
    would move the keyframe, and the graph's factor saying so."""

    keyframe: int
    shift: np.ndarray
    turn: float
    factor: Any

    def within(self, metres: float, degrees: float) -> bool:
        return float(np.hypot(*self.shift)) <= metres and abs(math.degrees(self.turn)) <= degrees

    def agrees(self, other: _Tie, metres: float, degrees: float) -> bool:
        return (float(np.hypot(*(self.shift - other.shift))) <= metres
                and abs(math.degrees(wrap_angle(self.turn - other.turn))) <= degrees)


@dataclass(frozen=True)
class Keyframe:
    """One node: where odometry and the map had the camera, and its obstacle points (N x 2, float32)
    in the camera's own planar frame."""

    odom: Pose
    pose: Pose
    points: np.ndarray


class LoopCloser:
    """The keyframes of one map and their pose graph. :meth:`add` takes every placed frame and says
    when the graph was solved (the map's obstacles are then to be drawn again from :attr:`keyframes`)."""

    def __init__(self, config: LoopConfig, matching: LocalizationConfig, grid: GridGeometry,
                 counters: Counter[str]) -> None:
        try:
            import gtsam  # the slam extra's; imported where loops close, as evo is where errors are computed
        except ImportError as exc:
            raise RuntimeError("[loops] enabled needs GTSAM: pip install 'ovamos[slam]'") from exc

        self.config, self.grid, self.counters = config, grid, counters
        self._gtsam = gtsam
        self._matching = matching.model_copy(update={
            "odometry_sigma_m": config.search_m, "odometry_sigma_deg": config.search_deg,
            "odometry_sigma_per_m": 0.0, "odometry_sigma_deg_per_m": 0.0, "odometry_sigma_deg_per_turn_deg": 0.0,
            "coarse_m": max(matching.coarse_m, config.search_m),
            "max_step_m": 2 * config.search_m, "max_step_deg": 2 * config.search_deg})
        self.keyframes: list[Keyframe] = []
        self._pending: list[_Tie] = []  # ties of consecutive keyframes that would move the map alike
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        diagonal = gtsam.noiseModel.Diagonal.Sigmas
        self._sequence = diagonal(np.array([config.sequence_sigma_m, config.sequence_sigma_m,
                                            math.radians(config.sequence_sigma_deg)]))
        self._unmatched = diagonal(np.array([config.unmatched_sigma_m, config.unmatched_sigma_m,
                                             math.radians(config.unmatched_sigma_deg)]))
        self._refused = False  # a frame since the last keyframe was not matched
        self._loop = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(1.0),
            diagonal(np.array([config.loop_sigma_m, config.loop_sigma_m, math.radians(config.loop_sigma_deg)])))

    def add(self, odom: Pose, pose: Pose, obstacles: np.ndarray, matched: bool) -> Pose | None:
        """A frame placed at ``pose`` in the map (the camera's; ``odom``: where odometry had it) with
        its ``obstacles`` (N x 2 map xy); ``matched``: whether the localizer's match placed it. When it
        makes a keyframe that closes a loop and the graph is solved: the new ``map_T_odom``, else None."""
        c = self.config
        self._refused |= not matched
        if self.keyframes:
            last = self.keyframes[-1].pose
            if (math.hypot(pose.x - last.x, pose.y - last.y) < c.keyframe_m
                    and abs(math.degrees(wrap_angle(pose.yaw - last.yaw))) < c.keyframe_deg):
                return None
        if len(self.keyframes) >= c.max_keyframes:
            self.counters["keyframes_full"] += 1
            return None
        if len(obstacles) > c.keyframe_points:
            obstacles = obstacles[np.linspace(0, len(obstacles) - 1, c.keyframe_points).astype(np.int64)]
        k = len(self.keyframes)
        self.keyframes.append(Keyframe(odom, pose, pose.inverse().apply_points(obstacles).astype(np.float32)))
        self.counters["keyframes"] += 1
        g = self._gtsam
        self._values.insert(k, _pose2(g, pose))
        if k == 0:
            self._graph.add(g.PriorFactorPose2(0, _pose2(g, pose), g.noiseModel.Diagonal.Sigmas(np.full(3, 1e-3))))
            return None
        previous = self.keyframes[k - 1].pose
        noise = self._unmatched if self._refused else self._sequence
        self._graph.add(g.BetweenFactorPose2(k - 1, k, _pose2(g, previous).between(_pose2(g, pose)), noise))
        self._refused = False
        return self._close(k, obstacles)

    def _close(self, k: int, obstacles: np.ndarray) -> Pose | None:
        c, pose = self.config, self.keyframes[k].pose
        old = [j for j in range(k - c.gap + 1) if _distance(self.keyframes[j].pose, pose) < c.radius_m]
        if not old:
            return None
        self.counters["loop_tried"] += 1
        match = self._match(k, obstacles)
        if match is None:
            return None
        seen = match.compose(pose)
        nearest = min(old, key=lambda j: _distance(self.keyframes[j].pose, pose))
        g = self._gtsam
        tie = _Tie(k, np.array([seen.x - pose.x, seen.y - pose.y]), match.yaw,
                   g.BetweenFactorPose2(nearest, k, _pose2(g, self.keyframes[nearest].pose).between(_pose2(g, seen)),
                                        self._loop))
        if tie.within(c.agree_m, c.agree_deg):
            self._graph.add(tie.factor)  # it agrees: kept for later solutions, nothing to move now
            self.counters["loop_closed"] += 1
            return None
        # a tie that moves the map waits for the next keyframes' to say the same: one match of a
        # few old keyframes can be off by a decimetre
        last = self._pending[-1] if self._pending else None
        if last is None or last.keyframe != k - 1 or not tie.agrees(last, c.agree_m, c.agree_deg):
            self._pending = []
        self._pending.append(tie)
        if len(self._pending) < c.confirmations:
            self.counters["loop_unconfirmed"] += 1
            return None
        ties, self._pending = self._pending, []
        size = self._graph.size()
        for each in ties:
            self._graph.add(each.factor)
        solved = g.LevenbergMarquardtOptimizer(self._graph, self._values).optimize()
        moved = _pose(solved.atPose2(k))
        if (_distance(moved, pose) > c.max_shift_m
                or abs(math.degrees(wrap_angle(moved.yaw - pose.yaw))) > c.max_shift_deg):
            self._graph.resize(size)
            self.counters["loop_refused"] += 1
            return None
        self.counters["loop_closed"] += len(ties)
        self._values = solved
        self.keyframes = [Keyframe(kf.odom, _pose(solved.atPose2(i)), kf.points) for i, kf in enumerate(self.keyframes)]
        self.counters["loop_solved"] += 1
        return moved.compose(self.keyframes[k].odom.inverse())

    def _match(self, k: int, obstacles: np.ndarray) -> Pose | None:
        """Keyframe ``k``'s points matched against a map of the keyframes at least ``gap`` older
        within ``submap_m``: the correction (map frame) that puts it there, or None when the match
        is refused or cut by its bound."""
        c, pose, grid = self.config, self.keyframes[k].pose, self.grid
        reach = c.submap_m + c.search_m
        r0, c0 = grid.to_cell(pose.x - reach, pose.y - reach)
        r1, c1 = grid.to_cell(pose.x + reach, pose.y + reach)
        r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1 + 1, grid.rows), min(c1 + 1, grid.cols)
        if r1 - r0 < 2 or c1 - c0 < 2:
            return None
        window = GridGeometry(grid.resolution, grid.x0 + c0 * grid.resolution, grid.y0 + r0 * grid.resolution,
                              r1 - r0, c1 - c0)
        obstacle = np.zeros(window.shape, bool)
        cells = ObstaclePoints(window)
        old = [kf for kf in self.keyframes[:k - c.gap + 1] if _distance(kf.pose, pose) <= c.submap_m]
        for kf in sorted(old, key=lambda kf: _distance(kf.pose, pose))[:c.submap_keyframes]:
            mark_obstacles(kf.pose.apply_points(kf.points), window, obstacle, cells)
        # the old keyframes saw the floor by their walls: a point elsewhere was out of their view
        explored = cv2.dilate(obstacle.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        localizer = Localizer(self._matching)
        found = localizer.match(obstacles, (pose.x, pose.y), obstacle, explored, cells, pose)
        if not found.accepted or found.clamped or found.inlier_ratio < c.min_inlier_ratio:
            return None
        return found.correction

    def draw(self, obstacle: np.ndarray, cells: ObstaclePoints) -> None:
        """Every keyframe's points at its pose onto ``obstacle`` (the map's grid) and ``cells``."""
        for kf in self.keyframes:
            mark_obstacles(kf.pose.apply_points(kf.points), self.grid, obstacle, cells)


def _distance(a: Pose, b: Pose) -> float:
    return math.hypot(a.x - b.x, a.y - b.y)


def _pose2(gtsam: Any, pose: Pose) -> Any:
    return gtsam.Pose2(pose.x, pose.y, pose.yaw)


def _pose(value: Any) -> Pose:
    return Pose(x=float(value.x()), y=float(value.y()), yaw=wrap_angle(float(value.theta())))
