"""Localization benchmark: milliseconds per 640x480 frame for matching a frame against the map.

A simulated robot with realistic odometry (services/sim/odometry.py) looks around and wanders a
generated home in primitives (seeded); each frame, rendered beforehand (not timed) at its true pose
and posed by its odometry, is fused into a fresh default map (1000 x 1000 cells at 5 cm) with
localization on, and the localizer's match (thinning, fields, Gauss-Newton, the checks) is timed,
not the projection the map makes of every frame anyway; beside it, the loop closer's time per frame
(keyframes, ties against old keyframes, solutions and the obstacles drawn again after one).
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
from ovamos.services.mapping.loops import LoopConfig
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


def _run(frames: list[Any]) -> tuple[list[float], list[float], Counter[str]]:
    """The match's seconds per frame, the loop closer's (keyframes, ties, solutions and the
    obstacles drawn again after one), and the verdicts."""
    state = MapState(MappingConfig(localization=LocalizationConfig(enabled=True), loops=LoopConfig(enabled=True)))
    localizer, loops = state.localizer, state.loops
    assert localizer is not None and loops is not None
    match, add, draw = localizer.match, loops.add, state.draw_keyframes
    times: list[float] = []
    loop_times: list[float] = []

    def timed(*args: Any) -> Match:
        start = time.perf_counter()
        result = match(*args)
        times.append(time.perf_counter() - start)
        return result

    def closing(*args: Any) -> Pose | None:
        start = time.perf_counter()
        result = add(*args)
        loop_times.append(time.perf_counter() - start)
        return result

    def drawing() -> None:  # after a solution: part of that frame's loop closure
        start = time.perf_counter()
        draw()
        loop_times[-1] += time.perf_counter() - start

    localizer.match = timed
    loops.add = closing  # type: ignore[method-assign]
    state.draw_keyframes = drawing  # type: ignore[method-assign]
    for frame in frames:
        state.integrate(frame)
    return times, loop_times, localizer.counters


def run_benchmark(frames: int = 60, runs: int = 3, progress: Console | None = None) -> dict[str, Any]:
    rendered = _frames(frames)
    medians, p95s, loop_means, loop_maxes, verdicts = [], [], [], [], Counter[str]()
    for _ in range(runs):
        times, loop_times, verdicts = _run(rendered)
        medians.append(statistics.median(times) * 1e3)
        p95s.append(float(np.percentile(times, 95)) * 1e3)
        loop_means.append(statistics.fmean(loop_times) * 1e3)
        loop_maxes.append(max(loop_times) * 1e3)
        if progress:
            progress.print(f"run {len(medians)}: median {medians[-1]:.2f} ms, p95 {p95s[-1]:.2f} ms; loop "
                           f"closure mean {loop_means[-1]:.2f} ms, max {loop_maxes[-1]:.1f} ms")
    return {"frames_per_run": frames, "runs": runs, "median_ms": round(statistics.median(medians), 2),
            "p95_ms": round(statistics.median(p95s), 2), "run_median_ms": [round(m, 2) for m in medians],
            "loop_mean_ms": round(statistics.median(loop_means), 2),
            "loop_max_ms": round(statistics.median(loop_maxes), 1),
            "verdicts": dict(sorted(verdicts.items()))}


def print_table(console: Console, result: dict[str, Any]) -> None:
    table = Table("median ms / frame", "p95 ms / frame", "runs (median ms)", "loop closure ms / frame (mean, max)",
                  "matches by verdict (one run)",
                  title=f"Localization per 640x480 frame, 1000x1000 grid; median of {result['runs']} runs x "
                        f"{result['frames_per_run']} frames")
    table.add_row(f"{result['median_ms']:.2f}", f"{result['p95_ms']:.2f}",
                  ", ".join(f"{m:.2f}" for m in result["run_median_ms"]),
                  f"{result['loop_mean_ms']:.2f}, {result['loop_max_ms']:.1f}",
                  ", ".join(f"{k} {v}" for k, v in result["verdicts"].items()))
    console.print(table)
