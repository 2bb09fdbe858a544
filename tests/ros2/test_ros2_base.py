"""The ros2 base against a mock ROS 2 base (tests/ros2/fake_base.py, real rclpy in its own process):
velocity out as TwistStamped or Twist, the base's own odometry in, primitives closing the loop on
it, the deadman's zeros on cmd_vel, stale odometry a fault naming the topic and recovered."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.base_driver.config import DriverConfig
from services.base_driver.controller import BaseController
from shared.messages import DriverMode
from shared.motion import Action
from tests.base_driver_helpers import command, run, wait_for_mode
from tests.polling import wait_for

HERE = Path(__file__).resolve().parent
START = (2.0, -1.0, math.radians(45))


class FakeBase:
    """The mock base's process: every command it received, and its odometry paused or not."""

    def __init__(self, twist: bool, namespace: str) -> None:
        argv = [sys.executable, str(HERE / "fake_base.py"), "--start", *map(str, START)]
        argv += ["--twist"] if twist else []
        argv += ["--namespace", namespace] if namespace else []
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     cwd=HERE.parent.parent)
        self._lock = threading.Lock()
        self._commands: list[dict[str, float]] = []
        self._ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()
        assert self._ready.wait(30), "the mock base did not start"

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            got = json.loads(line)
            if got.get("ready"):
                self._ready.set()
                continue
            with self._lock:
                self._commands.append(got)

    def commands(self) -> list[dict[str, float]]:
        with self._lock:
            return list(self._commands)

    def say(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


@pytest.fixture(params=[False, True], ids=["TwistStamped", "Twist"])
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[FakeBase, BaseController]]:
    twist = request.param
    namespace = "/robot1" if twist else ""
    base = FakeBase(twist, namespace)
    config = DriverConfig(hardware="ros2", ros2={"stamped": not twist, "namespace": namespace})  # type: ignore[arg-type]
    driver = BaseController(config).start()
    try:
        wait_for_mode(driver, DriverMode.READY, timeout=30)
        yield base, driver
    finally:
        driver.stop()
        base.close()


def test_a_primitive_through_ros_lands_on_the_bases_own_odometry(rig: tuple[FakeBase, BaseController]) -> None:
    base, driver = rig
    start = driver.odometry()
    assert (start.x, start.y, start.yaw) == pytest.approx(START, abs=1e-6)  # its frame, not ours
    assert run(driver, command(Action.MOVE_FORWARD)) == "done"
    end = driver.odometry()
    assert math.hypot(end.x - start.x, end.y - start.y) == pytest.approx(0.25, abs=0.02)
    assert math.atan2(end.y - start.y, end.x - start.x) == pytest.approx(START[2], abs=0.05)
    assert max(c["v"] for c in base.commands()) > 0.05
    assert run(driver, command(Action.TURN_LEFT)) == "done"
    assert math.degrees(driver.odometry().yaw - end.yaw) == pytest.approx(30.0, abs=2.0)
    assert driver.counters["ros2_odom"] > 0 and driver.counters["ros2_cmd"] > 0


def test_the_deadman_sends_zero_velocity_on_cmd_vel(rig: tuple[FakeBase, BaseController]) -> None:
    base, driver = rig
    assert driver.submit(command(linear=0.1)) == "accepted"
    wait_for(lambda: any(c["v"] > 0.05 for c in base.commands()), what="the base driven")
    moving = next(c["t"] for c in base.commands() if c["v"] > 0.05)
    wait_for(lambda: (cs := base.commands())[-1]["v"] == 0.0 and cs[-1]["t"] > moving, 10,
             what="zero velocity on cmd_vel after the deadman")


def test_stale_odometry_is_a_fault_naming_the_topic_and_recovers(rig: tuple[FakeBase, BaseController]) -> None:
    base, driver = rig
    base.say("pause")
    wait_for_mode(driver, DriverMode.FAULT)
    topic = driver.config.ros2.topic("odom")
    assert any(f"no nav_msgs/Odometry on {topic} for" in f for f in driver.state().faults), driver.state()
    base.say("resume")
    wait_for_mode(driver, DriverMode.READY, timeout=15)
    assert run(driver, command(Action.TURN_RIGHT)) == "done"
