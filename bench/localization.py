"""Localization benchmark: milliseconds per 640x480 frame for matching a frame against the map.

A simulated robot with realistic odometry (services/sim/odometry.py) looks around and wanders a
generated home in primitives (seeded); each frame, rendered beforehand (not timed) at its true pose
and posed by its odometry, is fused into a fresh default map (1000 x 1000 cells at 5 cm) with
localization on, and the localizer's match (thinning, fields, Gauss-Newton, the checks) is timed,
not the projection the map makes of every frame anyway.
"""

from __future__ import annotations

import statistics
import time
from collections import Counter
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from ovamos.bench.sim import SCENE_SEED
from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.localization import LocalizationConfig, Match
from ovamos.services.mapping.state import MapState
from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.shared.motion import Action, Pose
from ovamos.world.evaluator import GroundTruth
from ovamos.world.generate import generate_scene

WALK_SEED = 0


def _walk(truth: GroundTruth, steps: int) -> list[tuple[Pose, Pose]]:
    """(true pose, odometry) after each of ``steps`` primitives: a look-around, then ahead until
    blocked, then a turn either way (seeded)."""
    rng = np.random.default_rng(WALK_SEED)
    rows, cols = np.nonzero(truth.free)
    pick = int(rng.integers(len(rows)))
    x, y = truth.grid.to_world(rows[pick], cols[pick])
    robot = SimRobot(Pose(x=float(x), y=float(y), yaw=0.0), truth.is_free,
                     MotionConfig(odometry="realistic", odometry_seed=WALK_SEED))
    poses = [(robot.pose, robot.odom)]
    for step in range(steps - 1):
        if step < 12:
            robot.apply(Action.TURN_LEFT)
        elif not robot.apply(Action.MOVE_FORWARD) or rng.random() < 0.1:
            robot.apply(Action.TURN_LEFT if rng.random() < 0.5 else Action.TURN_RIGHT)
        poses.append((robot.pose, robot.odom))
    return poses


def _frames(count: int) -> list[Any]:
    from ovamos.world.render import SceneRenderer
    scene = generate_scene(SCENE_SEED)
    with SceneRenderer(scene, 640, 480) as renderer:
        return [renderer.render(true.x, true.y, true.yaw, seq=i, stamp=float(i), posed_at=odom)
                for i, (true, odom) in enumerate(_walk(GroundTruth(scene), count))]


def _run(frames: list[Any]) -> tuple[list[float], Counter[str]]:
    state = MapState(MappingConfig(localization=LocalizationConfig(enabled=True)))
    localizer = state.localizer
    assert localizer is not None
    match, times = localizer.match, []

    def timed(*args: Any) -> Match:
        start = time.perf_counter()
        result = match(*args)
        times.append(time.perf_counter() - start)
        return result

    localizer.match = timed
    for frame in frames:
        state.integrate(frame)
    return times, localizer.counters


def run_benchmark(frames: int = 60, runs: int = 3, progress: Console | None = None) -> dict[str, Any]:
    rendered = _frames(frames)
    medians, p95s, verdicts = [], [], Counter[str]()
    for _ in range(runs):
        times, verdicts = _run(rendered)
        medians.append(statistics.median(times) * 1e3)
        p95s.append(float(np.percentile(times, 95)) * 1e3)
        if progress:
            progress.print(f"run {len(medians)}: median {medians[-1]:.2f} ms, p95 {p95s[-1]:.2f} ms")
    return {"frames_per_run": frames, "runs": runs, "median_ms": round(statistics.median(medians), 2),
            "p95_ms": round(statistics.median(p95s), 2), "run_median_ms": [round(m, 2) for m in medians],
            "verdicts": dict(sorted(verdicts.items()))}


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("median ms / frame", "p95 ms / frame", "runs (median ms)", "matches by verdict (one run)",
                  title=f"Localization per 640x480 frame, 1000x1000 grid; median of {result['runs']} runs x "
                        f"{result['frames_per_run']} frames")
    table.add_row(f"{result['median_ms']:.2f}", f"{result['p95_ms']:.2f}",
                  ", ".join(f"{m:.2f}" for m in result["run_median_ms"]),
                  ", ".join(f"{k} {v}" for k, v in result["verdicts"].items()))
    console.print(table)
