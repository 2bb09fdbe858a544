"""The map: obstacles, explored area, per target a value layer with its update counts and the
area searched for it, objects.

Each frame touches only the cells inside its field of view (a window around
the view polygon), so an update costs what the frame sees, not the grid size.

What is per target and why: the map outlives a task, so a later task's target meets a house
explored for other targets. Its cells were never looked at for it: counting those views would
decay its first readings to nothing (the paper's decay is of places looked at *for the target*
without success), and frontiers of the whole explored area would leave it nowhere to explore.
So each layer counts its own views and keeps its own searched area, and frontiers are those of
the area searched for every remaining target (docs/notes/repeated-tasks.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TypedDict

import cv2
import numpy as np

from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.layers import fov_confidence, fuse
from ovamos.services.mapping.localization import Localizer, ObstaclePoints, mark_obstacles
from ovamos.services.mapping.loops import LoopCloser
from ovamos.services.mapping.objects import ObjectMap
from ovamos.services.mapping.projection import View, placed, planar_pose, project
from ovamos.shared.detections import Detection
from ovamos.shared.grid import GridGeometry, inflate
from ovamos.shared.messages import MapSnapshot, PerceptionResult, RgbdFrame
from ovamos.shared.motion import IDENTITY, Pose


class MapState:
    """One map, of one odometry session (``odom_session``: the frames it fuses are posed in it).

    A frame counts once: obstacles, explored area and update counts take each frame (seq and
    stamp) once, however often it arrives (a camera re-publishes its latest frame while the
    robot stands still, and the decay must not grow then). A second perception result for a
    fused frame (re-scored for targets added since) adds the values and objects of the targets
    the frame was not fused for yet, and nothing else.
    """

    def __init__(self, config: MappingConfig | None = None, targets: Sequence[str] = (),
                 odom_session: str = "") -> None:
        self.config = c = config or MappingConfig()
        self.odom_session = odom_session
        half = c.grid_cells * c.resolution / 2
        self.grid = GridGeometry(c.resolution, c.center[0] - half, c.center[1] - half,
                                 c.grid_cells, c.grid_cells)
        self.obstacle = np.zeros(self.grid.shape, bool)
        self.explored = np.zeros(self.grid.shape, bool)
        self.values: dict[str, np.ndarray] = {}
        self.confidence: dict[str, np.ndarray] = {}
        self.counts: dict[str, np.ndarray] = {}    # per layer: frames that saw each cell for it
        self.searched: dict[str, np.ndarray] = {}  # per layer: cells seen in a frame scored for it
        self.objects = ObjectMap(c.object_merge_distance_m, c.object_confirm_hits, c.decision_threshold,
                                 **_evidence(c))
        self.localizer = Localizer(c.localization) if c.localization.enabled else None
        self.obstacle_points = ObstaclePoints(self.grid) if self.localizer is not None else None
        self.loops = (LoopCloser(c.loops, c.localization, self.grid, self.localizer.counters)
                      if self.localizer is not None and c.localization.source == "scan" and c.loops.enabled
                      else None)
        # what the keyframes did not draw (a resumed map's): kept when obstacles are drawn again
        self._obstacle_base = np.zeros(self.grid.shape, bool) if self.loops is not None else None
        self.seq = -1
        self.after_action = 0  # newest RgbdFrame.after_action fused: the map's causal freshness
        # bounding box (row0, row1, col0, col1) of everything explored: frontier search stays in it
        self._bbox: tuple[int, int, int, int] | None = None
        # (seq, stamp) of the newest fused frames -> the targets their values were fused for, and
        # the frame as it was placed in the map (a second result is fused where the first was)
        self._fused: dict[tuple[int, float], tuple[set[str], RgbdFrame]] = {}
        for target in targets:
            self.add_layer(target)

    # -- targets ------------------------------------------------------------------------------
    @property
    def layers(self) -> tuple[str, ...]:
        return tuple(self.values)

    def add_layer(self, target: str) -> None:
        """Start a value layer for a new target (no-op if it exists)."""
        if target not in self.values:
            self.values[target] = np.zeros(self.grid.shape, np.float32)
            self.confidence[target] = np.zeros(self.grid.shape, np.float32)
            self.counts[target] = np.zeros(self.grid.shape, np.uint16)
            self.searched[target] = np.zeros(self.grid.shape, bool)

    def remove_layer(self, target: str) -> None:
        """Drop a target's layer (found, or removed from the task) with its counts and area."""
        for grids in (self.values, self.confidence, self.counts, self.searched):
            grids.pop(target, None)

    # -- integration --------------------------------------------------------------------------
    def apply(self, frame: RgbdFrame, result: PerceptionResult | None = None) -> bool:
        """Fuse a frame with its perception result; the layers follow the result's target list
        (a found or removed target's layer goes, a new one starts), so no other message is needed.
        A frame fused before adds only the values of targets it was not fused for (see the class).
        Whether anything was fused."""
        scores, detections = None, []
        if result is not None:
            for target in set(self.layers) - set(result.targets):
                self.remove_layer(target)
            for target in result.targets:
                self.add_layer(target)
            scores, detections = result.score_map(), result.detections()
        fused = self._fused.get((frame.seq, frame.stamp))
        if fused is None:
            self.integrate(frame, scores, detections)
            return True
        targets, placed = fused
        new = {t: s for t, s in (scores or {}).items() if t not in targets}
        if new:
            window, seen, confidence = self._confidence(self._project(placed))
            self._fuse_evidence(placed, window, seen, confidence, new, [d for d in detections if d.label in new])
            targets.update(new)
        return bool(new)

    def has_fused(self, frame: RgbdFrame) -> bool:
        """Whether ``frame`` (its seq and stamp) is one of the newest ``remember_frames`` fused."""
        return (frame.seq, frame.stamp) in self._fused

    def integrate(self, frame: RgbdFrame, scores: Mapping[str, float] | None = None,
                  detections: Sequence[Detection] = ()) -> None:
        """Fuse one frame: obstacles and explored area always; values, their update counts and
        searched area, and objects when given. The frame is posed by odometry; it is fused where
        :meth:`place` puts it in the map."""
        frame, view = self.place(frame)
        self._mark_obstacles(view)
        window, seen, confidence = self._confidence(view)
        if window is not None:
            rows, cols = window
            self.explored[rows, cols] |= seen
            self._grow_bbox(rows, cols)
        self._fuse_evidence(frame, window, seen, confidence, scores, detections)
        self.seq = max(self.seq, frame.seq)
        self.after_action = max(self.after_action, frame.after_action)
        self._fused[(frame.seq, frame.stamp)] = (set(scores or ()), frame)
        for key in list(self._fused)[:max(0, len(self._fused) - self.config.remember_frames)]:
            del self._fused[key]

    def _fuse_evidence(self, frame: RgbdFrame, window: tuple[slice, slice] | None, seen: np.ndarray,
                       confidence: np.ndarray, scores: Mapping[str, float] | None,
                       detections: Sequence[Detection]) -> None:
        """The value layers (with their counts and searched area) and objects of ``scores``'
        targets from one frame."""
        if window is not None:
            rows, cols = window
            counted = (confidence > 0).astype(np.uint16)
            for target, score in (scores or {}).items():
                if target in self.values:
                    v, conf = self.values[target][rows, cols], self.confidence[target][rows, cols]
                    self.values[target][rows, cols], self.confidence[target][rows, cols] = \
                        fuse(v, conf, float(score), confidence)
                    counts = self.counts[target][rows, cols]
                    np.add(counts, counted, out=counts, where=counts < np.iinfo(np.uint16).max)
                    self.searched[target][rows, cols] |= seen
        if scores is not None:  # the frame was searched for these targets: views count
            self.objects.observe(frame, [t for t in scores if t in self.values])
        if detections:
            self.objects.add([d for d in detections if d.label in self.values], frame)

    @property
    def map_T_odom(self) -> Pose:
        """Where the odometry frame lies in the map (identity without localization)."""
        return IDENTITY if self.localizer is None else self.localizer.map_T_odom

    def place(self, frame: RgbdFrame) -> tuple[RgbdFrame, View]:
        """``frame`` (posed by odometry) placed in the map, with its view: by ``map_T_odom``, then
        by the localizer's match of its scan against the map, or as the base's own localization
        has it (:mod:`.localization`)."""
        if self.localizer is None:
            return frame, self._project(frame)
        odom = planar_pose(frame)
        if self.config.localization.source == "base":
            self.localizer.follow(odom)
            frame = placed(frame, self.localizer.map_T_odom)
            return frame, self._project(frame)
        frame = placed(frame, self.localizer.map_T_odom)
        view = self._project(frame)
        assert self.obstacle_points is not None
        match = self.localizer.match(view.obstacles, view.camera, self.obstacle, self.explored,
                                     self.obstacle_points, odom)
        if match.accepted and not match.correction.identity:
            frame, view = placed(frame, match.correction), view.moved(match.correction)
        if self.loops is not None:
            at = planar_pose(frame)
            map_T_odom = self.loops.add(odom, at, view.obstacles, match.accepted)
            if map_T_odom is not None:  # a loop closed: the keyframes were re-placed, and this frame
                self.localizer.map_T_odom = map_T_odom
                shift = map_T_odom.compose(odom).compose(at.inverse())
                frame, view = placed(frame, shift), view.moved(shift)
                self.draw_keyframes()
        return frame, view

    def draw_keyframes(self) -> None:
        """The obstacles drawn again from the loop closer's keyframes at their solved poses (and
        what they did not draw: a resumed map's)."""
        assert self.loops is not None and self._obstacle_base is not None
        self.obstacle = self._obstacle_base.copy()
        self.obstacle_points = ObstaclePoints(self.grid)
        self.loops.draw(self.obstacle, self.obstacle_points)

    def _project(self, frame: RgbdFrame) -> View:
        c = self.config
        return project(frame, c.pixel_stride, (c.depth_min, c.depth_max),
                       (c.min_obstacle_height, c.max_obstacle_height))

    def _confidence(self, view: View) -> tuple[tuple[slice, slice] | None, np.ndarray, np.ndarray]:
        """The window of cells around the view, which of them it covers, and each cell's FOV
        confidence (0 outside the view or below the floor: not counted, no value)."""
        window, seen, theta = self._view_cells(view)
        confidence = np.where(seen, fov_confidence(theta, view.hfov), 0.0).astype(np.float32)
        confidence[confidence < self.config.confidence_floor] = 0.0
        return window, seen, confidence

    def _grow_bbox(self, rows: slice, cols: slice) -> None:
        box = (rows.start, rows.stop, cols.start, cols.stop)
        if self._bbox is not None:
            box = (min(box[0], self._bbox[0]), max(box[1], self._bbox[1]),
                   min(box[2], self._bbox[2]), max(box[3], self._bbox[3]))
        self._bbox = box

    def _mark_obstacles(self, view: View) -> None:
        mark_obstacles(view.obstacles, self.grid, self.obstacle, self.obstacle_points)

    def _view_cells(self, view: View) -> tuple[tuple[slice, slice] | None, np.ndarray, np.ndarray]:
        """The window of cells around the view polygon, which of them it covers, and their
        angle to the optical axis."""
        g = self.grid
        cells = (view.polygon - (g.x0, g.y0)) / g.resolution
        lo = np.maximum(np.floor(cells.min(axis=0)).astype(int), 0)
        hi = np.minimum(np.ceil(cells.max(axis=0)).astype(int) + 1, (g.cols, g.rows))
        if (hi <= lo).any():
            return None, np.zeros((0, 0), bool), np.zeros((0, 0))
        mask = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
        local = np.round((cells - lo - 0.5) * 16).astype(np.int32)
        cv2.fillPoly(mask, [local], 1, cv2.LINE_8, shift=4)
        xs = g.x0 + (np.arange(lo[0], hi[0]) + 0.5) * g.resolution
        ys = g.y0 + (np.arange(lo[1], hi[1]) + 0.5) * g.resolution
        theta = np.arctan2(ys[:, None] - view.camera[1], xs[None, :] - view.camera[0]) - view.heading
        theta = (theta + math.pi) % (2 * math.pi) - math.pi
        return (slice(lo[1], hi[1]), slice(lo[0], hi[0])), mask.astype(bool), theta

    # -- reading ------------------------------------------------------------------------------
    def frontiers(self) -> np.ndarray:
        """N x 2 world waypoints, one per frontier segment between free cells searched for every
        remaining target (the explored area while there is no target) and the rest."""
        if self._bbox is None:
            return np.zeros((0, 2))
        pad = 2 + math.ceil(self.config.robot_radius / self.grid.resolution)
        r0, r1 = max(self._bbox[0] - pad, 0), min(self._bbox[1] + pad, self.grid.rows)
        c0, c1 = max(self._bbox[2] - pad, 0), min(self._bbox[3] + pad, self.grid.cols)
        # Obstacles grown by the robot radius: cells the robot cannot stand on are neither
        # free nor unknown, so walls (and the gaps between their sampled points) make no frontier.
        blocked = inflate(self.obstacle[r0:r1, c0:c1], self.config.robot_radius, self.grid.resolution)
        explored = self.explored[r0:r1, c0:c1]
        for searched in self.searched.values():
            explored = explored & searched[r0:r1, c0:c1]
        unknown = (~explored & ~blocked).astype(np.uint8)
        near_unknown = cv2.dilate(unknown, np.ones((3, 3), np.uint8)).astype(bool)
        frontier = explored & ~blocked & near_unknown
        n, labels, stats, centroids = cv2.connectedComponentsWithStats(frontier.astype(np.uint8),
                                                                       connectivity=8)
        keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= self.config.frontier_min_cells) + 1
        if keep.size == 0:
            return np.zeros((0, 2))
        fr, fc = np.nonzero(np.isin(labels, keep))
        lab = labels[fr, fc]
        # one waypoint per segment: its cell nearest to the segment's centroid
        dist = (fc - centroids[lab, 0]) ** 2 + (fr - centroids[lab, 1]) ** 2
        order = np.lexsort((dist, lab))
        _, first = np.unique(lab[order], return_index=True)
        pick = order[first]
        xs, ys = self.grid.to_world(fr[pick] + r0, fc[pick] + c0)
        return np.stack([xs, ys], axis=1).astype(np.float64).reshape(-1, 2)

    # -- snapshots and checkpoints --------------------------------------------------------------
    def snapshot(self, stamp: float, *, with_confidence: bool = True) -> MapSnapshot:
        """The map as a message: a copy, so it stays one consistent state however long its
        encoding takes and whatever is fused meanwhile. Checkpoints need the confidences, the
        planner does not (nor the searched areas: the frontiers are made of them)."""
        layers = self.layers

        def stacked(grids: dict[str, np.ndarray], dtype: type) -> np.ndarray:
            return (np.stack([grids[t] for t in layers]) if layers
                    else np.zeros((0, *self.grid.shape), dtype))

        values = stacked(self.values, np.float32)
        confidence = stacked(self.confidence, np.float32) if with_confidence else None
        searched = stacked(self.searched, np.bool_) if with_confidence else None
        return MapSnapshot(seq=self.seq, after_action=self.after_action, odom_session=self.odom_session,
                           stamp=stamp, map_T_odom=self.map_T_odom,
                           resolution=self.grid.resolution, origin=(self.grid.x0, self.grid.y0),
                           layers=layers, objects=self.objects.instances(),
                           obstacle=self.obstacle.copy(), explored=self.explored.copy(),
                           counts=stacked(self.counts, np.uint16), values=values,
                           confidence=confidence, searched=searched, frontiers=self.frontiers())

    @classmethod
    def from_snapshot(cls, snapshot: MapSnapshot, config: MappingConfig) -> MapState:
        """Resume from a snapshot (a checkpoint); it must fit the configured grid."""
        state = cls(config, odom_session=snapshot.odom_session)
        if (snapshot.obstacle.shape != state.grid.shape or snapshot.resolution != state.grid.resolution
                or tuple(snapshot.origin) != (state.grid.x0, state.grid.y0)):
            raise ValueError("the snapshot's grid does not match the configured grid")
        if snapshot.confidence is None or snapshot.searched is None:
            raise ValueError("no confidences or searched areas (a published snapshot, not a checkpoint)")
        state.obstacle = snapshot.obstacle.copy()
        if state.loops is not None:
            state._obstacle_base = snapshot.obstacle.copy()
        state.explored = snapshot.explored.copy()
        for i, target in enumerate(snapshot.layers):
            state.values[target] = snapshot.values[i].copy()
            state.confidence[target] = snapshot.confidence[i].copy()
            state.counts[target] = snapshot.counts[i].copy()
            state.searched[target] = snapshot.searched[i].copy()
        state.objects = ObjectMap.from_instances(
            snapshot.objects, config.object_merge_distance_m, config.object_confirm_hits,
            config.decision_threshold, **_evidence(config))
        if state.localizer is not None:
            state.localizer.map_T_odom = snapshot.map_T_odom
        state.seq = snapshot.seq
        state.after_action = snapshot.after_action
        rows, cols = np.nonzero(state.explored)
        if rows.size:
            state._bbox = (int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1)
        return state


class _Evidence(TypedDict):
    min_hit_ratio: float
    view_range_m: float


def _evidence(config: MappingConfig) -> _Evidence:
    return {"min_hit_ratio": config.object_min_hit_ratio, "view_range_m": config.object_view_range_m}
