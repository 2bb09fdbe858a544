"""Pictures of the mapping service's state, for people debugging a search.

One BGR image of a :class:`~shared.messages.MapSnapshot` seen from above (image
up = world +y, as in :mod:`services.sim.draw`): unexplored cells dark grey,
explored free cells light, obstacles black, the value map the planner decides on
(decayed, :func:`value_image`) as a heat map over explored free cells, frontier waypoints, object instances with their labels,
and optionally the robot and its path. By default the picture is cropped to
what has been explored (plus a margin): the service's grid is sized for the
largest home, and early in a search almost all of it is unknown.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from services.mapping.layers import DECAY_KAPPA, DECAY_TAU, value_map
from shared.atomic import write_atomic
from shared.messages import MapSnapshot
from shared.robot import ROBOT as ROBOT_GEOMETRY

__all__ = ["crop_box", "map_raster", "render_map", "value_image", "write_png"]

UNEXPLORED = (70, 70, 70)     # BGR
FREE = (235, 235, 235)
OBSTACLE = (0, 0, 0)
FRONTIER = (200, 0, 200)
ROBOT = (200, 60, 20)
PATH = (200, 60, 20)
CONFIRMED = (40, 170, 40)     # filled square: the planner may stop here
UNCONFIRMED = (0, 140, 255)   # hollow circle: seen, not yet trusted
COLORMAP = cv2.COLORMAP_TURBO  # blue (low) -> red (high), as the sim draws depth
HEADING_LENGTH_M = 0.35


def value_image(snapshot: MapSnapshot, layer: str | None = None, *, tau: float = DECAY_TAU,
                kappa: float = DECAY_KAPPA) -> np.ndarray:
    """The value map shown by :func:`render_map`: H x W float in [0, 1].

    The map the planner decides on (:func:`services.mapping.layers.value_map`: each
    layer over the explored cells divided by its peak, decayed by the update counts with
    ``tau`` and ``kappa``, summed), of every layer (``layer=None``) or of one by name,
    divided by its maximum for colour. An all-zero map gives zeros. Unknown layer names
    raise ``ValueError`` naming the known ones.
    """
    if layer is not None and layer not in snapshot.layers:
        known = ", ".join(repr(n) for n in snapshot.layers) or "none"
        raise ValueError(f"unknown value layer {layer!r} (layers: {known})")
    total = value_map(snapshot, snapshot.layers if layer is None else (layer,), tau, kappa)
    if total is None:
        return np.zeros(snapshot.obstacle.shape)
    total = np.clip(np.nan_to_num(total.astype(np.float64), nan=0.0, posinf=0.0), 0.0, None)
    top = total.max()
    return total / top if top > 0 else total


def crop_box(snapshot: MapSnapshot, extra_xy: np.ndarray, margin_cells: int
              ) -> tuple[int, int, int, int]:
    """(r0, r1, c0, c1), end-exclusive: explored cells and extra points, plus a margin."""
    rows, cols = snapshot.obstacle.shape
    r, c = np.nonzero(snapshot.explored | snapshot.obstacle)
    if len(extra_xy):
        res, (x0, y0) = snapshot.resolution, snapshot.origin
        er = np.floor((extra_xy[:, 1] - y0) / res).astype(np.int64)
        ec = np.floor((extra_xy[:, 0] - x0) / res).astype(np.int64)
        inside = (er >= 0) & (er < rows) & (ec >= 0) & (ec < cols)
        r, c = np.concatenate([r, er[inside]]), np.concatenate([c, ec[inside]])
    if r.size == 0:
        return 0, rows, 0, cols
    return (max(0, int(r.min()) - margin_cells), min(rows, int(r.max()) + 1 + margin_cells),
            max(0, int(c.min()) - margin_cells), min(cols, int(c.max()) + 1 + margin_cells))


def map_raster(snapshot: MapSnapshot, heat: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """The raster layers of the cells in ``box`` (r0, r1, c0, c1, end-exclusive), one BGR pixel per
    cell, world +y up (row 0 of the grid at the bottom): unexplored, explored free, ``heat``
    (:func:`value_image`) over explored free cells, obstacles. The operator's page draws its
    vector layers over this same picture."""
    r0, r1, c0, c1 = box
    window = np.s_[r0:r1, c0:c1]
    explored, obstacle = snapshot.explored[window], snapshot.obstacle[window]
    image = np.empty((r1 - r0, c1 - c0, 3), np.uint8)
    image[:] = UNEXPLORED
    image[explored] = FREE
    hot = explored & ~obstacle & (heat[window] > 0)
    if hot.any():
        scaled = np.clip(np.round(heat[window][hot] * 255), 0, 255).astype(np.uint8)
        image[hot] = cv2.applyColorMap(scaled.reshape(-1, 1), COLORMAP).reshape(-1, 3)
    image[obstacle] = OBSTACLE
    return np.ascontiguousarray(image[::-1])


def _text(image: np.ndarray, label: str, at: tuple[int, int], scale: float = 0.35) -> None:
    """Dark text with a light halo, readable over any map colour."""
    for colour, thickness in (((255, 255, 255), 3), ((20, 20, 20), 1)):
        cv2.putText(image, label, at, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness,
                    cv2.LINE_AA)


def render_map(snapshot: MapSnapshot, *, layer: str | None = None,
               robot: tuple[float, float, float] | None = None,
               path: Sequence[tuple[float, float]] = (), crop: bool = True,
               px_per_cell: int = 2, margin_cells: int = 10, tau: float = DECAY_TAU,
               kappa: float = DECAY_KAPPA) -> np.ndarray:
    """A BGR uint8 picture of ``snapshot`` from above (see the module docstring).

    ``layer`` picks the value layer to show (``None``: all of them; either way the
    decayed map the planner decides on, :func:`value_image`, with the decay's ``tau`` and
    ``kappa``); ``robot`` is (x, y, yaw) in world metres and
    radians; ``path`` world (x, y) points drawn as a polyline. ``crop`` keeps the
    bounding box of explored cells, the robot, the path, objects and frontiers,
    grown by ``margin_cells``; the whole grid when there is nothing to show.
    Confirmed objects are filled green squares, unconfirmed ones hollow orange
    circles, each labelled ``label xhits``.
    """
    if px_per_cell < 1:
        raise ValueError(f"px_per_cell must be >= 1, got {px_per_cell}")
    heat = value_image(snapshot, layer, tau=tau, kappa=kappa)  # validates the layer name first
    res, (x0, y0) = snapshot.resolution, snapshot.origin
    rows, cols = snapshot.obstacle.shape
    objects = np.array([(o.x, o.y) for o in snapshot.objects], float).reshape(-1, 2)
    frontiers = np.asarray(snapshot.frontiers, float).reshape(-1, 2)
    path_xy = np.asarray(path, float).reshape(-1, 2)
    extra = [objects, frontiers, path_xy]
    if robot is not None:
        extra.append(np.array([robot[:2]], float))
    r0, r1, c0, c1 = box = (crop_box(snapshot, np.vstack(extra), margin_cells) if crop
                            else (0, rows, 0, cols))
    image = map_raster(snapshot, heat, box)
    if px_per_cell > 1:
        image = cv2.resize(image, None, fx=px_per_cell, fy=px_per_cell,
                           interpolation=cv2.INTER_NEAREST)

    k = px_per_cell / res  # pixels per metre

    def px(x: float, y: float) -> tuple[int, int]:
        """World metres -> pixel (u, v) in the cropped, flipped, scaled picture."""
        return (math.floor(((x - x0) / res - c0) * px_per_cell),
                math.floor((r1 - (y - y0) / res) * px_per_cell))

    for x, y in frontiers:
        cv2.circle(image, px(x, y), max(3, px_per_cell * 2), FRONTIER, 1, cv2.LINE_AA)
    if len(path_xy) > 1:
        pts = np.array([px(x, y) for x, y in path_xy], np.int32)
        cv2.polylines(image, [pts], False, PATH, 1, cv2.LINE_AA)
    size = max(3, px_per_cell * 2)
    for obj in snapshot.objects:
        u, v = px(obj.x, obj.y)
        if obj.confirmed:
            cv2.rectangle(image, (u - size, v - size), (u + size, v + size), CONFIRMED, -1)
            cv2.rectangle(image, (u - size, v - size), (u + size, v + size), (0, 0, 0), 1)
        else:
            cv2.circle(image, (u, v), size, UNCONFIRMED, 2, cv2.LINE_AA)
        _text(image, f"{obj.label} x{obj.hits}", (u + size + 2, v + 4))
    if robot is not None:
        x, y, yaw = robot
        centre = px(x, y)
        tip = px(x + max(HEADING_LENGTH_M, 8 / k) * math.cos(yaw),
                 y + max(HEADING_LENGTH_M, 8 / k) * math.sin(yaw))
        radius = max(3, int(round(ROBOT_GEOMETRY.radius_m * k)))
        cv2.circle(image, centre, radius + 1, (255, 255, 255), 1, cv2.LINE_AA)  # stands out on blue
        cv2.circle(image, centre, radius, ROBOT, -1, cv2.LINE_AA)
        cv2.line(image, centre, tip, (0, 0, 0), 2, cv2.LINE_AA)
    return image


def write_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Write ``image`` as a PNG at ``path`` atomically (:func:`shared.atomic.write_atomic`);
    returns the path.

    A viewer that reloads the file while a search runs never sees half a
    picture. Raises ``ValueError`` when OpenCV cannot encode the image and
    ``OSError`` when the file cannot be written (e.g. a missing directory).
    """
    target = Path(path)
    try:
        ok, data = cv2.imencode(".png", image)
    except cv2.error as exc:
        raise ValueError(f"cannot encode a {image.dtype} {image.shape} image as PNG: "
                         f"{exc.err or exc}") from None
    if not ok:
        raise ValueError(f"cannot encode a {image.dtype} {image.shape} image as PNG")
    # readable by all (a temporary file is private): a picture is for anyone to look at
    return write_atomic(target, data.tobytes(), mode=0o644)
