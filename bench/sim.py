"""Simulator benchmark: rendered RGB-D frames per second.

Times the whole :meth:`ovamos.world.render.SceneRenderer.render` call (camera
placement, the lit and segmentation passes, read-back, metric depth and
instance ids, the :class:`~ovamos.shared.messages.RgbdFrame`) at 640x480 and 320x240,
in a procedurally generated home (fixed seed), from seeded random robot poses
in its free space: what the search benchmark renders.
"""

from __future__ import annotations

import math
import statistics
import time
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from ovamos.world.evaluator import GroundTruth
from ovamos.world.generate import generate_scene

RESOLUTIONS = ((640, 480), (320, 240))
WARMUP = 3
SCENE_SEED = 4  # a 144 m2, 8-room home with 47 objects


def camera_poses(truth: GroundTruth, frames: int, seed: int = 0) -> list[tuple[float, float, float]]:
    """``frames`` seeded robot poses (x, y, yaw) in the scene's free space."""
    rng = np.random.default_rng(seed)
    rows, cols = np.nonzero(truth.free)
    picks = rng.integers(len(rows), size=frames)
    xs, ys = truth.grid.to_world(rows[picks], cols[picks])
    return [(float(x), float(y), float(rng.uniform(-math.pi, math.pi))) for x, y in zip(xs, ys)]


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
    except Exception:
        return "unknown"


def run_benchmark(frames: int = 50, runs: int = 3, progress: Console | None = None
                  ) -> dict[str, Any]:
    from ovamos.world.render import SceneRenderer

    if frames < 1 or runs < 1:
        raise ValueError("frames and runs must be at least 1")
    scene = generate_scene(SCENE_SEED)
    poses = camera_poses(GroundTruth(scene), frames)
    result: dict[str, Any] = {"frames_per_run": frames, "runs": runs, "scene_seed": SCENE_SEED,
                              "area_m2": round(scene.area, 1), "objects": len(scene.objects),
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
                  title=f"Rendered RGB-D + instance-id frames in home {result['scene_seed']} "
                        f"({result['area_m2']} m2, {result['rooms']} rooms, {result['objects']} "
                        f"objects); median of {result['runs']} runs x {result['frames_per_run']} frames")
    for width, height in RESOLUTIONS:
        key = f"fps_{width}x{height}"
        fps = result[key]
        table.add_row(f"{width}x{height}", f"{fps:.1f}", f"{1e3 / fps:.1f}",
                      ", ".join(f"{r:.1f}" for r in result[f"run_{key}"]))
    console.print(table)
    console.print(f"OpenGL renderer: {result.get('gl_renderer', 'unknown')}")
