"""Simulator benchmark: rendered RGB-D frames per second.

Times the whole :meth:`services.sim.render.SceneRenderer.render` call (camera
placement, the lit and segmentation passes, read-back, metric depth and
instance ids, the :class:`~shared.messages.RgbdFrame`) at 640x480 and 320x240,
with the camera moving along a fixed path through a fixed house: about 8 x 8 m,
five rooms with doorways, 60 boxes. The house is built here from a seeded RNG,
not by the procedural generator, so the numbers stay comparable while that
generator changes.
"""

from __future__ import annotations

import math
import statistics
import time
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from services.sim.world import Room, Scene, SceneObject, Wall

RESOLUTIONS = ((640, 480), (320, 240))
WARMUP = 3
DOOR_M = 0.9
OBJECT_CLASSES = ("chair", "table", "sofa", "bed", "plant", "tv", "cabinet", "box", "lamp", "cup")


def _wall_with_door(x0: float, y0: float, x1: float, y1: float, door_at: float | None
                    ) -> list[Wall]:
    """A wall from (x0, y0) to (x1, y1), split around a doorway centred ``door_at`` along it."""
    if door_at is None:
        return [Wall(x0=x0, y0=y0, x1=x1, y1=y1)]
    length = math.hypot(x1 - x0, y1 - y0)
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    a, b = door_at - DOOR_M / 2, door_at + DOOR_M / 2
    return [Wall(x0=x0, y0=y0, x1=x0 + ux * a, y1=y0 + uy * a),
            Wall(x0=x0 + ux * b, y0=y0 + uy * b, x1=x1, y1=y1)]


# A closed tour through the living room, kitchen, office and bedroom, via their doorways.
WAYPOINTS = ((1.5, 1.5), (4.0, 2.0), (6.7, 2.0), (6.7, 6.0), (6.7, 2.6), (4.0, 2.6), (1.8, 3.0),
             (1.8, 6.0), (1.5, 1.5))


def _distance_to_tour(x: float, y: float) -> float:
    pts = np.asarray(WAYPOINTS)
    a, d = pts[:-1], np.diff(pts, axis=0)
    t = np.clip(((np.array([x, y]) - a) * d).sum(1) / (d * d).sum(1), 0.0, 1.0)
    return float(np.hypot(*(a + d * t[:, None] - (x, y)).T).min())


def bench_scene(seed: int = 7, n_objects: int = 60) -> Scene:
    """A fixed 8 x 8 m house: five rooms, interior walls with doorways, boxes of many sizes."""
    rng = np.random.default_rng(seed)
    rooms = (
        Room(id=0, type="living_room", x0=0.0, y0=0.0, x1=5.0, y1=4.0),
        Room(id=1, type="kitchen", x0=5.0, y0=0.0, x1=8.0, y1=4.0),
        Room(id=2, type="bedroom", x0=0.0, y0=4.0, x1=3.5, y1=8.0),
        Room(id=3, type="bathroom", x0=3.5, y0=4.0, x1=5.5, y1=8.0),
        Room(id=4, type="office", x0=5.5, y0=4.0, x1=8.0, y1=8.0),
    )
    walls = [  # the outline, then interior walls with a doorway each
        Wall(x0=0, y0=0, x1=8, y1=0), Wall(x0=8, y0=0, x1=8, y1=8),
        Wall(x0=8, y0=8, x1=0, y1=8), Wall(x0=0, y0=8, x1=0, y1=0),
        *_wall_with_door(5.0, 0.0, 5.0, 4.0, 2.0),
        *_wall_with_door(0.0, 4.0, 3.5, 4.0, 1.8),
        *_wall_with_door(3.5, 4.0, 5.5, 4.0, 1.0),
        *_wall_with_door(5.5, 4.0, 8.0, 4.0, 1.2),
        *_wall_with_door(3.5, 4.0, 3.5, 8.0, 2.5),
        *_wall_with_door(5.5, 4.0, 5.5, 8.0, None),
    ]
    objects = []
    for i in range(n_objects):
        room = rooms[i % len(rooms)]
        for _ in range(1000):  # keep the camera's tour clear: the camera never starts inside a box
            sx, sy, sz = rng.uniform(0.1, 1.2), rng.uniform(0.1, 1.0), rng.uniform(0.1, 1.6)
            margin = 0.1 + max(sx, sy) / 2
            x = float(rng.uniform(room.x0 + margin, room.x1 - margin))
            y = float(rng.uniform(room.y0 + margin, room.y1 - margin))
            if _distance_to_tour(x, y) > 0.4 + math.hypot(sx, sy) / 2:
                break
        objects.append(SceneObject(
            id=i + 1, cls=OBJECT_CLASSES[i % len(OBJECT_CLASSES)], room=room.id, x=x, y=y,
            z=0.0, sx=float(sx), sy=float(sy), sz=float(sz),
            yaw=float(rng.uniform(-math.pi, math.pi)),
            rgba=(*(float(c) for c in rng.uniform(0.1, 0.95, 3)), 1.0)))
    return Scene(seed=seed, width=8.0, depth=8.0, rooms=rooms, walls=tuple(walls),
                 objects=tuple(objects))


def camera_path(frames: int) -> list[tuple[float, float, float]]:
    """``frames`` poses (x, y, yaw) evenly spaced along the tour, looking ahead and swaying."""
    pts = np.asarray(WAYPOINTS)
    seg = np.diff(pts, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    poses = []
    for i in range(frames):
        s = cum[-1] * i / frames
        k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
        x, y = pts[k] + seg[k] * (s - cum[k]) / (cum[k + 1] - cum[k])
        yaw = math.atan2(seg[k, 1], seg[k, 0]) + 0.7 * math.sin(2 * math.pi * 5 * i / frames)
        poses.append((float(x), float(y), yaw))
    return poses


def _fps(renderer: Any, poses: list[tuple[float, float, float]]) -> float:
    start = time.perf_counter()
    for seq, (x, y, yaw) in enumerate(poses):
        renderer.render(x, y, yaw, seq=seq, stamp=time.time())
    return len(poses) / (time.perf_counter() - start)


def _gl_renderer() -> str:
    """The OpenGL renderer of the current context (say llvmpipe: CPU, or a GPU's name)."""
    try:
        from OpenGL import GL

        return GL.glGetString(GL.GL_RENDERER).decode()
    except Exception:  # noqa: BLE001 - informative only
        return "unknown"


def run_benchmark(frames: int = 50, runs: int = 3, progress: Console | None = None
                  ) -> dict[str, Any]:
    from services.sim.render import SceneRenderer

    if frames < 1 or runs < 1:
        raise ValueError("frames and runs must be at least 1")
    scene = bench_scene()
    poses = camera_path(frames)
    result: dict[str, Any] = {"frames_per_run": frames, "runs": runs, "objects": len(scene.objects),
                              "walls": len(scene.walls), "rooms": len(scene.rooms)}
    for width, height in RESOLUTIONS:
        key = f"fps_{width}x{height}"
        with SceneRenderer(scene, width, height) as renderer:
            for x, y, yaw in poses[:WARMUP]:
                renderer.render(x, y, yaw)
            result["gl_renderer"] = _gl_renderer()  # the context is current after render()
            rates = []
            for run in range(runs):
                rates.append(_fps(renderer, poses))
                if progress:
                    progress.print(f"{width}x{height} run {run + 1}/{runs}: "
                                   f"{rates[-1]:.1f} frames/s")
        result[key] = round(statistics.median(rates), 1)
        result[f"run_{key}"] = [round(r, 1) for r in rates]
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("resolution", "frames/s", "ms/frame", "runs (frames/s)",
                  title=f"Rendered RGB-D + instance-id frames, {result['rooms']} rooms, "
                        f"{result['walls']} walls, {result['objects']} boxes; median of "
                        f"{result['runs']} runs x {result['frames_per_run']} frames")
    for width, height in RESOLUTIONS:
        key = f"fps_{width}x{height}"
        fps = result[key]
        table.add_row(f"{width}x{height}", f"{fps:.1f}", f"{1e3 / fps:.1f}",
                      ", ".join(f"{r:.1f}" for r in result[f"run_{key}"]))
    console.print(table)
    console.print(f"OpenGL renderer: {result.get('gl_renderer', 'unknown')}")
