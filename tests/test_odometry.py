"""Odometry as a real base reports it: the simulated robot's true motion departs from what its
wheels say by the preset's errors, on every simulated base, the same way for the same seed."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from ovamos.bench.search import (
    EPISODES_FILE,
    ODOMETRY_FIELDS,
    RUN_FILE,
    TRAJECTORIES,
    SearchError,
    run_search,
    summary,
    write_outputs,
)
from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.sim.odometry import ODOMETRY_PRESETS, OdometryErrors, WheelSlip, odometry_errors
from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.services.sim.wheels import base_motion, frame_pose, wheeled
from ovamos.shared.messages import PlanCommand
from ovamos.shared.motion import Action, Pose
from ovamos.shared.simtime import SimClock

#: only systematic errors, so a run measures them exactly
SYSTEMATIC = OdometryErrors(wheel_scale=0.02, wheel_ratio=0.01, track_scale=0.04)
START = Pose(x=0.0, y=0.0, yaw=0.0)


def open_space(x: float, y: float) -> bool:
    return True


def _robot(errors: OdometryErrors, base: str = "kinematic", seed: int = 3) -> SimRobot:
    motion = MotionConfig(odometry=errors, odometry_seed=seed)
    return SimRobot(START, open_space, base_motion(motion, base, DriverConfig()))


def _expected_turn_ratio(slip: WheelSlip) -> float:
    """True rotation over odometry's for a turn in place: the wheels' mean scale over the track's."""
    return (slip.left_scale + slip.right_scale) / 2 / slip.track_scale


def test_presets_are_named_and_ideal_has_no_errors() -> None:
    assert set(ODOMETRY_PRESETS) == {"ideal", "realistic", "hard"}
    assert odometry_errors("ideal").ideal and not odometry_errors("hard").ideal
    assert MotionConfig(odometry="realistic").odometry == ODOMETRY_PRESETS["realistic"]
    with pytest.raises(ValueError, match="unknown odometry preset 'carpet'"):
        odometry_errors("carpet")
    ideal = SimRobot(START, open_space)
    assert ideal.slip is None and ideal.odom is ideal.pose


def test_the_kinematic_base_reports_the_systematic_errors_of_a_straight_run_and_a_turn() -> None:
    robot = _robot(SYSTEMATIC)
    assert robot.slip is not None
    scale = (robot.slip.left_scale + robot.slip.right_scale) / 2
    assert abs(scale - 1) == pytest.approx(SYSTEMATIC.wheel_scale, rel=1e-3)
    for _ in range(8):  # 2 m straight ahead, as the wheels tell it
        assert robot.apply(Action.MOVE_FORWARD)
    assert robot.odom.x == pytest.approx(2.0) and robot.odom.yaw == pytest.approx(0.0)
    true = math.hypot(robot.pose.x, robot.pose.y)
    assert true / 2.0 == pytest.approx(scale, rel=2e-3)  # the distance error of the wheels' mean size
    # the wheel-size difference curves the run: yaw = 2 m * (r_right - r_left) / track
    curve = 2.0 * (robot.slip.right_scale - robot.slip.left_scale) / robot.slip.track(robot.config.track_width_m)
    assert robot.pose.yaw == pytest.approx(curve, rel=1e-6)
    assert abs(curve) > 0.05  # a 1 % wheel ratio over 2 m: about 4 degrees

    turning = _robot(SYSTEMATIC)
    for _ in range(12):  # a full turn, as the wheels tell it
        assert turning.apply(Action.TURN_LEFT)
    assert turning.odom.yaw == pytest.approx(0.0, abs=1e-9)
    assert turning.slip is not None
    off = math.remainder(turning.pose.yaw, 2 * math.pi)
    assert off == pytest.approx(2 * math.pi * (_expected_turn_ratio(turning.slip) - 1), rel=1e-6)


@pytest.mark.parametrize("base", ["kobuki", "opencr", "odrive"])
def test_a_wheeled_base_reports_the_systematic_errors(base: str) -> None:
    """The real driver integrates its encoders with the nominal geometry: its odometry says the
    primitive was driven, the robot went where the true wheels took it."""
    robot = _robot(SYSTEMATIC, base)
    assert robot.slip is not None
    wheels = wheeled(robot, base, clock=SimClock()).start()
    try:
        wheels.wait_ready()
        assert wheels.run_command(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD)) == "done"
        odom = wheels.driver.odometry()
        driven = math.hypot(odom.x, odom.y)
        assert driven == pytest.approx(robot.config.forward_m, abs=0.02)  # the controller's tolerance
        scale = (robot.slip.left_scale + robot.slip.right_scale) / 2
        assert math.hypot(robot.pose.x, robot.pose.y) / driven == pytest.approx(scale, abs=0.004)
        assert frame_pose(robot, wheels) == Pose(x=odom.x, y=odom.y, yaw=odom.yaw)  # frames posed by odometry

        before_true, before_odom = robot.pose.yaw, wheels.driver.odometry().yaw
        assert wheels.run_command(PlanCommand(action_id=2, stamp=0.0, action=Action.TURN_LEFT)) == "done"
        turned_odom = math.remainder(wheels.driver.odometry().yaw - before_odom, 2 * math.pi)
        turned_true = math.remainder(robot.pose.yaw - before_true, 2 * math.pi)
        assert turned_true / turned_odom == pytest.approx(_expected_turn_ratio(robot.slip), abs=0.004)
    finally:
        wheels.stop()


def test_the_ros2_robots_wheels_report_the_errors() -> None:
    """The ROS 2 simulated robot moves by :meth:`SimRobot.drive` and publishes :attr:`SimRobot.odom`."""
    robot = _robot(SYSTEMATIC)
    assert robot.slip is not None
    radius = robot.config.wheel_radius_m
    for _ in range(100):  # 1 m straight ahead at 0.5 m/s, as the wheels turn
        assert robot.drive(0.5 / radius, 0.5 / radius, 0.02)
    assert robot.odom.x == pytest.approx(1.0) and robot.odom.y == pytest.approx(0.0, abs=1e-9)
    scale = (robot.slip.left_scale + robot.slip.right_scale) / 2
    assert robot.distance == pytest.approx(scale, rel=1e-3)


def test_the_same_seed_gives_the_same_drift_and_another_seed_another() -> None:
    def walk(seed: int) -> tuple[Pose, Pose]:
        robot = _robot(ODOMETRY_PRESETS["hard"], seed=seed)
        for action in [Action.MOVE_FORWARD] * 6 + [Action.TURN_LEFT] * 3 + [Action.MOVE_FORWARD] * 6:
            robot.apply(action)
        return robot.pose, robot.odom

    assert walk(7) == walk(7)
    assert walk(7)[0] != walk(8)[0]
    assert walk(7)[1] == walk(8)[1]  # odometry is the nominal motion either way


def test_slip_grows_with_the_distance_each_wheel_travels() -> None:
    slip = WheelSlip(OdometryErrors(slip_m=1e-4), seed=0)
    errors = [slip.wheels(1.0, 1.0)[0] - 1.0 for _ in range(4000)]
    spread = math.sqrt(sum(e * e for e in errors) / len(errors))
    assert spread == pytest.approx(math.sqrt(1e-4 * 1.0), rel=0.05)  # variance k * |d|
    assert slip.wheels(0.0, 0.0) == (0.0, 0.0)  # no travel, no slip


def test_a_bump_knocks_the_robot_where_the_wheels_do_not_see_it() -> None:
    wall = SimRobot(START, lambda x, y: x < 0.1, MotionConfig(odometry=OdometryErrors(bump_deg=5.0, bump_m=0.01)))
    assert not wall.apply(Action.MOVE_FORWARD)
    assert wall.odom == START  # the encoders saw the wheels stall
    assert wall.pose != START and wall.pose.x < 0.1


def test_ideal_odometry_keeps_an_episode_line_as_it_was_and_drift_adds_its_errors(tmp_path: Path) -> None:
    """``--odometry ideal``: no slip, frames posed at the true pose, nothing new in the line (the
    lines are byte for byte those from before odometry errors: checked by hand, see the method).
    ``--odometry hard --localization on``: the believed trajectory, its errors (evo) and the
    localizer's verdicts in the line, ATE in the summary, both trajectories as TUM files."""
    ideal = run_search(1, 1, ("ovamos",), workers=1, max_steps=20, out=tmp_path / "ideal")
    line = json.loads((tmp_path / "ideal" / EPISODES_FILE).read_text())
    assert not set(ODOMETRY_FIELDS) & set(line) and ideal.results[0].believed is None
    assert "ate_median_m" not in summary(ideal)["policies"]["ovamos"]

    hard = run_search(1, 1, ("ovamos",), workers=1, max_steps=20, odometry="hard", localization=True,
                      out=tmp_path / "hard")
    (result,) = hard.results
    assert result.believed is not None and len(result.believed) == len(result.trajectory)
    assert result.believed != result.trajectory and result.odometry is not None and result.odometry.poses == 21
    assert result.localization is not None and result.localization.get("matched", 0) > 0
    scores = summary(hard)["policies"]["ovamos"]
    assert scores["ate_median_m"] == pytest.approx(result.odometry.ate_median_m, abs=1e-3)
    write_outputs(tmp_path / "hard", hard, summary(hard))
    tum = tmp_path / "hard" / TRAJECTORIES / f"ovamos-{result.episode_id}-believed.tum"
    assert len(tum.read_text().splitlines()) == 21
    assert json.loads((tmp_path / "hard" / RUN_FILE).read_text())["odometry"] == "hard"
    with pytest.raises(SearchError, match="unknown odometry preset 'gravel'"):
        run_search(1, 1, ("ovamos",), workers=1, max_steps=5, odometry="gravel")
