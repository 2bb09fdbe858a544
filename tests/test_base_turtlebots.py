"""The base controller driving each TurtleBot base through its real client code (pyserial, the
dynamixel-sdk) on a pseudo-terminal against a simulated device that speaks the protocol byte for
byte: primitives land within a centimetre and a degree, and a bumper stops the wheels and reports
the move blocked. (The ODrive base has the same checks in test_base_driver_motion.py.)"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import pytest

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.controller import BaseController
from ovamos.services.base_driver.kobuki.config import KobukiConfig
from ovamos.services.base_driver.kobuki.protocol import WHEEL_BASE_M, WHEEL_RADIUS_M
from ovamos.services.base_driver.kobuki.sim import SimKobuki
from ovamos.services.base_driver.opencr.config import OpenCRConfig
from ovamos.services.base_driver.opencr.sim import SimOpenCR
from ovamos.services.base_driver.opencr.table import MODELS
from ovamos.services.sim.robot import MotionConfig, SimRobot
from ovamos.services.sim.wheels import SerialSimRobot
from ovamos.shared.messages import DriverMode
from ovamos.shared.motion import Action, Pose
from tests.base_driver_helpers import command, run, wait_for_mode
from tests.polling import wait_for

pytestmark = [pytest.mark.system, pytest.mark.serial]  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)


@contextmanager
def kobuki() -> Iterator[tuple[BaseController, Callable[[], tuple[float, float]], SimKobuki]]:
    with SimKobuki() as sim:
        config = DriverConfig(hardware="kobuki", kobuki=KobukiConfig(port=sim.port),
                              wheel_radius_m=WHEEL_RADIUS_M, track_width_m=WHEEL_BASE_M,
                              feedback_timeout_s=0.2, max_linear_m_s=0.2)
        driver = BaseController(config).start()
        try:
            yield driver, lambda: (sim.left_travel_m, sim.right_travel_m), sim
        finally:
            driver.stop()


@contextmanager
def opencr() -> Iterator[tuple[BaseController, Callable[[], tuple[float, float]], SimOpenCR]]:
    model = MODELS["burger"]
    with SimOpenCR("burger") as sim:
        config = DriverConfig(hardware="opencr", opencr=OpenCRConfig(port=sim.path, model="burger"),
                              wheel_radius_m=model.wheel_radius_m, track_width_m=model.track_m,
                              feedback_timeout_s=0.2, max_linear_m_s=0.2, max_angular_rad_s=2.0)
        driver = BaseController(config).start()
        try:
            yield driver, sim.wheel_travel_m, sim
        finally:
            driver.stop()


BASES = {"kobuki": (kobuki, WHEEL_BASE_M), "opencr": (opencr, MODELS["burger"].track_m)}


@pytest.mark.parametrize("name", sorted(BASES))
def test_primitives_land_within_a_centimetre_and_a_degree(name: str) -> None:
    make, track = BASES[name]
    with make() as (driver, travel, _sim):
        wait_for_mode(driver, DriverMode.READY)
        left0, right0 = travel()
        assert run(driver, command(Action.MOVE_FORWARD)) == "done"
        left1, right1 = travel()
        assert (left1 - left0 + right1 - right0) / 2 == pytest.approx(0.25, abs=0.01)
        assert run(driver, command(Action.TURN_LEFT)) == "done"
        left2, right2 = travel()
        turned = math.degrees(((right2 - right1) - (left2 - left1)) / track)
        assert turned == pytest.approx(30.0, abs=1.0)
        assert driver.state().primitives is not None


def test_a_kobuki_bumper_stops_a_forward_move_as_blocked_and_latches_a_fault() -> None:
    with kobuki() as (driver, travel, sim):
        wait_for_mode(driver, DriverMode.READY)
        move = command(Action.MOVE_FORWARD)
        assert driver.submit(move) == "accepted"
        wait_for(lambda: sum(travel()) / 2 > 0.05, 10, "the move under way")
        sim.press_bumper("centre")
        pressed_at = sum(travel()) / 2
        state = wait_for(lambda: (s := driver.state()).last_completed == move.action_id and s, 5,
                         "the move ended")
        assert state.last_outcome == "blocked"
        assert state.mode is DriverMode.FAULT and any("bumper centre" in f for f in state.faults)
        assert sum(travel()) / 2 - pressed_at < 0.03  # stopped at once, not at the 0.25 m goal


def _go_silent(sim: SimKobuki | SimOpenCR, silent: bool) -> None:
    if isinstance(sim, SimKobuki):
        sim.stop_sending() if silent else sim.resume_sending()
    else:
        sim.silent = silent


def _send_garbage(sim: SimKobuki | SimOpenCR) -> None:
    if isinstance(sim, SimKobuki):
        sim.send_noise(n=64)
        sim.send_bad_checksum()
        sim.send_partial_packet()
    else:
        sim.inject_noise()
        sim.corrupt_replies(2)


@pytest.mark.parametrize("name", sorted(BASES))
def test_deadman_estop_stale_feedback_and_garbage_through_each_base(name: str) -> None:
    make, _track = BASES[name]
    with make() as (driver, travel, sim):
        wait_for_mode(driver, DriverMode.READY)
        # deadman: a velocity command that is not renewed ramps the wheels to a stop
        assert driver.submit(command(linear=0.1)) == "accepted"
        wait_for(lambda: sum(travel()) / 2 > 0.02, 5, "teleop moving")
        wait_for(lambda: _at_rest(travel), 5, "stopped by the deadman")
        # e-stop: latched, wheels stay still, a command is rejected until the clear
        driver.engage_estop("test", "hand on the button")
        assert driver.state().mode is DriverMode.ESTOP
        moved = sum(travel())
        assert driver.submit(command(Action.MOVE_FORWARD)) == "rejected"
        assert _at_rest(travel) and sum(travel()) == pytest.approx(moved, abs=1e-3)
        driver.clear_estop("test")
        wait_for_mode(driver, DriverMode.READY)
        # stale feedback: a fault with the reason, then recovery once the base answers again
        _go_silent(sim, True)
        wait_for_mode(driver, DriverMode.FAULT, 5)
        assert driver.state().faults
        _go_silent(sim, False)
        wait_for_mode(driver, DriverMode.READY, 10)
        # garbage on the line: skipped and counted; a corrupted reply to a write (OpenCR) is a
        # fault like any failed write, and the base is working again after its recovery
        _send_garbage(sim)
        time.sleep(0.5)
        wait_for_mode(driver, DriverMode.READY, 10)
        assert run(driver, command(Action.MOVE_FORWARD)) == "done"
        counted = driver.counters  # the controller's and its hardware interface's
        assert sum(v for k, v in counted.items() if any(w in k for w in ("malformed", "corrupt", "skipped",
                                                                         "resync"))) > 0, counted


def _at_rest(travel: Callable[[], tuple[float, float]]) -> bool:
    before = travel()
    time.sleep(0.2)
    return max(abs(a - b) for a, b in zip(before, travel())) < 1e-4


@pytest.mark.parametrize("hardware", ["kobuki", "opencr"])
def test_a_simulated_turtlebot_that_hits_a_wall_backs_off_to_where_the_step_began(hardware: str) -> None:
    """The simulator's robot on each TurtleBot base (real client, simulated board): a wall 10 cm
    ahead stalls the wheels, the step backs off to its start through the same serial path and
    completes as blocked; odometry and the true pose agree."""
    fixed = DriverConfig().model_copy(update={"hardware": hardware}).fixed_wheels()
    assert fixed is not None
    motion = MotionConfig(wheel_radius_m=fixed[0], track_width_m=fixed[1])
    robot = SimRobot(Pose(x=0.0, y=0.0, yaw=0.0), lambda x, y: x < 0.1, motion)
    with SerialSimRobot(robot, hardware) as sim:
        wait_for_mode(sim.driver, DriverMode.READY)
        assert run(sim.driver, command(Action.MOVE_FORWARD)) == "blocked"
        assert sim.pose.x == pytest.approx(0.0, abs=0.01)
        assert sim.driver.odometry().x == pytest.approx(sim.pose.x, abs=0.005)
        assert sim.driver.counters["back_offs"] == 1 and sim.driver.state().mode is DriverMode.READY
