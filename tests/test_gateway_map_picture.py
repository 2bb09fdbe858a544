"""The gateway's map picture (``map.png``) of a task on a map that outlives it: the legend, the
robot with its heading, and only the task's targets' objects drawn as its detections."""

from __future__ import annotations

import cv2
import numpy as np

from ovamos.services.gateway.maps import map_png, map_view
from ovamos.services.gateway.models import Pose
from ovamos.services.gateway.store import TaskRecord
from ovamos.services.mapping import render
from ovamos.shared.messages import FoundObject, Goal, ObjectInstance, TaskStatus
from tests.gateway_mocks import small_map

PPC = 2  # the PNG's pixels per cell


def _snapshot():
    base = small_map()  # 40 x 40 cells of 5 cm, explored 5..34, a confirmed chair at (0.6, 1.4)
    lamp = ObjectInstance(label="lamp", x=1.2, y=0.5, score=0.9, hits=5, confirmed=True)  # an earlier task's
    return base.model_copy(update={"objects": (*base.objects, lamp)})


def _task(**changes) -> TaskRecord:
    fields = dict(id="t1", robot_id="sim", status=TaskStatus.SEARCHING, targets=["chair", "sofa"], max_steps=100,
                  path=[(0.4, 0.4), (0.5, 0.6)])
    return TaskRecord(**{**fields, **changes})


def _decode(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def _at(image: np.ndarray, x: float, y: float, reach: int = 7) -> np.ndarray:
    """The pixels around world (x, y) in the PNG, whose map is the whole 40 x 40 grid (the explored
    cells 5..34 and the 10-cell margin)."""
    u, v = int(x / 0.05 * PPC), int((40 - y / 0.05) * PPC)
    return image[v - reach:v + reach + 1, u - reach:u + reach + 1]


def _has(pixels: np.ndarray, bgr) -> bool:
    return bool((pixels == bgr).all(axis=-1).any())


def test_the_png_has_its_legend_and_draws_the_tasks_detections_robot_goal_and_found() -> None:
    task = _task(found=[FoundObject(label="chair", x=0.6, y=1.4, step=4)])
    image = _decode(map_png(_snapshot(), task=task, robot=Pose(x=0.5, y=0.6, yaw=0.0),
                            goal=Goal(kind="frontier", x=1.5, y=1.0)))
    assert image.shape[1] == 40 * PPC + render.LEGEND_WIDTH  # the legend to the map's right
    assert _has(image[:, 40 * PPC:], render.CONFIRMED) and _has(image[:, 40 * PPC:], render.OTHER)
    lamp = _at(image, 1.2, 0.5)
    assert _has(lamp, render.OTHER) and not _has(lamp, render.CONFIRMED)  # not a target of this task
    assert tuple(_at(image, 0.6, 1.4, 0)[0, 0]) == render.FOUND
    assert _has(_at(image, 0.5, 0.6, 4), render.ROBOT)
    assert _has(_at(image, 1.5, 1.0, 9), render.GOAL)


def test_without_a_task_the_layers_say_which_objects_are_the_tasks() -> None:
    image = _decode(map_png(_snapshot(), [(0.4, 0.4), (0.5, 0.6)]))  # as GET map.png asks today
    assert _has(_at(image, 0.6, 1.4), render.CONFIRMED)  # the chair: the map's one layer
    assert _has(_at(image, 1.2, 0.5), render.OTHER)
    assert image.shape[1] == 40 * PPC + render.LEGEND_WIDTH


def test_the_page_s_map_window_holds_the_goal_and_the_found_targets() -> None:
    snap = small_map().model_copy(update={"objects": ()})
    far = Goal(kind="frontier", x=1.9, y=1.95)
    view = map_view(snap, _task(found=[FoundObject(label="chair", x=0.02, y=0.03, step=2)]), goal=far,
                    margin_cells=0)  # the explored cells alone span 0.25 to 1.75 m
    right, top = view.x0 + view.width * view.resolution, view.y0 + view.height * view.resolution
    for x, y in [(far.x, far.y), (0.02, 0.03)]:
        assert view.x0 <= x <= right and view.y0 <= y <= top
