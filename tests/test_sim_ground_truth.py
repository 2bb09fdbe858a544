"""Ground-truth evaluator and robot motion on hand-made scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.shared.motion import Action, Pose
from ovamos.world.evaluator import GroundTruth, spl
from tests.sim_scenes import two_rooms


@pytest.fixture(scope="module")
def truth() -> GroundTruth:
    return GroundTruth(two_rooms())


def descend(truth: GroundTruth, field: np.ndarray, x: float, y: float) -> tuple[float, float, float]:
    """Walk a shortest path down a distance field (each step to a neighbour n with
    field[n] + step == field[here]); returns the end point and the path length."""
    grid = truth.grid
    row, col = grid.to_cell(x, y)
    length = 0.0
    while True:
        steps = [(field[row + dr, col + dc] + grid.resolution * math.hypot(dr, dc), row + dr, col + dc)
                 for dr in (-1, 0, 1) for dc in (-1, 0, 1)
                 if (dr or dc) and grid.contains(row + dr, col + dc)]
        total, r, c = min(steps)
        if total > field[row, col] + 1e-9:
            break
        length += grid.resolution * math.hypot(r - row, c - col)
        row, col = r, c
    return *grid.to_world(row, col), length


def test_a_stop_close_to_an_instance_succeeds_and_one_1_2_m_away_fails(truth) -> None:
    # fridge 1 occupies x in [0.05, 0.75]: straight free line east of it
    assert truth.stop("fridge", 0.75 + 0.8, 3.0).success
    far = truth.stop("fridge", 0.75 + 1.2, 3.0)
    assert not far.success and far.distance == pytest.approx(1.2, abs=0.06)


def test_a_stop_behind_a_wall_fails_even_when_the_object_is_near_in_a_straight_line(truth) -> None:
    # (2.7, 1.0) is 1.2 m from the table's west edge in a straight line, through the wall at x = 3
    result = truth.stop("table", 2.75, 0.8)
    assert not result.success
    assert result.distance > 2.0  # the way round goes through the door


def test_a_small_object_is_reached_at_its_support(truth) -> None:
    # the cup is 0.6 m inside the table's 1.2 m length: a robot at the table's end is 0.6+ m away
    d = truth.distance_to_class("cup", 4.5 + 0.6 + 0.3, 1.0)
    assert d == pytest.approx(0.6 + 0.3 - 0.04, abs=0.06)


def test_a_class_is_stoppable_only_where_a_reachable_place_is_within_1_m(truth) -> None:
    assert truth.stoppable_classes(1.5, 1.0) == ["cup", "fridge", "table"]
    # a 3 m wide table in the office: the cup in its middle is 1.5 m from any free cell
    scene = two_rooms()
    table, cup = (o for o in scene.objects if o.cls in ("table", "cup"))
    wide = scene.model_copy(update={"objects": tuple(
        o.model_copy(update={"sx": 2.6, "sy": 2.6, "x": 4.5, "y": 1.9}) if o is table else
        o.model_copy(update={"x": 4.5, "y": 1.9}) if o is cup else o for o in scene.objects)})
    assert GroundTruth(wide).stoppable_classes(1.5, 1.0) == ["fridge", "table"]


def test_an_optimal_path_gets_mspl_1(truth) -> None:
    start = (1.5, 1.0)
    shortest = truth.shortest_tour(start, ["cup"])
    x, y, travelled = descend(truth, truth.class_field("cup"), *start)
    assert truth.stop("cup", x, y).success
    assert spl(True, shortest, travelled) == pytest.approx(1.0, abs=0.02)
    assert spl(True, shortest, 2 * shortest) == pytest.approx(0.5)
    assert spl(False, shortest, travelled) == 0.0


def test_the_tour_takes_the_best_order_and_instances(truth) -> None:
    start = (5.0, 2.0)  # next to the second fridge and the table
    tour = truth.shortest_tour(start, ["fridge", "cup"])
    near_fridge = truth.scene.object(4)
    cup, fridge = truth.object_field(3), truth.object_field(4)

    def leg(field, here) -> float:
        return field[truth.grid.to_cell(*here)] - field.min()

    via_near = min(leg(cup, start) + leg(fridge, truth.viewpoint(truth.scene.object(3))),
                   leg(fridge, start) + leg(cup, truth.viewpoint(near_fridge)))
    assert tour == pytest.approx(via_near)
    assert tour < 4.0  # never the far fridge behind the wall


def test_moves_into_walls_are_blocked_and_counted(truth) -> None:
    robot = SimRobot(Pose(x=2.6, y=0.8, yaw=0.0), truth.is_free)
    assert robot.apply(Action.MOVE_FORWARD) is False  # 0.25 m east hits the wall at x = 3
    assert robot.pose == Pose(x=2.6, y=0.8, yaw=0.0) and robot.blocked == 1
    for _ in range(3):
        robot.apply(Action.TURN_LEFT)
    assert robot.pose.yaw == pytest.approx(math.pi / 2)
    assert robot.apply(Action.MOVE_FORWARD)
    assert (robot.pose.x, robot.pose.y) == pytest.approx((2.6, 1.05))
    assert robot.distance == pytest.approx(0.25) and robot.blocked == 1


def test_wheel_velocities_integrate_to_lines_and_turns(truth) -> None:
    cfg = MotionConfig()
    robot = SimRobot(Pose(x=1.0, y=1.0, yaw=0.0), truth.is_free, cfg)
    speed = 0.2 / cfg.wheel_radius_m  # 0.2 m/s
    for _ in range(50):
        assert robot.drive(speed, speed, 0.02)
    assert (robot.pose.x, robot.pose.y, robot.pose.yaw) == pytest.approx((1.2, 1.0, 0.0))
    spin = (math.pi / 2) * cfg.track_width_m / 2 / cfg.wheel_radius_m  # pi/2 rad in 1 s
    for _ in range(50):
        robot.drive(-spin, spin, 0.02)
    assert robot.pose.yaw == pytest.approx(math.pi / 2) and robot.pose.x == pytest.approx(1.2)
    robot.pose = Pose(x=2.6, y=0.8, yaw=0.0)
    assert not all(robot.drive(speed, speed, 0.1) for _ in range(10))
    assert robot.pose.x < 3.0 - 0.18 and robot.blocked == 1
