"""Top-down pictures of scenes (rooms, walls, objects with labels, robot and path).

People debug searches by looking: this is the picture ``ovamos sim scene``
writes, and later benchmarks draw trajectories on it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from ovamos.shared.camera import DEPTH_RANGE_M
from ovamos.shared.messages import RgbdFrame
from ovamos.shared.motion import Pose
from ovamos.shared.robot import ROBOT
from ovamos.world.occupancy import box_corners, wall_corners
from ovamos.world.scene import Scene

ROOM_COLOURS = {  # BGR, light so labels stay readable
    "kitchen": (200, 230, 250), "living_room": (210, 240, 210), "bedroom": (240, 220, 215),
    "bathroom": (245, 240, 200), "office": (225, 225, 225), "dining_room": (215, 215, 245),
}
MARGIN_M = 0.3


class _Canvas:
    def __init__(self, scene: Scene, px_per_m: float) -> None:
        self.scene, self.k = scene, px_per_m
        w = int(math.ceil((scene.width + 2 * MARGIN_M) * px_per_m))
        h = int(math.ceil((scene.depth + 2 * MARGIN_M) * px_per_m))
        self.image = np.full((h, w, 3), 255, np.uint8)

    def px(self, xy: np.ndarray) -> np.ndarray:
        """World metres -> pixels (y up in the world is up in the picture)."""
        xy = np.asarray(xy, float)
        u = (xy[..., 0] + MARGIN_M) * self.k
        v = self.image.shape[0] - (xy[..., 1] + MARGIN_M) * self.k
        return np.stack([u, v], -1)

    def poly(self, corners: np.ndarray, colour: tuple[int, int, int], outline: bool = True) -> None:
        pts = np.round(self.px(corners)).astype(np.int32)
        cv2.fillPoly(self.image, [pts], colour, cv2.LINE_AA)
        if outline:
            cv2.polylines(self.image, [pts], True, (60, 60, 60), 1, cv2.LINE_AA)

    def text(self, label: str, xy: tuple[float, float], scale: float = 0.35,
             colour: tuple[int, int, int] = (30, 30, 30)) -> None:
        u, v = np.round(self.px(np.array(xy))).astype(int)
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        cv2.putText(self.image, label, (int(u - tw / 2), int(v + th / 2)), cv2.FONT_HERSHEY_SIMPLEX,
                    scale, colour, 1, cv2.LINE_AA)


def _bgr(rgba: Sequence[float]) -> tuple[int, int, int]:
    return int(rgba[2] * 255), int(rgba[1] * 255), int(rgba[0] * 255)


def draw_scene(scene: Scene, *, px_per_m: float = 60.0, robot: Pose | None = None,
               path: Sequence[tuple[float, float]] = (), labels: bool = True) -> np.ndarray:
    """A BGR image of the scene seen from above."""
    canvas = _Canvas(scene, px_per_m)
    for room in scene.rooms:
        corners = np.array([[room.x0, room.y0], [room.x1, room.y0], [room.x1, room.y1], [room.x0, room.y1]])
        canvas.poly(corners, ROOM_COLOURS.get(room.type, (235, 235, 235)), outline=False)
    for obj in sorted(scene.objects, key=lambda o: o.z):
        canvas.poly(box_corners(obj.x, obj.y, obj.sx, obj.sy, obj.yaw), _bgr(obj.rgba))
    for wall in scene.walls:
        canvas.poly(wall_corners(wall.x0, wall.y0, wall.x1, wall.y1), (40, 40, 40), outline=False)
    if labels:
        for room in scene.rooms:
            canvas.text(room.type.replace("_", " "), ((room.x0 + room.x1) / 2, room.y1 - 0.25),
                        0.5, (90, 90, 90))
        for obj in scene.objects:
            canvas.text(obj.cls.replace("_", " "), (obj.x, obj.y), 0.3)
    if len(path) > 1:
        pts = np.round(canvas.px(np.array(path))).astype(np.int32)
        cv2.polylines(canvas.image, [pts], False, (200, 60, 20), 2, cv2.LINE_AA)
    if robot is not None:
        centre = np.round(canvas.px(np.array([robot.x, robot.y]))).astype(int)
        tip = np.round(canvas.px(np.array([robot.x + 0.35 * math.cos(robot.yaw),
                                           robot.y + 0.35 * math.sin(robot.yaw)]))).astype(int)
        cv2.circle(canvas.image, tuple(centre), int(ROBOT.radius_m * px_per_m), (200, 60, 20), -1, cv2.LINE_AA)
        cv2.line(canvas.image, tuple(centre), tuple(tip), (0, 0, 0), 2, cv2.LINE_AA)
    return canvas.image


def side_by_side(frame: RgbdFrame, max_depth_m: float = DEPTH_RANGE_M[1]) -> np.ndarray:
    """One BGR image of a frame: colour | depth (turbo, black = no reading) | instance ids."""
    bgr = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
    depth = frame.depth.astype(np.float32) * frame.depth_scale
    scaled = np.clip(depth / max_depth_m * 255, 0, 255).astype(np.uint8)
    depth_img = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    depth_img[depth <= 0] = 0
    panels = [bgr, depth_img]
    if frame.instance_ids is not None:
        ids = frame.instance_ids.astype(np.int64)
        hashed = (ids * 2654435761) % (1 << 24)  # Knuth's multiplicative hash: distinct colours
        id_img = np.stack([hashed & 255, (hashed >> 8) & 255, (hashed >> 16) & 255], -1).astype(np.uint8)
        id_img[ids == 0] = 0
        panels.append(id_img)
    return np.hstack(panels)
