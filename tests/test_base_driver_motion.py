"""The driver moving a simulated base: enable sequence, primitives, odometry, deadman, duplicates."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import pytest

from ovamos.services.base_driver.odrive.protocol import AxisState, ControlMode, InputMode
from ovamos.services.sim.wheels import WheeledSimRobot
from ovamos.shared.messages import DriverMode
from ovamos.shared.motion import Action
from tests.base_driver_helpers import command, heading_deg, run, sim_base, wheels_at_rest
from tests.polling import wait_for

pytestmark = [pytest.mark.system, pytest.mark.serial]  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)


@pytest.fixture
def base() -> Iterator[WheeledSimRobot]:
    base = sim_base()
    yield base
    base.stop()


def test_enable_sequence_sets_limits_mode_and_closed_loop(base: WheeledSimRobot) -> None:
    cfg = base.driver.config
    for axis in base.odrives.axes.values():
        assert axis.state is AxisState.CLOSED_LOOP_CONTROL and axis.errors == 0
        assert axis.control_mode is ControlMode.VELOCITY_CONTROL and axis.input_mode is InputMode.VEL_RAMP
        assert axis.vel_limit == pytest.approx(cfg.max_wheel_rev_s * 1.1, rel=1e-6)  # Set_Limits
        assert axis.current_limit == pytest.approx(cfg.odrive.current_limit_a)
    assert base.driver.state().faults == ()


def test_forward_and_turns_land_within_a_centimetre_and_a_degree(base: WheeledSimRobot) -> None:
    start = base.pose
    assert run(base.driver, command(Action.MOVE_FORWARD)) == "done"
    moved = base.pose
    assert math.hypot(moved.x - start.x, moved.y - start.y) == pytest.approx(0.25, abs=0.01)
    assert abs(heading_deg(start, moved)) < 1.0
    assert run(base.driver, command(Action.TURN_LEFT)) == "done"
    assert heading_deg(moved, base.pose) == pytest.approx(30.0, abs=1.0)
    turned = base.pose
    assert run(base.driver, command(Action.TURN_RIGHT)) == "done"
    assert heading_deg(turned, base.pose) == pytest.approx(-30.0, abs=1.0)
    # odometry (from the encoder estimates) agrees with the true pose once at rest
    odom = base.driver.odometry()
    assert (odom.x, odom.y) == pytest.approx((base.pose.x, base.pose.y), abs=0.002)
    assert odom.yaw == pytest.approx(base.pose.yaw, abs=math.radians(0.2))
    assert wheels_at_rest(base.driver, base.driver.config.settle_rev_s)


def test_stop_completes_at_rest_and_a_resent_id_runs_once(base: WheeledSimRobot) -> None:
    cmd = command(Action.MOVE_FORWARD)
    assert run(base.driver, cmd) == "done"
    assert base.driver.submit(cmd) == "duplicate"          # the planner re-sent it
    assert run(base.driver, command(Action.STOP)) == "done"
    assert base.driver.state().mode is DriverMode.READY
    assert base.pose.x == pytest.approx(0.25, abs=0.01)    # once, not twice
    assert base.driver.counters["duplicates"] == 1


def test_velocity_limits_hold_for_an_excessive_teleop_command(base: WheeledSimRobot) -> None:
    cfg = base.driver.config
    fastest = 0.0
    for _ in range(15):  # renewed well within the deadman
        base.driver.submit(command(linear=5.0, angular=0.0))
        time.sleep(0.1)
        fastest = max(fastest, base.driver.odometry().linear)
    assert fastest == pytest.approx(cfg.max_linear_m_s, rel=0.05)


def test_deadman_ramps_to_zero_when_commands_stop(base: WheeledSimRobot) -> None:
    d, cfg = base.driver, base.driver.config
    for _ in range(10):  # a teleop stream: keeps moving past the deadman time
        d.submit(command(linear=0.2))
        time.sleep(0.1)
    assert d.state().mode is DriverMode.MOVING and d.odometry().linear > 0.15
    last = time.monotonic()
    wait_for(lambda: wheels_at_rest(d), 10, "wheels at rest after the deadman")
    stopped_after = time.monotonic() - last
    ramp = 0.2 / cfg.max_linear_accel_m_s2
    # generous: a slow CI host adds its scheduling delays to 0.5 s + the ramp
    assert stopped_after < cfg.deadman_s + ramp + 2.0
    state = d.state()
    assert state.mode is DriverMode.READY and state.last_outcome == "aborted"
    assert d.counters["deadman"] == 1
    x = base.pose.x
    time.sleep(0.3)
    assert base.pose.x == pytest.approx(x, abs=1e-4)  # holding (0.2 m/s would be 6 cm)


def test_a_blocked_move_backs_off_to_its_start_and_reports_blocked() -> None:
    base = sim_base(is_free=lambda x, y: x < 0.1)  # a wall 10 cm ahead
    try:
        assert run(base.driver, command(Action.MOVE_FORWARD)) == "blocked"
        wait_for(lambda: wheels_at_rest(base.driver), 10, "wheels at rest")
        assert base.pose.x == pytest.approx(0.0, abs=0.01)  # back where the step began
        assert base.driver.odometry().x == pytest.approx(base.pose.x, abs=0.005)
        assert base.driver.counters["back_offs"] == 1
        assert base.driver.state().mode is DriverMode.READY
    finally:
        base.stop()


def test_the_driver_advertises_its_primitive_sizes() -> None:
    from ovamos.services.base_driver.config import DriverConfig
    from ovamos.services.base_driver.controller import BaseDriver
    from ovamos.shared.robot import PRIMITIVES, Primitives

    assert BaseDriver(DriverConfig()).state().primitives == PRIMITIVES
    assert BaseDriver(DriverConfig(forward_m=0.3)).state().primitives == Primitives(forward_m=0.3)


def test_a_primitive_runs_on_the_planners_keep_alive_and_stops_when_it_stops() -> None:
    """command_timeout_s: copies of the active command (the planner re-sends it every resend_s)
    keep a primitive going; without them (the link is down) it is aborted and the wheels stop."""
    base = sim_base(command_timeout_s=0.5)
    try:
        d, cfg = base.driver, base.driver.config
        kept = command(Action.MOVE_FORWARD)
        assert d.submit(kept) == "accepted"
        while d.state().last_completed < kept.action_id:
            time.sleep(0.2)
            d.submit(kept)  # the keep-alive: a duplicate, executed once
        assert d.state().last_outcome == "done" and base.pose.x == pytest.approx(0.25, abs=0.01)
        orphan = command(Action.MOVE_FORWARD)
        sent = time.monotonic()
        assert d.submit(orphan) == "accepted"
        wait_for(lambda: d.state().last_completed >= orphan.action_id, 10, "the orphaned command ends")
        wait_for(lambda: wheels_at_rest(d), 10, "wheels at rest")
        stopped_after = time.monotonic() - sent
        assert d.state().last_outcome == "aborted" and d.counters["command_timeouts"] == 1
        ramp = cfg.max_linear_m_s / cfg.max_linear_accel_m_s2
        assert stopped_after < cfg.command_timeout_s + ramp + 1.0  # generous for a loaded CI host
        assert 0.26 < base.pose.x < 0.45                           # short of the second 0.25 m
    finally:
        base.stop()
