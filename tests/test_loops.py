"""Loop closure: keyframes that come back to a place the map saw before its frame turned are tied
to it, the pose graph is solved and the robot is put back where it is; a solution that would move it
too far is refused; ties of one keyframe alone move nothing. Scans are a rectangular room's walls
seen from each pose (no rendering: the pose graph is what is tested)."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.localization import LocalizationConfig, ObstaclePoints
from ovamos.services.mapping.loops import LoopCloser, LoopConfig
from ovamos.services.mapping.state import MapState
from ovamos.shared.grid import GridGeometry
from ovamos.shared.motion import Pose

pytest.importorskip("gtsam")

GRID = GridGeometry(0.05, -2.0, -2.0, 200, 200)
START = Pose(x=2.0, y=2.0, yaw=0.0)
#: the map's frame turned 6 degrees about the start, unseen (a bump while nothing could be matched)
KNOCK = Pose(x=0.0, y=0.0, yaw=math.radians(6.0))


def _room() -> np.ndarray:
    """A 6 m x 4 m room's walls, a point every 2 cm, with a pillar that breaks its symmetry."""
    t = np.arange(0.0, 1.0, 0.02 / 6.0)
    walls = [np.stack([6 * t, 0 * t], 1), np.stack([6 * t, 0 * t + 4], 1),
             np.stack([0 * t, 4 * t], 1), np.stack([0 * t + 6, 4 * t], 1)]
    a = np.linspace(0, 2 * math.pi, 60, endpoint=False)
    pillar = np.stack([4.5 + 0.3 * np.cos(a), 3.0 + 0.3 * np.sin(a)], 1)
    return np.vstack([*walls, pillar])


ROOM = _room()


def _seen(true: Pose) -> np.ndarray:
    """The room's points within 4 m and 45 degrees of the heading (world xy)."""
    d = ROOM - (true.x, true.y)
    bearing = np.arctan2(d[:, 1], d[:, 0]) - true.yaw
    bearing = (bearing + math.pi) % (2 * math.pi) - math.pi
    return ROOM[(np.hypot(d[:, 0], d[:, 1]) < 4.0) & (np.abs(bearing) < math.pi / 4)]


def _about_start(turn: Pose, pose: Pose) -> Pose:
    """``pose`` with the map turned by ``turn`` about START."""
    to = Pose(x=START.x, y=START.y, yaw=0.0)
    return to.compose(turn).compose(to.inverse()).compose(pose)


def _walk() -> list[Pose]:
    """A look-around at START, out to (4, 2), a turn, back, and a look-around at START again."""
    poses = [Pose(x=2.0, y=2.0, yaw=math.radians(30 * k)) for k in range(12)]
    poses += [Pose(x=2.0 + 0.35 * i, y=2.0, yaw=0.0) for i in range(1, 7)]
    poses += [Pose(x=4.1, y=2.0, yaw=math.radians(30 * k)) for k in range(1, 7)]
    poses += [Pose(x=4.1 - 0.35 * i, y=2.0, yaw=math.pi) for i in range(1, 7)]
    poses += [Pose(x=2.0, y=2.0, yaw=math.pi + math.radians(30 * k)) for k in range(1, 12)]
    return poses


def _run(config: LoopConfig) -> tuple[LoopCloser, list[tuple[Pose, Pose]], Counter[str]]:
    """Every pose of the walk given to a loop closer as the localizer would, the map turned by KNOCK
    from the first step out on; (where the closer has the camera, the truth) per frame."""
    counters: Counter[str] = Counter()
    closer = LoopCloser(config, LocalizationConfig(enabled=True), GRID, counters)
    map_T_odom = Pose(x=0.0, y=0.0, yaw=0.0)
    placed: list[tuple[Pose, Pose]] = []
    for i, true in enumerate(_walk()):
        odom = true if i < 12 else _about_start(KNOCK, true)  # odometry: the truth, then knocked
        believed = map_T_odom.compose(odom)
        obstacles = believed.apply_points(true.inverse().apply_points(_seen(true)))
        moved = closer.add(odom, believed, obstacles, matched=i != 12)  # the knock: nothing matched
        if moved is not None:
            map_T_odom = moved
        placed.append((map_T_odom.compose(odom), true))
    return closer, placed, counters


def _error(pair: tuple[Pose, Pose]) -> tuple[float, float]:
    believed, true = pair
    return math.hypot(believed.x - true.x, believed.y - true.y), abs(math.degrees(math.remainder(
        believed.yaw - true.yaw, 2 * math.pi)))


def test_a_robot_back_where_the_map_began_is_put_back_and_its_keyframes_with_it() -> None:
    closer, placed, counters = _run(LoopConfig(enabled=True))
    assert counters["loop_solved"] >= 1 and counters["loop_refused"] == 0, counters
    out = _error(placed[20])  # out at (4, 2): 6 degrees off, as the knock left it
    assert out[1] == pytest.approx(6.0, abs=0.1)
    metres, degrees = _error(placed[-1])  # back at the start, after the ties
    assert metres < 0.03 and degrees < 1.0, (metres, degrees)
    # the keyframes made out there moved with the graph: drawn again, the walls are single
    obstacle = np.zeros(GRID.shape, bool)
    closer.draw(obstacle, ObstaclePoints(GRID))
    rows, cols = np.nonzero(obstacle)
    xs, ys = GRID.to_world(rows, cols)
    nearest = np.min(np.hypot(xs[:, None] - ROOM[None, :, 0], ys[:, None] - ROOM[None, :, 1]), axis=1)
    assert np.mean(nearest < 0.1) > 0.97


def test_a_solution_that_would_move_the_robot_too_far_is_refused_and_nothing_moves() -> None:
    closer, placed, counters = _run(LoopConfig(enabled=True, max_shift_deg=2.0))
    assert counters["loop_refused"] >= 1 and counters["loop_solved"] == 0, counters
    assert _error(placed[-1])[1] == pytest.approx(6.0, abs=0.1)  # still knocked: odometry's word kept
    assert [kf.pose for kf in closer.keyframes] == [believed for believed, _ in placed]  # never re-placed


def test_one_keyframes_tie_moves_nothing_until_the_next_one_says_the_same() -> None:
    _, _, counters = _run(LoopConfig(enabled=True, confirmations=1000))
    assert counters["loop_unconfirmed"] >= 2 and counters["loop_solved"] == 0, counters


def test_the_map_closes_loops_only_when_asked_and_while_it_localizes_by_scan() -> None:
    loops = LoopConfig(enabled=True)
    assert MapState(MappingConfig(grid_cells=100, loops=loops)).loops is None  # localization off
    on = MappingConfig(grid_cells=100, localization=LocalizationConfig(enabled=True))
    assert MapState(on).loops is None  # off by default
    assert MapState(on.model_copy(update={"loops": loops})).loops is not None
    base = on.model_copy(update={"localization": LocalizationConfig(enabled=True, source="base"), "loops": loops})
    assert MapState(base).loops is None
