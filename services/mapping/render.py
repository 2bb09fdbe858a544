"""Pictures of the mapping service's state, for people debugging a search.

One BGR image of a :class:`~ovamos.shared.messages.MapSnapshot` seen from above (image
up = world +y, as in :mod:`ovamos.world.draw`): unexplored cells dark grey,
explored free cells light, obstacles black, the value map the planner decides on
(decayed, :func:`value_image`) as a heat map over explored free cells, frontier waypoints,
object instances with their labels, and optionally the robot with its heading, its path, the
planner's goal and the targets the task found; a legend to the right says what each mark means.
By default the picture is cropped to what has been explored (plus a margin): the service's grid
is sized for the largest home, and early in a search almost all of it is unknown.

The map outlives a task and holds objects of every label it ever searched for: only objects
whose label is one of the task's ``targets`` are drawn as its detections (green: confirmed,
orange: not yet); the others are grey. Labels are placed where they overlap no other label nor
mark and stay inside the map (:func:`place_labels`); one that finds no room gets a number on the
map and its text in the legend.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ovamos.services.mapping.layers import DECAY_KAPPA, DECAY_TAU, value_map
from ovamos.shared.atomic import write_atomic
from ovamos.shared.messages import FoundObject, Goal, MapSnapshot
from ovamos.shared.robot import ROBOT as ROBOT_GEOMETRY

__all__ = ["LEGEND", "crop_box", "map_raster", "place_labels", "render_map", "value_image", "write_png"]

UNEXPLORED = (70, 70, 70)     # BGR
FREE = (235, 235, 235)
OBSTACLE = (0, 0, 0)
FRONTIER = (200, 0, 200)
ROBOT = (200, 60, 20)
PATH = (200, 60, 20)
GOAL = (38, 38, 220)          # red ring with a dot, as the page draws it (#dc2626)
CONFIRMED = (40, 170, 40)     # green ring: a detection the planner may stop at
UNCONFIRMED = (0, 140, 255)   # orange ring: seen, not yet trusted
OTHER = (160, 160, 160)       # grey ring: an object of a label this task does not search
FOUND = (74, 163, 22)         # filled square, white border: a target the task declared found
INK = (20, 20, 20)
PANEL = (255, 255, 255)
COLORMAP = cv2.COLORMAP_TURBO  # blue (low) -> red (high), as the sim draws depth
FONT = cv2.FONT_HERSHEY_SIMPLEX
LABEL_SCALE = 0.4
LEGEND_SCALE = 0.4
LEGEND_WIDTH = 200            # pixels, right of the map
LEGEND_ROW = 17
LABEL_REACH = 3               # label heights a label may go from its mark (leader line): else a number


def value_image(snapshot: MapSnapshot, layer: str | None = None, *, tau: float = DECAY_TAU,
                kappa: float = DECAY_KAPPA) -> np.ndarray:
    """The value map shown by :func:`render_map`: H x W float in [0, 1].

    The map the planner decides on (:func:`ovamos.services.mapping.layers.value_map`: each
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


# -- labels ----------------------------------------------------------------------------------------
Rect = tuple[int, int, int, int]  # x0, y0, x1, y1 (end-exclusive) in pixels


class _Placer:
    """Greedy label placement: each label goes to the first free spot, nearest its anchor first."""

    # right, left, above, below, then the diagonals and between: a label reads best beside its mark
    ANGLES = np.deg2rad([0, 180, -90, 90, -35, 35, -145, 145, -65, 65, -115, 115, -15, 15, -165, 165])

    def __init__(self, size: tuple[int, int], avoid: Sequence[Rect] = (), clearance: int = 6) -> None:
        self.width, self.height = size
        self.taken = np.array(avoid, float).reshape(-1, 4)
        self.clearance = clearance

    def _free(self, x0: np.ndarray, y0: np.ndarray, w: int, h: int) -> np.ndarray:
        """Which of the rectangles at (x0, y0) of size (w, h) lie inside and overlap nothing taken."""
        ok = (x0 >= 0) & (y0 >= 0) & (x0 + w <= self.width) & (y0 + h <= self.height)
        t = self.taken
        for lo in range(0, len(x0), 4096):  # in chunks: a big picture has many grid spots
            part = np.s_[lo:lo + 4096]
            xs, ys = x0[part, None], y0[part, None]
            ok[part] &= ~((xs < t[:, 2]) & (xs + w > t[:, 0]) & (ys < t[:, 3]) & (ys + h > t[:, 1])).any(axis=1)
        return ok

    def place(self, anchor: tuple[float, float], size: tuple[int, int], clearance: int | None = None,
              reach: float | None = None) -> tuple[Rect, bool] | None:
        """The free rectangle of ``size`` (w, h) nearest ``anchor``, at least ``clearance`` pixels
        from it and at most about ``reach`` more (default: anywhere in the picture), and whether
        it is away from it (worth a leader line), now taken; None when no such spot is free.

        First the spots beside the anchor and on rings around it, one label height apart (16
        directions each); then, as those are sparse far out, every spot of a 3-pixel grid within
        reach, nearest first."""
        w, h = size
        clearance = self.clearance if clearance is None else clearance
        if w > self.width or h > self.height:
            return None
        step = max(h, 6)
        reach = math.hypot(self.width, self.height) if reach is None else reach
        s, a = np.meshgrid(np.arange(int(reach // step) + 1) * step, self.ANGLES, indexing="ij")
        s = s.ravel()  # ring-major: nearer rings first
        x0 = np.round(anchor[0] + np.cos(a.ravel()) * (clearance + w / 2 + s) - w / 2)
        y0 = np.round(anchor[1] + np.sin(a.ravel()) * (clearance + h / 2 + s) - h / 2)
        free = np.flatnonzero(self._free(x0, y0, w, h))
        away = bool(free.size and s[free[0]] > 0)
        if free.size == 0:
            gx, gy = np.meshgrid(np.arange(0, self.width - w + 1, 3, dtype=float),
                                 np.arange(0, self.height - h + 1, 3, dtype=float))
            x0, y0 = gx.ravel(), gy.ravel()
            # how far the rectangle's nearest point is from the anchor
            du = np.maximum(np.maximum(x0 - anchor[0], anchor[0] - (x0 + w)), 0)
            dv = np.maximum(np.maximum(y0 - anchor[1], anchor[1] - (y0 + h)), 0)
            gap = np.hypot(du, dv)
            near = np.flatnonzero((gap >= clearance) & (gap <= clearance + reach))
            near = near[np.argsort(gap[near], kind="stable")]
            x0, y0 = x0[near], y0[near]
            free = np.flatnonzero(self._free(x0, y0, w, h))
            away = True
            if free.size == 0:
                return None
        i = free[0]
        rect = (int(x0[i]), int(y0[i]), int(x0[i]) + w, int(y0[i]) + h)
        self.taken = np.vstack([self.taken, rect])
        return rect, away


def place_labels(anchors: Sequence[tuple[float, float]], sizes: Sequence[tuple[int, int]],
                 bounds: tuple[int, int], avoid: Sequence[Rect] = (), clearance: int = 6
                 ) -> list[Rect | None]:
    """Rectangles (x0, y0, x1, y1, end-exclusive pixels) for labels of ``sizes`` (w, h) at
    ``anchors`` (u, v) inside a ``bounds`` (width, height) picture, in order: none overlaps
    another nor a rectangle of ``avoid`` (the marks), each as near its anchor as it can be
    (at least ``clearance`` pixels from it: beside its mark). None for a label with no room left.
    """
    placer = _Placer(bounds, avoid, clearance)
    placed = [placer.place(a, s) for a, s in zip(anchors, sizes)]
    return [p[0] if p else None for p in placed]


@dataclass
class _Label:
    text: str
    anchor: tuple[int, int]
    clearance: int  # from the anchor: past its mark
    colour: tuple[int, int, int] = INK
    numbered: bool = True  # without room: a number on the map and the text in the legend


def _text_size(text: str, scale: float) -> tuple[int, int, int]:
    (w, h), base = cv2.getTextSize(text, FONT, scale, 1)
    return w, h, base


def _boxed(text: str) -> tuple[int, int]:
    """The size (w, h) of ``text``'s label: the text on a light box with a pixel of margin."""
    w, h, base = _text_size(text, LABEL_SCALE)
    return w + 4, h + base + 3


def _draw_label(image: np.ndarray, text: str, rect: Rect, colour: tuple[int, int, int]) -> None:
    """``text`` in ``rect`` on a light, slightly see-through box: readable over any map colour."""
    x0, y0, x1, y1 = rect
    box = image[y0:y1, x0:x1]
    box[:] = (box * 0.2 + 255 * 0.8).astype(np.uint8)
    _, h, _ = _text_size(text, LABEL_SCALE)
    cv2.putText(image, text, (x0 + 2, y0 + 1 + h), FONT, LABEL_SCALE, colour, 1, cv2.LINE_AA)


def _leader(image: np.ndarray, anchor: tuple[int, int], rect: Rect) -> None:
    """A thin line from a mark to its label placed away from it."""
    u = min(max(anchor[0], rect[0]), rect[2] - 1)
    v = min(max(anchor[1], rect[1]), rect[3] - 1)
    cv2.line(image, anchor, (u, v), INK, 1, cv2.LINE_AA)


def _draw_labels(image: np.ndarray, labels: Sequence[_Label], avoid: Sequence[Rect]) -> list[str]:
    """Place and draw ``labels`` (in order of importance) over the map; the legend's lines for
    those that found no room near their mark ("3 cup x2": the number drawn at the mark), in order.

    A label goes beside its mark, or a little farther with a leader line; one with no room
    within ``LABEL_REACH`` label heights gets a number instead (placed as near as it can be;
    "- cup x2" in the legend when even that finds no room), or, for an earlier task's object,
    nothing. Leaders are drawn first: no line crosses a label."""
    placer = _Placer((image.shape[1], image.shape[0]), avoid)
    drawn: list[tuple[str, Rect, _Label, bool]] = []
    unplaced: list[_Label] = []
    for label in labels:
        size = _boxed(label.text)
        spot = placer.place(label.anchor, size, label.clearance, LABEL_REACH * size[1])
        if spot is not None:
            drawn.append((label.text, spot[0], label, spot[1]))
        elif label.numbered:
            unplaced.append(label)
    listed = []
    for n, label in enumerate(unplaced, start=1):
        spot = placer.place(label.anchor, _boxed(str(n)), label.clearance)
        if spot is not None:
            drawn.append((str(n), spot[0], label, spot[1]))
        listed.append(f"{n} {label.text}" if spot is not None else f"- {label.text}")
    for _, rect, label, away in drawn:
        if away:
            _leader(image, label.anchor, rect)
    for text, rect, label, _ in drawn:
        _draw_label(image, text, rect, label.colour)
    return listed


# -- marks -----------------------------------------------------------------------------------------
def _ring(image: np.ndarray, at: tuple[int, int], radius: int, colour: tuple[int, int, int],
          thickness: int = 2) -> None:
    """A coloured ring with a dark edge: visible over the heat map's colours too."""
    cv2.circle(image, at, radius, (30, 30, 30), thickness + 2, cv2.LINE_AA)
    cv2.circle(image, at, radius, colour, thickness, cv2.LINE_AA)


def _square(image: np.ndarray, at: tuple[int, int], half: int, colour: tuple[int, int, int]) -> None:
    u, v = at
    cv2.rectangle(image, (u - half - 1, v - half - 1), (u + half + 1, v + half + 1), (255, 255, 255), -1)
    cv2.rectangle(image, (u - half, v - half), (u + half, v + half), colour, -1)


def _goal(image: np.ndarray, at: tuple[int, int], radius: int) -> None:
    """The planner's goal: a red ring with a red dot in it."""
    _ring(image, at, radius, GOAL)
    cv2.circle(image, at, max(1, radius // 4), GOAL, -1, cv2.LINE_AA)


def _robot(image: np.ndarray, centre: tuple[int, int], radius: int, yaw: float) -> Rect:
    """The robot: a blue disc with a white edge and an arrow along its heading, long enough to
    stand out of the disc at any scale; the rectangle it covers."""
    length = max(2.2 * radius, radius + 10)
    tip = (int(round(centre[0] + length * math.cos(yaw))), int(round(centre[1] - length * math.sin(yaw))))
    cv2.circle(image, centre, radius + 1, (255, 255, 255), 1, cv2.LINE_AA)  # stands out on blue
    cv2.circle(image, centre, radius, ROBOT, -1, cv2.LINE_AA)
    # a white edge out of the disc only (inside it, black on blue needs none); heads of 7 pixels
    rim = (int(round(centre[0] + radius * math.cos(yaw))), int(round(centre[1] - radius * math.sin(yaw))))
    cv2.arrowedLine(image, rim, tip, (255, 255, 255), 4, cv2.LINE_AA, tipLength=min(0.9, 7 / (length - radius)))
    cv2.arrowedLine(image, centre, tip, (0, 0, 0), 2, cv2.LINE_AA, tipLength=min(0.5, 7 / length))
    return (min(centre[0] - radius, tip[0] - 4) - 1, min(centre[1] - radius, tip[1] - 4) - 1,
            max(centre[0] + radius, tip[0] + 4) + 2, max(centre[1] + radius, tip[1] + 4) + 2)


# -- the legend ------------------------------------------------------------------------------------
def _fit(text: str, width: int, scale: float = LEGEND_SCALE) -> str:
    """``text`` cut (with "..") to fit ``width`` pixels."""
    if _text_size(text, scale)[0] <= width:
        return text
    while text and _text_size(text + "..", scale)[0] > width:
        text = text[:-1]
    return text + ".."


Swatch = Callable[[np.ndarray, int, int], object]  # draws into the legend at (x, the row's middle)


def _swatch_box(colour: tuple[int, int, int], edge: tuple[int, int, int] | None = None) -> Swatch:
    def draw(panel: np.ndarray, x: int, mid: int) -> None:
        cv2.rectangle(panel, (x, mid - 5), (x + SWATCH, mid + 5), colour, -1)
        if edge is not None:
            cv2.rectangle(panel, (x, mid - 5), (x + SWATCH, mid + 5), edge, 1)
    return draw


def _swatch_ramp(panel: np.ndarray, x: int, mid: int) -> None:
    ramp = cv2.applyColorMap(np.linspace(0, 255, SWATCH + 1).astype(np.uint8)[None, :], COLORMAP)
    panel[mid - 5:mid + 6, x:x + SWATCH + 1] = ramp


def _swatch_ring(colour: tuple[int, int, int]) -> Swatch:
    return lambda panel, x, mid: _ring(panel, (x + SWATCH // 2, mid), 5, colour)


SWATCH = 30  # pixels
LEGEND: tuple[tuple[str, Swatch], ...] = (
    ("unexplored", _swatch_box(UNEXPLORED)),
    ("free", _swatch_box(FREE, (150, 150, 150))),
    ("obstacle", _swatch_box(OBSTACLE)),
    ("value low -> high", _swatch_ramp),
    ("frontier", lambda panel, x, mid: cv2.circle(panel, (x + SWATCH // 2, mid), 4, FRONTIER, 1)),
    ("path", lambda panel, x, mid: (cv2.line(panel, (x, mid), (x + SWATCH, mid), (200, 200, 200), 3),
                                     cv2.line(panel, (x, mid), (x + SWATCH, mid), PATH, 1))),
    ("robot, heading", lambda panel, x, mid: _robot(panel, (x + 8, mid), 5, 0.0)),
    ("goal", lambda panel, x, mid: _goal(panel, (x + SWATCH // 2, mid), 7)),
    ("detection, confirmed", _swatch_ring(CONFIRMED)),
    ("detection, unconfirmed", _swatch_ring(UNCONFIRMED)),
    ("found target", lambda panel, x, mid: _square(panel, (x + SWATCH // 2, mid), 5, FOUND)),
    ("other task's object", _swatch_ring(OTHER)),
)
"""The legend's entries, in order: what each mark and colour of the picture means, and how its
swatch is drawn."""


def _legend(height: int, targets: Sequence[str], layer: str | None, listed: Sequence[str]
            ) -> np.ndarray:
    """The legend beside the map: the targets and the value layer shown, each mark and colour,
    then the labels that found no room on the map (by their number there)."""
    rows = 2 + len(LEGEND) + (1 + len(listed) if listed else 0)
    panel = np.full((max(height, 8 + rows * LEGEND_ROW), LEGEND_WIDTH, 3), PANEL, np.uint8)
    cv2.line(panel, (0, 0), (0, panel.shape[0] - 1), (180, 180, 180), 1)
    x = 8
    y = 4 + LEGEND_ROW

    def line(text: str, indent: int = x) -> None:
        nonlocal y
        cv2.putText(panel, _fit(text, LEGEND_WIDTH - indent - 4), (indent, y - 4), FONT, LEGEND_SCALE,
                    INK, 1, cv2.LINE_AA)
        y += LEGEND_ROW

    line("targets: " + (", ".join(targets) or "-"))
    line("value: " + (layer if layer is not None else "all targets"))
    for name, swatch in LEGEND:
        swatch(panel, x, y - LEGEND_ROW // 2 - 2)
        line(name, x + SWATCH + 8)
    if listed:
        line("labels by number:")
        for text in listed:
            line(text, x + 6)
    return panel


# -- the picture -----------------------------------------------------------------------------------
def render_map(snapshot: MapSnapshot, *, layer: str | None = None,
               robot: tuple[float, float, float] | None = None,
               path: Sequence[tuple[float, float]] = (), targets: Sequence[str] | None = None,
               found: Sequence[FoundObject] = (), goal: Goal | None = None, crop: bool = True,
               px_per_cell: int = 2, margin_cells: int = 10, legend: bool = True,
               tau: float = DECAY_TAU, kappa: float = DECAY_KAPPA) -> np.ndarray:
    """A BGR uint8 picture of ``snapshot`` from above (see the module docstring).

    ``layer`` picks the value layer to show (``None``: all of them; either way the
    decayed map the planner decides on, :func:`value_image`, with the decay's ``tau`` and
    ``kappa``); ``robot`` is (x, y, yaw) in world metres and radians, drawn as a disc with an
    arrow along its heading; ``path`` world (x, y) points drawn as a polyline; ``found`` the
    task's found targets (filled green squares, labelled with their step); ``goal`` where the
    planner is taking the robot (a red double ring).

    ``targets`` are the task's targets (default: the snapshot's layers, which are the remaining
    targets, and the labels of ``found``): objects of other labels (an earlier task's) are
    grey; the task's confirmed ones green rings, its unconfirmed ones orange rings, each
    labelled ``label xhits`` (none for a found target's label: its square says it).

    ``crop`` keeps the bounding box of explored cells, the robot, the path, objects, frontiers,
    found targets and the goal, grown by ``margin_cells``; the whole grid when there is nothing
    to show. The map takes the top-left of the picture, ``px_per_cell`` pixels per cell;
    ``legend`` adds the legend to its right (the picture is then at least as tall as it).
    """
    if px_per_cell < 1:
        raise ValueError(f"px_per_cell must be >= 1, got {px_per_cell}")
    heat = value_image(snapshot, layer, tau=tau, kappa=kappa)  # validates the layer name first
    found = list(found)
    if targets is None:
        targets = [*snapshot.layers, *(f.label for f in found if f.label not in snapshot.layers)]
    wanted = set(targets)
    res, (x0, y0) = snapshot.resolution, snapshot.origin
    rows, cols = snapshot.obstacle.shape
    objects = np.array([(o.x, o.y) for o in snapshot.objects], float).reshape(-1, 2)
    frontiers = np.asarray(snapshot.frontiers, float).reshape(-1, 2)
    path_xy = np.asarray(path, float).reshape(-1, 2)
    extra = [objects, frontiers, path_xy, np.array([(f.x, f.y) for f in found], float).reshape(-1, 2)]
    if robot is not None:
        extra.append(np.array([robot[:2]], float))
    if goal is not None:
        extra.append(np.array([(goal.x, goal.y)], float))
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
        cv2.polylines(image, [pts], False, (255, 255, 255), 3, cv2.LINE_AA)  # shows on the blue too
        cv2.polylines(image, [pts], False, PATH, 1, cv2.LINE_AA)

    size = max(4, px_per_cell * 2)
    marks: list[Rect] = []
    first: list[_Label] = []   # found targets and the goal: placed before the detections
    labels: list[_Label] = []
    others: list[_Label] = []

    def mark(at: tuple[int, int], half: int) -> int:
        """Keep labels off a mark of ``half`` its width at ``at``; a label's clearance from it."""
        marks.append((at[0] - half - 2, at[1] - half - 2, at[0] + half + 3, at[1] + half + 3))
        return half + 4

    found_labels = {f.label for f in found}
    ours = sorted((o for o in snapshot.objects if o.label in wanted), key=lambda o: not o.confirmed)
    for obj in (o for o in snapshot.objects if o.label not in wanted):  # beneath this task's marks
        at = px(obj.x, obj.y)
        _ring(image, at, size - 1, OTHER, 1)
        others.append(_Label(obj.label, at, mark(at, size), (110, 110, 110), numbered=False))
    for obj in ours:
        at = px(obj.x, obj.y)
        _ring(image, at, size, CONFIRMED if obj.confirmed else UNCONFIRMED)
        clearance = mark(at, size)
        if obj.label not in found_labels:
            labels.append(_Label(f"{obj.label} x{obj.hits}", at, clearance))
    for f in found:
        at = px(f.x, f.y)
        _square(image, at, size + 1, FOUND)
        first.append(_Label(f"found {f.label} (step {f.step})", at, mark(at, size + 2)))
    if goal is not None:
        at = px(goal.x, goal.y)
        _goal(image, at, size + 4)
        first.append(_Label(f"goal: {goal.label or goal.kind}", at, mark(at, size + 5)))
    if robot is not None:
        x, y, yaw = robot
        radius = max(5, int(round(ROBOT_GEOMETRY.radius_m * k)))
        marks.append(_robot(image, px(x, y), radius, yaw))
    listed = _draw_labels(image, [*first, *labels, *others], marks)
    if not legend:
        return image
    panel = _legend(image.shape[0], targets, layer, listed)
    if panel.shape[0] > image.shape[0]:
        image = cv2.copyMakeBorder(image, 0, panel.shape[0] - image.shape[0], 0, 0,
                                   cv2.BORDER_CONSTANT, value=PANEL)
    return np.hstack([image, panel])


def write_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Write ``image`` as a PNG at ``path`` atomically (:func:`ovamos.shared.atomic.write_atomic`);
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
