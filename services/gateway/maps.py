"""The latest map of a robot, asked from its mapping service on demand: as a PNG, or as the
raster plus vector layers the operator's page draws (:func:`map_view`).

The gateway keeps no map of its own: it queries ``map/snapshot`` when a
picture is requested (:func:`ovamos.services.gateway.service.fetch_snapshot`), so it never
holds megabytes per robot nor shows a map staler than the mapping service's. The robot's path (the positions its
latest task reported) is drawn over the map; the PNG carries a legend and, given the task, draws
as its detections only the objects of its targets (:func:`map_png`).
"""

from __future__ import annotations

import base64
from collections.abc import Sequence

import cv2
import numpy as np

from ovamos.services.gateway.models import Candidate, MapView, Pose
from ovamos.services.gateway.store import TaskRecord
from ovamos.services.mapping.render import crop_box, map_raster, render_map, value_image
from ovamos.shared.messages import DecisionTrace, Goal, MapSnapshot
from ovamos.shared.robot import ROBOT


class NoMap(LookupError):
    """No mapping service answered for the robot."""


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("the map could not be encoded as PNG")
    return data.tobytes()


def map_png(snapshot: MapSnapshot, path: Sequence[tuple[float, float]] = (),
            layer: str | None = None, *, task: TaskRecord | None = None, robot: Pose | None = None,
            goal: Goal | None = None) -> bytes:
    """PNG bytes of :func:`render_map`, with its legend; ValueError for an unknown ``layer``.

    With the robot's latest ``task``, the picture is of that task: its path (unless ``path`` is
    given), its found targets, and only objects of its targets drawn as its detections (the map
    also holds those of earlier tasks' targets: grey); without, the snapshot's layers (the
    remaining targets) say which are the task's. ``robot`` is drawn with its heading, ``goal``
    as a red ring."""
    if task is not None and not path:
        path = task.path
    return _png(render_map(snapshot, layer=layer, path=path,
                           robot=None if robot is None else (robot.x, robot.y, robot.yaw),
                           targets=task.targets if task is not None else None,
                           found=task.found if task is not None else (), goal=goal))


def map_view(snapshot: MapSnapshot, task: TaskRecord | None, *, layer: str | None = None,
             robot: Pose | None = None, goal: Goal | None = None, decision: DecisionTrace | None = None,
             margin_cells: int = 10) -> MapView:
    """The page's map: the raster of the window holding the explored area, the robot, the goal,
    ``task``'s path and found targets, objects and frontiers
    (:func:`ovamos.services.mapping.render.crop_box`), and those in world metres; the candidates the
    planner weighed at its latest ``decision`` (none when no task searches). ValueError for an
    unknown ``layer``.

    Objects are those of the whole map, of every label it ever searched for: the page draws only
    those of the task's targets as its detections (``task_id`` names the task)."""
    heat = value_image(snapshot, layer)  # validates the layer name first
    path = task.path if task is not None else []
    found = task.found if task is not None else []
    points = ([(o.x, o.y) for o in snapshot.objects] + [tuple(f) for f in snapshot.frontiers] + path
              + [(f.x, f.y) for f in found])
    for at in (robot, goal):
        if at is not None:
            points.append((at.x, at.y))
    r0, r1, c0, c1 = box = crop_box(snapshot, np.asarray(points, float).reshape(-1, 2), margin_cells)
    res, (x0, y0) = snapshot.resolution, snapshot.origin
    image = base64.b64encode(_png(map_raster(snapshot, heat, box))).decode()
    return MapView(seq=snapshot.seq, odom_session=snapshot.odom_session,
                   map_T_odom=Pose(**snapshot.map_T_odom.model_dump()), stamp=snapshot.stamp,
                   resolution=res, x0=x0 + c0 * res, y0=y0 + r0 * res, width=c1 - c0, height=r1 - r0,
                   image=f"data:image/png;base64,{image}", layers=list(snapshot.layers), layer=layer,
                   frontiers=[(float(x), float(y)) for x, y in snapshot.frontiers],
                   candidates=[] if decision is None else [Candidate(x=o.x, y=o.y, value=o.value)
                                                           for o in decision.options if o.kind == "candidate"],
                   objects=list(snapshot.objects), task_id=task.id if task is not None else None,
                   path=path, found=task.found if task is not None else [], robot=robot,
                   robot_radius_m=ROBOT.radius_m, goal=goal)
