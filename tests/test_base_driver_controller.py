"""The controller over a fake hardware interface, on an injected clock: the safety that every base
gets the same way (bumpers, wheel drops, cliffs, stale feedback, hardware errors, recovery)."""

from __future__ import annotations

import math

import pytest

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.controller import BaseController, make_hardware
from ovamos.services.base_driver.odrive.client import ODriveCanHardware
from ovamos.shared.messages import DriverMode
from ovamos.shared.motion import Action, Pose
from tests.base_driver_helpers import FakeHardware, FakeOdometryBase, command

DT = 0.02


class Rig:
    def __init__(self, **config: object) -> None:
        self.t = 0.0
        self.config = DriverConfig(recover_every_s=0.2, **config)
        self.hw = FakeHardware(lambda: self.t, self.config.track_width_m, self.config.wheel_radius_m)
        self.d = BaseController(self.config, self.hw, clock=lambda: self.t)

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT)):
            self.t += DT
            self.d.tick()

    def until(self, predicate, limit_s: float = 20.0) -> None:
        for _ in range(round(limit_s / DT)):
            if predicate():
                return
            self.t += DT
            self.d.tick()
        raise AssertionError(f"not reached in {limit_s} s: {self.d.state()}")

    @property
    def mode(self) -> DriverMode:
        return self.d.state().mode


@pytest.fixture
def rig() -> Rig:
    rig = Rig()
    rig.run(0.1)
    assert rig.mode is DriverMode.READY
    return rig


def test_the_factory_builds_the_configured_hardware() -> None:
    assert isinstance(make_hardware(DriverConfig()), ODriveCanHardware)
    assert DriverConfig().hardware == "odrive_can"


def test_a_forward_primitive_closes_the_loop_on_the_fake_wheels(rig: Rig) -> None:
    cmd = command(Action.MOVE_FORWARD)
    assert rig.d.submit(cmd) == "accepted"
    rig.until(lambda: rig.d.state().last_completed == cmd.action_id)
    assert rig.d.state().last_outcome == "done"
    assert rig.d.odometry().x == pytest.approx(0.25, abs=0.005)
    cmd = command(Action.TURN_LEFT)
    rig.d.submit(cmd)
    rig.until(lambda: rig.d.state().last_completed == cmd.action_id)
    assert math.degrees(rig.d.odometry().yaw) == pytest.approx(30.0, abs=0.5)


def test_a_bumper_during_a_forward_move_blocks_it_halts_and_latches_a_fault(rig: Rig) -> None:
    cmd = command(Action.MOVE_FORWARD)
    rig.d.submit(cmd)
    rig.until(lambda: rig.d.odometry().linear > 0.05)
    halts = rig.hw.halts
    rig.hw.bumpers = ("left",)
    rig.run(DT)
    state = rig.d.state()
    assert state.last_completed == cmd.action_id and state.last_outcome == "blocked"
    assert state.mode is DriverMode.FAULT and "bumper left pressed" in state.faults
    assert rig.hw.halts > halts and (rig.hw.v, rig.hw.w) == (0.0, 0.0)  # at once, not ramped
    assert rig.d.submit(command(Action.TURN_LEFT)) == "rejected"
    opens = rig.hw.opens
    rig.run(1.0)  # latched while it is pressed: no re-open
    assert rig.mode is DriverMode.FAULT and rig.hw.opens == opens and rig.hw.v == 0.0
    rig.hw.bumpers = ()
    rig.until(lambda: rig.mode is DriverMode.READY, 2.0)
    assert rig.d.state().faults == () and rig.d.counters["recoveries"] == 1
    # the hardware was re-opened: odometry went on integrating, in the same session
    assert rig.hw.opens > opens and rig.d.odometry().odom_session == state.odom_session


def test_the_odometry_session_is_one_per_controller_in_its_states_and_odometry(rig: Rig) -> None:
    session = rig.d.state().odom_session
    assert session and rig.d.odometry().odom_session == session
    rig.run(1.0)
    assert rig.d.state().odom_session == rig.d.odometry().odom_session == session
    assert Rig().d.state().odom_session != session  # a driver started again: a new session


def test_a_collision_report_during_a_forward_move_backs_off_to_the_start_then_blocks() -> None:
    """BaseController.bump (the simulator's contact check): the robot drives straight back to
    where the step began, so a blocked step leaves it where the planner thinks it is; with
    back_off_on_bump off it stays at the contact. Neither is a fault."""
    for back_off, end_x in ((True, 0.0), (False, 0.1)):
        rig = Rig(back_off_on_bump=back_off)
        rig.run(0.1)
        cmd = command(Action.MOVE_FORWARD)
        rig.d.submit(cmd)
        rig.until(lambda: rig.d.odometry().x > 0.1)
        rig.d.bump()
        rig.until(lambda: rig.d.state().last_completed == cmd.action_id)
        state = rig.d.state()
        assert state.last_outcome == "blocked" and state.mode is DriverMode.READY
        assert rig.d.odometry().x == pytest.approx(end_x, abs=0.02)
        assert rig.d.counters["back_offs"] == int(back_off)
    rig.d.bump()  # nothing under way: nothing to block
    rig.run(DT)
    assert rig.d.counters["bumps"] == 1


def test_a_forward_move_whose_wheels_stall_ends_blocked_without_a_bumper() -> None:
    """A TurtleBot 3 against a wall: no bumper, the wheels stop turning. The move ends blocked
    within stall_s instead of pushing until primitive_timeout_s; a free move is never judged so."""
    rig = Rig()
    rig.run(0.1)
    free = command(Action.MOVE_FORWARD)
    rig.d.submit(free)
    rig.until(lambda: rig.d.state().last_completed == free.action_id)
    assert rig.d.state().last_outcome == "done" and rig.d.counters["stalls"] == 0
    rig.hw.stalled = True
    stuck = command(Action.MOVE_FORWARD)
    rig.d.submit(stuck)
    started = rig.t
    rig.until(lambda: rig.d.state().last_completed == stuck.action_id, limit_s=5.0)
    assert rig.d.state().last_outcome == "blocked" and rig.d.counters["stalls"] >= 1
    assert rig.t - started < 3.0 < rig.config.primitive_timeout_s
    assert rig.mode is DriverMode.READY  # not a fault: the next command may turn away


def test_a_bumper_while_turning_aborts_the_turn(rig: Rig) -> None:
    cmd = command(Action.TURN_LEFT)
    rig.d.submit(cmd)
    rig.run(0.2)
    rig.hw.bumpers = ("centre", "right")
    rig.run(DT)
    state = rig.d.state()
    assert state.last_outcome == "aborted" and "bumper centre, right pressed" in state.faults


def test_a_wheel_drop_halts_and_is_a_fault_until_the_wheel_is_down(rig: Rig) -> None:
    rig.d.submit(command(linear=0.2))
    rig.run(0.3)
    rig.hw.wheel_drops = ("right",)
    rig.run(DT)
    state = rig.d.state()
    assert state.mode is DriverMode.FAULT and "wheel drop right" in state.faults
    assert state.last_outcome == "aborted" and rig.hw.v == 0.0
    rig.run(1.0)
    assert rig.mode is DriverMode.FAULT
    rig.hw.wheel_drops = ()
    rig.until(lambda: rig.mode is DriverMode.READY, 2.0)


def test_a_cliff_stops_forward_motion_but_not_turns_or_reversing(rig: Rig) -> None:
    rig.hw.cliffs = ("centre",)
    cmd = command(Action.MOVE_FORWARD)
    rig.d.submit(cmd)
    rig.run(0.2)
    state = rig.d.state()
    assert state.last_completed == cmd.action_id and state.last_outcome == "blocked"
    assert state.mode is DriverMode.READY and rig.d.odometry().x == pytest.approx(0.0, abs=1e-9)
    for _ in range(10):  # teleop forward: refused (zero), not a fault
        rig.d.submit(command(linear=0.2))
        rig.run(0.1)
    assert all(v <= 0.0 for v, _ in rig.hw.setpoints) and rig.mode is DriverMode.MOVING
    for _ in range(5):
        rig.d.submit(command(linear=-0.1, angular=0.5))
        rig.run(0.1)
    assert rig.d.odometry().linear < -0.05 and rig.d.odometry().angular > 0.3
    rig.hw.cliffs = ()
    cmd = command(Action.MOVE_FORWARD)
    rig.d.submit(cmd)
    rig.until(lambda: rig.d.state().last_completed == cmd.action_id)
    assert rig.d.state().last_outcome == "done"


def test_a_cliff_appearing_mid_move_stops_at_once(rig: Rig) -> None:
    rig.d.submit(command(Action.MOVE_FORWARD))
    rig.until(lambda: rig.d.odometry().linear > 0.1)
    rig.hw.cliffs = ("left",)
    rig.run(DT)
    assert rig.d.state().last_outcome == "blocked" and rig.hw.v <= 0.0


def test_stale_feedback_is_a_fault_until_it_is_fresh_again(rig: Rig) -> None:
    rig.hw.silent = True
    rig.run(0.4)
    state = rig.d.state()
    assert state.mode is DriverMode.FAULT
    assert any(f.startswith("no feedback from the fake base for") for f in state.faults), state.faults
    rig.hw.silent = False
    rig.until(lambda: rig.mode is DriverMode.READY, 2.0)
    assert rig.d.counters["faults"] == 1


def test_a_hardware_error_is_a_fault_with_its_reason_and_reopening_recovers(rig: Rig) -> None:
    rig.d.submit(command(linear=0.2))
    rig.run(0.2)
    rig.hw.broken = "serial port /dev/ttyUSB0 vanished"
    rig.run(DT)
    state = rig.d.state()
    assert state.mode is DriverMode.FAULT and state.faults == ("serial port /dev/ttyUSB0 vanished",)
    assert state.last_outcome == "aborted"
    opens = rig.hw.opens
    rig.run(1.0)  # re-opened every recover_every_s, refused each time
    assert rig.mode is DriverMode.FAULT and rig.hw.opens - opens >= 4
    rig.hw.broken = None
    rig.until(lambda: rig.mode is DriverMode.READY, 2.0)


def test_an_estop_halts_at_once_and_holds_the_wheels(rig: Rig) -> None:
    rig.d.submit(command(linear=0.2))
    rig.run(0.5)
    rig.d.engage_estop("test")
    assert (rig.hw.v, rig.hw.w) == (0.0, 0.0)
    rig.hw.bumpers = ("left",)  # sensors change nothing while latched
    rig.run(0.5)
    assert rig.mode is DriverMode.ESTOP and rig.hw.v == 0.0
    rig.hw.bumpers = ()
    rig.d.clear_estop("test")
    rig.until(lambda: rig.mode is DriverMode.READY, 1.0)


@pytest.mark.parametrize("report_velocity", [True, False])
def test_a_base_with_its_own_odometry_is_taken_as_it_is_and_its_primitives_land(report_velocity: bool) -> None:
    """A base that reports a pose and no wheel positions (a ROS 2 base's ``nav_msgs/Odometry``):
    the controller's odometry is that pose, in the base's own frame (here starting at (5, 3),
    facing 60 deg), not something integrated again; primitives close the loop on it, and with
    the pose alone the controller derives the velocities that decide a primitive has settled."""
    t = [0.0]
    config = DriverConfig(recover_every_s=0.2)
    start = Pose(x=5.0, y=3.0, yaw=math.radians(60))
    hw = FakeOdometryBase(lambda: t[0], start, report_velocity=report_velocity)
    d = BaseController(config, hw, clock=lambda: t[0])

    def until(predicate) -> None:
        for _ in range(round(20.0 / DT)):
            if predicate():
                return
            t[0] += DT
            d.tick()
        raise AssertionError(f"not reached: {d.state()}")

    assert not d.has_pose  # nothing reported yet: the service publishes no odometry (its (0, 0) is made up)
    until(lambda: d.state().mode is DriverMode.READY)
    assert d.has_pose and (d.odometry().x, d.odometry().y) == (5.0, 3.0)
    cmd = command(Action.MOVE_FORWARD)
    assert d.submit(cmd) == "accepted"
    until(lambda: d.state().last_completed == cmd.action_id)
    assert d.state().last_outcome == "done"
    moved = math.hypot(d.odometry().x - 5.0, d.odometry().y - 3.0)
    assert moved == pytest.approx(config.primitives.forward_m, abs=0.005)
    assert (d.odometry().x, d.odometry().y, d.odometry().yaw) == (hw.pose.x, hw.pose.y, hw.pose.yaw)
    cmd = command(Action.TURN_LEFT)
    d.submit(cmd)
    until(lambda: d.state().last_completed == cmd.action_id)
    assert math.degrees(d.odometry().yaw) == pytest.approx(60 + config.primitives.turn_deg, abs=0.5)
    assert d.odometry().yaw == hw.pose.yaw
