"""The robot's messages drawn in Foxglove's well-known schemas, so Foxglove shows them with no plug-in.

One :class:`ViewBuilder` turns decoded messages into view messages on a Foxglove context;
whatever sinks the context has get them: the recorder's MCAP file, ``ovamos view``'s
WebSocket server. World things are in the ``map`` frame (the odometry frame, x forward, y
left); images in ``camera``.

* ``/camera/color`` (CompressedImage, JPEG: a tenth of the raw image's bytes in the file; the
  raw channel keeps the exact pixels), ``/camera/depth`` (RawImage 32FC1 metres, or 16UC1 in
  the frame's own units);
* ``/map/obstacle``, ``/map/explored`` (Grid, uint8 0/1), ``/map/value/<target>`` (Grid,
  float32: the layer decayed by the update counts, as the planner decides on it);
* ``/map/frontiers``, ``/map/objects`` (SceneUpdate: frontier waypoints; objects with their
  labels, green when confirmed);
* ``/robot/pose`` (PoseInFrame), ``/robot/path`` (PosesInFrame), ``/tf`` (map -> base_link);
* ``/planner/candidates`` (SceneUpdate: candidates sized by belief, labelled with belief, path
  length and POUCT's Q and visits; the frontier weighed), ``/planner/goal`` (SceneUpdate);
* ``/log`` (Log): task events and the planner's decisions as log lines.

Images and grids are only made for channels someone takes (an MCAP file always does; a live
view's WebSocket client once it subscribes), so an idle ``ovamos view`` costs little.

:class:`ViewPump` runs a builder on a thread of its own behind an
:class:`~ovamos.shared.inbox.Inbox`: frames and maps keep only their newest sample while it is
busy (a view may skip frames; the raw channels never do), the rest queue in order.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
from foxglove import Context
from foxglove.channels import (
    CompressedImageChannel,
    FrameTransformChannel,
    GridChannel,
    LogChannel,
    PoseInFrameChannel,
    PosesInFrameChannel,
    RawImageChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    Color,
    CompressedImage,
    CubePrimitive,
    FrameTransform,
    Grid,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    RawImage,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector2,
    Vector3,
)

from ovamos.services.mapping.layers import value_map
from ovamos.shared.inbox import Inbox
from ovamos.shared.log import sampled
from ovamos.shared.messages import DecisionTrace, DecodeError, MapSnapshot, Odometry, RgbdFrame, TaskEvent, TaskStatus

__all__ = ["ViewBuilder", "ViewPump", "TOPICS", "LATEST_ONLY"]

WORLD, BASE, CAMERA = "map", "base_link", "camera"
TOPICS = ("/camera/color", "/camera/depth", "/map/obstacle", "/map/explored", "/map/frontiers",
          "/map/objects", "/robot/pose", "/robot/path", "/tf", "/planner/candidates", "/planner/goal", "/log")
"""The fixed view topics (``/map/value/<target>`` come and go with the targets)."""
log = logging.getLogger("ovamos.views")

LATEST_ONLY = frozenset({"rgbd", "map_snapshot"})
"""Keys whose views may skip samples while the pump is busy (large, and superseded by the next)."""
JPEG_QUALITY = 90
PATH_STEP_M = 0.05     # a new path point once the robot moved this far
PATH_MAX_POINTS = 20_000

GREEN, ORANGE, MAGENTA, BLUE, RED = ((0.15, 0.7, 0.15, 1.0), (1.0, 0.55, 0.0, 1.0), (0.8, 0.0, 0.8, 1.0),
                                     (0.1, 0.4, 1.0, 0.8), (0.9, 0.1, 0.1, 1.0))
_LOG_LEVEL = {TaskStatus.FAILED: LogLevel.Warning, TaskStatus.CANCELLED: LogLevel.Warning}


def _stamp(ns: int) -> Timestamp:
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _color(rgba: tuple[float, float, float, float]) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _yaw(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def _pose(x: float, y: float, z: float = 0.0, yaw: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=_yaw(yaw))


def _sphere(x: float, y: float, size: float, rgba: tuple[float, float, float, float]) -> SpherePrimitive:
    return SpherePrimitive(pose=_pose(x, y, size / 2), size=Vector3(x=size, y=size, z=size), color=_color(rgba))


def _text(x: float, y: float, z: float, text: str) -> TextPrimitive:
    return TextPrimitive(pose=_pose(x, y, z), billboard=True, font_size=14.0, scale_invariant=True,
                         color=_color((1.0, 1.0, 1.0, 1.0)), text=text)


def _scene(ns: int, entities: list[SceneEntity]) -> SceneUpdate:
    """Replaces everything shown before (lists that shrink leave nothing behind)."""
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=_stamp(ns), type=SceneEntityDeletionType.All)],
                       entities=entities)


def _entity(ns: int, id: str, **primitives: Any) -> SceneEntity:
    return SceneEntity(timestamp=_stamp(ns), frame_id=WORLD, id=id, **primitives)


class ViewBuilder:
    """Draws messages on ``context``'s view channels (one thread: it keeps the robot's path)."""

    def __init__(self, context: Context) -> None:
        self._context = context
        self._color = CompressedImageChannel("/camera/color", context=context)
        self._depth = RawImageChannel("/camera/depth", context=context)
        self._obstacle = GridChannel("/map/obstacle", context=context)
        self._explored = GridChannel("/map/explored", context=context)
        self._values: dict[str, GridChannel] = {}
        self._frontiers = SceneUpdateChannel("/map/frontiers", context=context)
        self._objects = SceneUpdateChannel("/map/objects", context=context)
        self._pose = PoseInFrameChannel("/robot/pose", context=context)
        self._path_channel = PosesInFrameChannel("/robot/path", context=context)
        self._tf = FrameTransformChannel("/tf", context=context)
        self._candidates = SceneUpdateChannel("/planner/candidates", context=context)
        self._goal = SceneUpdateChannel("/planner/goal", context=context)
        self._log = LogChannel("/log", context=context)
        self._path: list[Pose] = []
        self._path_xy = (0.0, 0.0)  # the newest path point
        self._handlers = {RgbdFrame: self._frame, MapSnapshot: self._map, Odometry: self._odom,
                          DecisionTrace: self._trace, TaskEvent: self._task}

    def draw(self, msg: object, ns: int) -> bool:
        """Draw ``msg`` (received at ``ns``, Unix nanoseconds); False for a type with no view."""
        handler = self._handlers.get(type(msg))
        if handler is None:
            return False
        handler(msg, ns)
        return True

    # -- camera --------------------------------------------------------------------------------
    def _frame(self, f: RgbdFrame, ns: int) -> None:
        h, w = f.depth.shape
        t = _stamp(ns)
        if self._depth.has_sinks():
            encoding = "32FC1" if f.depth.dtype == np.float32 else "16UC1"
            self._depth.log(RawImage(timestamp=t, frame_id=CAMERA, width=w, height=h, encoding=encoding,
                                     step=w * f.depth.itemsize, data=f.depth.tobytes()), log_time=ns)
        if not self._color.has_sinks():
            return
        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR),
                                [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise ValueError(f"frame {f.seq}: JPEG encoding failed")
        self._color.log(CompressedImage(timestamp=t, frame_id=CAMERA, format="jpeg", data=jpeg.tobytes()),
                        log_time=ns)

    # -- map -----------------------------------------------------------------------------------
    def _grid(self, s: MapSnapshot, ns: int, cells: np.ndarray, kind: PackedElementFieldNumericType,
              name: str) -> Grid:
        rows, cols = cells.shape
        size = cells.itemsize
        return Grid(timestamp=_stamp(ns), frame_id=WORLD, pose=_pose(s.origin[0], s.origin[1]),
                    column_count=cols, cell_size=Vector2(x=s.resolution, y=s.resolution),
                    row_stride=cols * size, cell_stride=size,
                    fields=[PackedElementField(name=name, offset=0, type=kind)],
                    data=np.ascontiguousarray(cells).tobytes())

    def _map(self, s: MapSnapshot, ns: int) -> None:
        u8 = PackedElementFieldNumericType.Uint8
        if self._obstacle.has_sinks():
            self._obstacle.log(self._grid(s, ns, s.obstacle.astype(np.uint8), u8, "obstacle"), log_time=ns)
        if self._explored.has_sinks():
            self._explored.log(self._grid(s, ns, s.explored.astype(np.uint8), u8, "explored"), log_time=ns)
        for layer in s.layers:
            channel = self._values.get(layer)
            if channel is None:
                channel = self._values[layer] = GridChannel(f"/map/value/{layer}", context=self._context)
            if not channel.has_sinks():
                continue
            values = value_map(s, (layer,))
            assert values is not None  # the layer is one of the snapshot's
            channel.log(self._grid(s, ns, values.astype(np.float32), PackedElementFieldNumericType.Float32,
                                   "value"), log_time=ns)
        frontiers = [_sphere(float(x), float(y), 0.15, MAGENTA) for x, y in s.frontiers]
        self._frontiers.log(_scene(ns, [_entity(ns, "frontiers", spheres=frontiers)] if frontiers else []),
                            log_time=ns)
        objects = [_entity(ns, f"object-{i}",
                           cubes=[CubePrimitive(pose=_pose(o.x, o.y, 0.15), size=Vector3(x=0.3, y=0.3, z=0.3),
                                                color=_color(GREEN if o.confirmed else ORANGE))],
                           texts=[_text(o.x, o.y, 0.5, f"{o.label} {o.score:.2f} ({o.hits} hits)"
                                                       + (" confirmed" if o.confirmed else ""))])
                   for i, o in enumerate(s.objects)]
        self._objects.log(_scene(ns, objects), log_time=ns)

    # -- robot ---------------------------------------------------------------------------------
    def _odom(self, o: Odometry, ns: int) -> None:
        t = _stamp(ns)
        pose = _pose(o.x, o.y, 0.0, o.yaw)
        self._pose.log(PoseInFrame(timestamp=t, frame_id=WORLD, pose=pose), log_time=ns)
        self._tf.log(FrameTransform(timestamp=t, parent_frame_id=WORLD, child_frame_id=BASE,
                                    translation=Vector3(x=o.x, y=o.y, z=0.0),
                                    rotation=_yaw(o.yaw)), log_time=ns)
        if not self._path or math.hypot(o.x - self._path_xy[0], o.y - self._path_xy[1]) >= PATH_STEP_M:
            self._path_xy = (o.x, o.y)
            self._path.append(pose)
            if len(self._path) > PATH_MAX_POINTS:  # bounded: keep every other point of the older half
                half = len(self._path) // 2
                self._path = self._path[:half:2] + self._path[half:]
            self._path_channel.log(PosesInFrame(timestamp=t, frame_id=WORLD, poses=self._path), log_time=ns)

    # -- planner and task ----------------------------------------------------------------------
    def _trace(self, d: DecisionTrace, ns: int) -> None:
        entities = []
        for i, o in enumerate(d.options):
            words = [o.kind] + ([f"p {o.belief:.2f}"] if o.belief is not None else []) \
                + ([f"{o.path_m:.1f} m"] if o.path_m is not None else ["no path"]) \
                + ([f"Q {o.q:.1f} N {o.visits}"] if o.q is not None else [])
            size = 0.15 + 0.5 * (o.belief or 0.0)
            entities.append(_entity(ns, f"option-{i}", spheres=[_sphere(o.x, o.y, size,
                                                                        BLUE if o.kind == "candidate" else MAGENTA)],
                                    texts=[_text(o.x, o.y, size + 0.2, " ".join(words))]))
        self._candidates.log(_scene(ns, entities), log_time=ns)
        goal = [] if d.goal is None else [_entity(ns, "goal", spheres=[_sphere(d.goal.x, d.goal.y, 0.3, RED)],
                                                  texts=[_text(d.goal.x, d.goal.y, 0.6,
                                                               f"goal: {d.goal.kind} {d.goal.label or ''}")])]
        self._goal.log(_scene(ns, goal), log_time=ns)
        where = "nothing" if d.goal is None else f"{d.goal.kind} ({d.goal.x:.2f}, {d.goal.y:.2f})"
        self._log.log(Log(timestamp=_stamp(ns), level=LogLevel.Info, name="planner",
                          message=f"step {d.step}: {where} of {len(d.options)} options: {d.reason}"),
                      log_time=ns)

    def _task(self, e: TaskEvent, ns: int) -> None:
        found = ", ".join(f"{f.label} at ({f.x:.1f}, {f.y:.1f})" for f in e.found) or "nothing"
        text = (f"task {e.task_id} {e.status.value}: step {e.steps}, {e.distance_m:.1f} m, found {found}"
                + (f"; {e.message}" if e.message else ""))
        self._log.log(Log(timestamp=_stamp(ns), level=_LOG_LEVEL.get(e.status, LogLevel.Info), name="task",
                          message=text), log_time=ns)


class ViewPump:
    """A :class:`ViewBuilder` on a thread of its own: :meth:`offer` never blocks its caller.

    Counters (read from any thread): ``drawn``, ``skipped`` (a newer frame or map came
    first, or the queue was full), ``malformed`` (payloads that did not decode), ``failed``.
    """

    def __init__(self, context: Context, ports: Mapping[str, type], *, limit: int = 1000) -> None:
        self.builder = ViewBuilder(context)
        self._ports = dict(ports)
        self._inbox = Inbox(limit=limit)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.counters: Counter[str] = Counter()
        self._thread = threading.Thread(target=self._run, name="views", daemon=True)
        self._thread.start()

    def offer(self, name: str, payload: bytes, ns: int) -> None:
        """Queue the payload of key ``name`` received at ``ns`` (any thread)."""
        if name not in self._ports:
            return
        self._inbox.put(self._draw, (name, payload, ns), channel=name, keep=1 if name in LATEST_ONLY else 0,
                        on_drop=lambda: self._count("skipped"))

    def _count(self, what: str) -> int:
        with self._lock:
            self.counters[what] += 1
            return self.counters[what]

    def _draw(self, item: tuple[str, bytes, int]) -> None:
        name, payload, ns = item
        try:
            msg = self._ports[name].from_bytes(payload)
        except DecodeError:
            self._count("malformed")
            return
        try:
            if self.builder.draw(msg, ns):
                self._count("drawn")
        except Exception:  # a view that cannot be drawn must not stop the others
            if sampled(n := self._count("failed")):
                log.exception("%s: view failed (%d so far)", name, n)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._inbox.run_until(time.monotonic() + 0.5, self._stop)

    def close(self) -> None:
        """Draw what is queued, then stop (idempotent)."""
        self._stop.set()
        self._thread.join()
        self._inbox.run_pending()
        self._inbox.close()
