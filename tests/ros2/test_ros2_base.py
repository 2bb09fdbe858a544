"""The ros2 base against a mock ROS 2 base (bench/ros2_peers/fake_base.py, real rclpy in its own process):
velocity out as TwistStamped or Twist, the base's own odometry in, primitives closing the loop on
it, the deadman's zeros on cmd_vel, stale odometry a fault naming the topic and recovered."""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from ovamos.bench.ros2_peers.nodes import MockNode
from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.controller import BaseController
from ovamos.shared.messages import DriverMode
from ovamos.shared.motion import Action
from tests.base_driver_helpers import command, run, wait_for_mode
from tests.polling import wait_for

START = (2.0, -1.0, math.radians(45))


def commands(base: MockNode) -> list[dict[str, float]]:
    """The velocity commands the mock base received, in order."""
    return [line for line in base.lines() if "v" in line]


def fake_base(twist: bool, namespace: str) -> MockNode:
    """The mock base: its lines are the commands it received (``v``, ``w``, ``t``)."""
    return MockNode("fake_base.py", "--start", *map(str, START), *(["--twist"] if twist else []),
                    *(["--namespace", namespace] if namespace else []))


@pytest.fixture(params=[False, True], ids=["TwistStamped", "Twist"])
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[MockNode, BaseController]]:
    twist = request.param
    namespace = "/robot1" if twist else ""
    base = fake_base(twist, namespace)
    config = DriverConfig(hardware="ros2", ros2={"stamped": not twist, "namespace": namespace})  # type: ignore[arg-type]
    driver = BaseController(config).start()
    try:
        wait_for_mode(driver, DriverMode.READY, timeout=30)
        yield base, driver
    finally:
        driver.stop()
        base.close()


def test_a_primitive_through_ros_lands_on_the_bases_own_odometry(rig: tuple[MockNode, BaseController]) -> None:
    base, driver = rig
    start = driver.odometry()
    assert (start.x, start.y, start.yaw) == pytest.approx(START, abs=1e-6)  # its frame, not ours
    assert run(driver, command(Action.MOVE_FORWARD)) == "done"
    end = driver.odometry()
    assert math.hypot(end.x - start.x, end.y - start.y) == pytest.approx(0.25, abs=0.02)
    assert math.atan2(end.y - start.y, end.x - start.x) == pytest.approx(START[2], abs=0.05)
    assert max(c["v"] for c in commands(base)) > 0.05
    assert run(driver, command(Action.TURN_LEFT)) == "done"
    assert math.degrees(driver.odometry().yaw - end.yaw) == pytest.approx(30.0, abs=2.0)
    assert driver.counters["ros2_odom"] > 0 and driver.counters["ros2_cmd"] > 0


def test_the_deadman_sends_zero_velocity_on_cmd_vel(rig: tuple[MockNode, BaseController]) -> None:
    base, driver = rig
    assert driver.submit(command(linear=0.1)) == "accepted"
    wait_for(lambda: any(c["v"] > 0.05 for c in commands(base)), what="the base driven")
    moving = next(c["t"] for c in commands(base) if c["v"] > 0.05)
    wait_for(lambda: (cs := commands(base))[-1]["v"] == 0.0 and cs[-1]["t"] > moving, 10,
             what="zero velocity on cmd_vel after the deadman")


def test_stale_odometry_is_a_fault_naming_the_topic_and_recovers(rig: tuple[MockNode, BaseController]) -> None:
    base, driver = rig
    base.say("pause")
    wait_for_mode(driver, DriverMode.FAULT)
    topic = driver.config.ros2.topic("odom")
    assert any(f"no nav_msgs/Odometry on {topic} for" in f for f in driver.state().faults), driver.state()
    base.say("resume")
    wait_for_mode(driver, DriverMode.READY, timeout=15)
    assert run(driver, command(Action.TURN_RIGHT)) == "done"


def test_a_ros_e_stop_engages_the_same_latch_and_only_the_laptop_clears_it(
        rig: tuple[MockNode, BaseController]) -> None:
    base, driver = rig
    assert driver.submit(command(linear=0.1)) == "accepted"
    wait_for(lambda: any(c["v"] > 0.05 for c in commands(base)), what="the base driven")
    base.say("estop-false")  # false is no clear, and no e-stop
    wait_for(lambda: driver.counters["ros2_estop_false_ignored"] == 1, what="the false counted")
    assert driver.state().mode is not DriverMode.ESTOP
    base.say("estop")
    wait_for_mode(driver, DriverMode.ESTOP)
    state = driver.state()
    assert state.estop_latched and any(f.startswith("e-stop by ros2: std_msgs/Bool true on ") for f in state.faults)
    pressed = len(commands(base))
    wait_for(lambda: len(commands(base)) > pressed + 5, what="commands after the press")
    assert all(c["v"] == 0.0 and c["w"] == 0.0 for c in commands(base)[pressed + 1:])  # zeros only
    base.say("estop-false")  # a ROS false does not release it
    wait_for(lambda: driver.counters["ros2_estop_false_ignored"] == 2, what="the second false counted")
    assert driver.state().mode is DriverMode.ESTOP
    driver.clear_estop("laptop")  # what driver/estop/clear does
    wait_for_mode(driver, DriverMode.READY, timeout=15)


DRIVE = """
import sys, time
from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.controller import BaseController
from ovamos.shared.messages import DriverMode, PlanCommand
driver = BaseController(DriverConfig(hardware="ros2", ros2={"stamped": False})).start()
while driver.state().mode is not DriverMode.READY:
    time.sleep(0.05)
for k in range(10**6):  # a planner's keep-alive: the same velocity command again and again
    driver.submit(PlanCommand(action_id=1, stamp=0.0, linear=0.1))
    if k == 0:
        print("driving", flush=True)
    time.sleep(0.1)
"""


def test_once_the_driver_is_killed_nothing_more_goes_out_and_a_create3_stops_by_itself() -> None:
    """SIGKILL leaves no zero command behind: a base that stops on a command timeout (the
    Create 3, and this mock) stops; one that does not (a TurtleBot 3) keeps its last velocity, as
    the docs say."""
    base = fake_base(twist=True, namespace="")
    driver = subprocess.Popen([sys.executable, "-c", DRIVE], stdout=subprocess.PIPE, text=True,
                              cwd=Path(__file__).resolve().parent.parent.parent)
    try:
        assert driver.stdout is not None and driver.stdout.readline().strip() == "driving"
        wait_for(lambda: any(c["v"] > 0.05 for c in commands(base)), what="the base driven")
        driver.kill()
        driver.wait(10)
        killed = time.monotonic()
        wait_for(lambda: any("timed_out" in line for line in base.lines()), what="the base's own timeout")
        stopped = next(line["timed_out"] for line in base.lines() if "timed_out" in line)
        last = commands(base)[-1]
        assert last["v"] > 0.05  # no zero came: the process was gone
        assert last["t"] <= killed and stopped > last["t"] + 0.5
    finally:
        if driver.poll() is None:
            driver.kill()
        base.close()
