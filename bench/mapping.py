"""Mapping benchmark: milliseconds per 640x480 frame for a full map update.

A full update is what the service does per frame: obstacles, explored area,
value layers (1, 3 or 10 targets) and the frontiers. Frames are rendered once
beforehand (not timed) in a generated home from seeded free poses, and fed in
order to a fresh default map (1000 x 1000 cells at 5 cm).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from rich.console import Console
from rich.table import Table

from ovamos.bench.sim import SCENE_SEED, camera_poses
from ovamos.services.mapping.state import MapState
from ovamos.world.evaluator import GroundTruth
from ovamos.world.generate import generate_scene

LAYER_COUNTS = (1, 3, 10)


def _frames(count: int) -> list[Any]:
    from ovamos.world.render import SceneRenderer
    scene = generate_scene(SCENE_SEED)
    with SceneRenderer(scene, 640, 480) as renderer:
        return [renderer.render(x, y, yaw, seq=i)
                for i, (x, y, yaw) in enumerate(camera_poses(GroundTruth(scene), count))]


def _run(frames: list[Any], layers: int) -> list[float]:
    targets = [f"target{i}" for i in range(layers)]
    state = MapState(targets=targets)
    scores = {t: 0.3 + 0.01 * i for i, t in enumerate(targets)}
    times = []
    for frame in frames:
        start = time.perf_counter()
        state.integrate(frame, scores)
        state.frontiers()
        times.append(time.perf_counter() - start)
    return times


def run_benchmark(frames: int = 40, runs: int = 3, progress: Console | None = None) -> dict[str, Any]:
    rendered = _frames(frames)
    result: dict[str, Any] = {"frames_per_run": frames, "runs": runs, "median_ms": {}, "run_ms": {}}
    for layers in LAYER_COUNTS:
        medians = [statistics.median(_run(rendered, layers)) * 1e3 for _ in range(runs)]
        result["median_ms"][str(layers)] = round(statistics.median(medians), 2)
        result["run_ms"][str(layers)] = [round(m, 2) for m in medians]
        if progress:
            progress.print(f"{layers} layer(s): {result['median_ms'][str(layers)]:.2f} ms/frame")
    return result


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("target layers", "median ms / frame", "runs (ms)",
                  title=f"Full map update per 640x480 frame, 1000x1000 grid; median of "
                        f"{result['runs']} runs x {result['frames_per_run']} frames")
    for layers in LAYER_COUNTS:
        key = str(layers)
        table.add_row(key, f"{result['median_ms'][key]:.2f}",
                      ", ".join(f"{m:.2f}" for m in result["run_ms"][key]))
    console.print(table)
