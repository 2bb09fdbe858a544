"""``ovamos doctor`` on a ROS 2 robot (the simulated one, real rclpy): odometry arriving and
``cmd_vel`` subscribed, camera frames at their rate; with the robot down, each fails naming its topic."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from ovamos.doctor import DoctorOptions, diagnose
from ovamos.services.sim.ros2_robot import CAMERA
from tests.polling import wait_for
from tests.ros2.test_ros2_sim_robot import _sim_robot


@pytest.fixture
def profile(tmp_path: Path) -> Path:
    """A robot profile with the ros2 base and camera on the simulated robot's topics."""
    (tmp_path / "base.json").write_text(json.dumps({"driver": {"hardware": "ros2"}}))
    (tmp_path / "camera.json").write_text(json.dumps({"backend": "ros2", "ros2": CAMERA.model_dump(mode="json")}))
    path = tmp_path / "robot.toml"
    path.write_text('robot_id = "robot1"\n' + "".join(
        f'[[services]]\nservice = "{name}"\nconfig = "{tmp_path / (file + ".json")}"\n'
        for name, file in (("base_driver", "base"), ("camera", "camera"))))
    return path


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Path]:
    yield from _sim_robot(tmp_path)


def _checks(profile: Path) -> dict[str, dict]:
    return {c.name: c.__dict__ for c in diagnose(profile, DoctorOptions(timeout_s=3.0))}


def test_with_the_robot_down_the_base_and_camera_fail_naming_their_topics(profile: Path) -> None:
    checks = _checks(profile)
    assert checks["base"]["status"] == "fail" and "no nav_msgs/Odometry on odom" in checks["base"]["detail"]
    assert checks["camera"]["status"] == "fail" and CAMERA.color in checks["camera"]["detail"]


def test_with_the_robot_up_odometry_cmd_vel_and_frames_pass(robot: Path, profile: Path) -> None:
    checks = wait_for(lambda: (c := _checks(profile))["base"]["status"] == c["camera"]["status"] == "pass" and c,
                      90, "the simulated robot up, as the doctor sees it")
    assert "cmd_vel has 1 subscriber(s)" in checks["base"]["detail"]
    assert checks["camera"]["status"] == "pass" and " Hz" in checks["camera"]["detail"], checks["camera"]
