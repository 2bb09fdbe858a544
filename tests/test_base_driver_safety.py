"""Safety of the driver against simulated ODrives: watchdog, heartbeats, e-stop, bus errors, bad frames.

Every fault is injected through the simulated hardware (or a real python-can
configuration that cannot open), never by poking the driver's state.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Iterator

import can
import numpy as np
import pytest

from ovamos.services.base_driver.config import DriverConfig
from ovamos.services.base_driver.controller import BaseDriver
from ovamos.services.base_driver.odrive.config import CanConfig, ODriveConfig
from ovamos.services.base_driver.odrive.protocol import AxisState, CanSimple, Cmd, ControlMode, InputMode, ODriveError
from ovamos.services.base_driver.odrive.sim import SimAxisConfig, SimODrives
from ovamos.services.sim.wheels import WheeledSimRobot
from ovamos.shared.messages import DriverMode
from ovamos.shared.motion import Action
from tests.base_driver_helpers import command, run, sim_base, wait_for_mode, wheels_at_rest
from tests.polling import wait_for

pytestmark = [pytest.mark.system, pytest.mark.serial]  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)

WATCHDOG = ODriveError.WATCHDOG_TIMER_EXPIRED


@pytest.fixture
def base() -> Iterator[WheeledSimRobot]:
    base = sim_base(recover_every_s=0.3)
    yield base
    base.stop()


def _axes_idle(base: WheeledSimRobot) -> bool:
    with base.odrives.lock:
        return all(a.state is AxisState.IDLE for a in base.odrives.axes.values())


def test_the_odrive_watchdog_disarms_an_axis_nobody_feeds() -> None:
    """The simulated ODrive on its own: setpoints stop => IDLE + WATCHDOG_TIMER_EXPIRED."""
    proto = CanSimple([0])
    with SimODrives([0], config=SimAxisConfig(watchdog_timeout_s=0.2)) as sim, \
            can.Bus(interface="virtual", channel=sim.channel) as bus:
        bus.send(proto.encode(0, Cmd.SET_CONTROLLER_MODE, Control_Mode=ControlMode.VELOCITY_CONTROL,
                              Input_Mode=InputMode.PASSTHROUGH))
        bus.send(proto.encode(0, Cmd.SET_AXIS_STATE, Axis_Requested_State=AxisState.CLOSED_LOOP_CONTROL))
        axis = sim.axes[0]
        for _ in range(10):  # fed every 50 ms: stays armed
            bus.send(proto.encode(0, Cmd.SET_INPUT_VEL, Input_Vel=1.0, Input_Torque_FF=0.0))
            time.sleep(0.05)
        assert axis.armed and axis.vel == 1.0
        # ... then nothing: it disarms and says why in its heartbeat
        def heartbeat() -> dict | None:
            msg = bus.recv(0.5)
            while msg is not None and msg.arbitration_id != 0x001:
                msg = bus.recv(0.5)
            return None if msg is None else proto.decode(msg).signals
        wait_for(lambda: (hb := heartbeat()) and hb["Axis_State"] == AxisState.IDLE
                 and hb["Axis_Error"] & WATCHDOG, 5, "a heartbeat reporting the watchdog expiry")
        wait_for(lambda: axis.vel == 0.0, 5, "the disarmed wheel at rest")


def test_a_hung_driver_lets_the_watchdog_stop_the_wheels_then_recovers(base: WheeledSimRobot,
                                                                     caplog: pytest.LogCaptureFixture) -> None:
    d = base.driver
    d.submit(command(linear=0.2))
    wait_for(lambda: d.odometry().linear > 0.1, 10, "moving")
    with d._lock:  # the control loop hangs (as a stuck process would): no more setpoints
        wait_for(lambda: all(a.errors & WATCHDOG for a in base.odrives.axes.values()), 5,
                 "the watchdogs expiring")
        assert _axes_idle(base)
    # the driver sees the disarmed axes, faults (aborting the command), then recovers on its own
    wait_for(lambda: d.counters["faults"] >= 1 and d.counters["recoveries"] >= 1, 10, "fault + recovery")
    assert "WATCHDOG_TIMER_EXPIRED" in caplog.text
    wait_for_mode(d, DriverMode.READY)
    assert all(a.errors == 0 for a in base.odrives.axes.values())


def test_a_stall_shorter_than_the_heartbeat_timeout_is_not_a_heartbeat_fault() -> None:
    """A busy host stalls the control loop and the CAN reader alike for a little under the timeout.

    The first tick after it sees heartbeat ages of the stall plus part of a heartbeat period from
    before it: over the timeout although the axes never stopped talking (the reader has their
    frames queued). The driver runs on an injected clock here, this test playing both ODrives,
    so the timing is exact.
    """
    t = [0.0]
    config = DriverConfig(odrive=ODriveConfig(can=CanConfig(interface="virtual", channel="stall-test")))
    left, right = config.odrive.left.node_id, config.odrive.right.node_id
    proto = CanSimple([left, right])
    d = BaseDriver(config, clock=lambda: t[0])

    def odrives_talk() -> None:
        received = d.counters["frames_rx"]
        for node in (left, right):
            bus.send(proto.encode(node, Cmd.HEARTBEAT, Axis_Error=0, Procedure_Result=0, Trajectory_Done_Flag=1,
                                  Axis_State=AxisState.CLOSED_LOOP_CONTROL))
            bus.send(proto.encode(node, Cmd.GET_ENCODER_ESTIMATES, Pos_Estimate=0.0, Vel_Estimate=0.0))
        wait_for(lambda: d.counters["frames_rx"] >= received + 4, 5, "the driver reading the frames")

    with can.Bus(interface="virtual", channel="stall-test") as bus:
        try:
            d.tick()  # opens the bus, starts enabling
            t[0] = 0.01
            odrives_talk()
            d.tick()
            assert d.state().mode is DriverMode.READY
            t[0] = 0.05
            d.tick()
            t[0] = 0.33  # stalled 0.28 s: the last heartbeats are 0.32 s old
            d.tick()
            assert d.counters["faults"] == 0, d.state().faults
            odrives_talk()  # the reader catches up
            for t[0] in (0.35, 0.40, 0.60):
                d.tick()
            assert d.counters["faults"] == 0, d.state().faults
            for t[0] in np.arange(0.62, 0.96, 0.02):  # silent while the loop ticks on: a fault
                d.tick()
            assert any("no heartbeat" in f for f in d.state().faults)
        finally:
            d.stop()


def test_heartbeat_loss_is_a_fault_until_heartbeats_return(base: WheeledSimRobot) -> None:
    d = base.driver
    base.odrives.drop_heartbeats(1)
    wait_for_mode(d, DriverMode.FAULT)
    assert any("no heartbeat from the right axis (node 1)" in f for f in d.state().faults)
    wait_for(lambda: _axes_idle(base), 5, "every axis told IDLE")
    assert d.submit(command(Action.MOVE_FORWARD)) == "rejected"
    assert d.state().last_outcome == "rejected"
    time.sleep(0.5)
    assert d.state().mode is DriverMode.FAULT  # no recovery while heartbeats are missing
    base.odrives.drop_heartbeats(1, drop=False)
    wait_for_mode(d, DriverMode.READY)
    assert d.state().faults == ()


def test_estop_latches_until_an_explicit_clear(base: WheeledSimRobot) -> None:
    d = base.driver
    d.submit(command(linear=0.2))
    wait_for(lambda: d.odometry().linear > 0.1, 10, "moving")
    d.engage_estop("test", "a person in the way")
    state = d.state()
    assert state.mode is DriverMode.ESTOP and state.estop_latched and state.last_outcome == "aborted"
    assert "e-stop by test: a person in the way" in state.faults
    wait_for(lambda: _axes_idle(base) and all(a.errors & ODriveError.ESTOP_REQUESTED
                                              for a in base.odrives.axes.values()), 5, "Estop applied")
    wait_for(lambda: wheels_at_rest(d), 10, "wheels at rest")
    x = base.pose.x
    # no motion while latched: commands are rejected, time passing does not unlatch it
    assert d.submit(command(Action.MOVE_FORWARD)) == "rejected"
    time.sleep(1.0)
    assert d.state().mode is DriverMode.ESTOP and base.pose.x == pytest.approx(x, abs=1e-4)
    d.clear_estop("test")
    wait_for_mode(d, DriverMode.READY)
    assert run(d, command(Action.MOVE_FORWARD)) == "done"
    assert base.pose.x == pytest.approx(x + 0.25, abs=0.01)


def test_bus_off_is_a_fault_without_spinning_and_recovers_when_the_bus_returns(base: WheeledSimRobot) -> None:
    d = base.driver
    d.submit(command(linear=0.2))
    wait_for(lambda: d.odometry().linear > 0.1, 10, "moving")
    base.odrives.set_bus_off(True)
    wait_for_mode(d, DriverMode.FAULT)
    assert any("bus off" in f for f in d.state().faults), d.state().faults
    assert d.state().last_outcome == "aborted"
    time.sleep(1.0)
    # each reader stopped at its first receive error instead of spinning on the dead bus
    assert d.counters["reader_errors"] <= d.counters["bus_opens"], d.counters
    assert d.counters["bus_opens"] >= 2  # it keeps trying to reopen, at recover_every_s
    # the ODrives heard nothing: their watchdogs disarmed them
    wait_for(lambda: _axes_idle(base), 5, "axes disarmed by their watchdogs")
    base.odrives.set_bus_off(False)
    wait_for_mode(d, DriverMode.READY)
    assert run(d, command(Action.TURN_LEFT)) == "done"


def test_a_missing_socketcan_interface_is_a_clear_fault_not_a_crash() -> None:
    config = DriverConfig(odrive=ODriveConfig(can=CanConfig(interface="socketcan", channel="ovamos-none0")),
                          recover_every_s=0.2)
    with BaseDriver(config) as d:
        state = d.state()
        assert state.mode is DriverMode.FAULT
        assert state.faults and state.faults[0].startswith("CAN bus unavailable: OSError")
        wait_for(lambda: d.counters["bus_opens"] >= 3, 10, "reopen attempts")
        assert d.submit(command(Action.MOVE_FORWARD)) == "rejected"


def test_an_axis_error_names_its_bits_and_a_sticky_one_blocks_recovery(base: WheeledSimRobot) -> None:
    d = base.driver
    base.odrives.inject_error(0, ODriveError.DRV_FAULT, sticky=True)
    wait_for_mode(d, DriverMode.FAULT)
    wait_for(lambda: any("left axis (node 0)" in f and "DRV_FAULT" in f and "disarm reason" in f
                         for f in d.state().faults), 5, f"a named fault ({d.state().faults})")
    time.sleep(1.5)  # recovery is tried but Clear_Errors cannot clear a hardware fault
    assert d.state().mode in (DriverMode.FAULT, DriverMode.IDLE) and d.counters["recoveries"] >= 1
    base.odrives.clear_injected(0)
    wait_for_mode(d, DriverMode.READY)


def test_malformed_and_unexpected_frames_are_counted_and_ignored(base: WheeledSimRobot) -> None:
    d = base.driver
    before = d.odometry()
    bad = [
        can.Message(arbitration_id=0x009, data=struct.pack("<ff", math.nan, 0.0), is_extended_id=False),
        can.Message(arbitration_id=0x009, data=b"\x01\x02", is_extended_id=False),
        can.Message(arbitration_id=0x021, data=b"\x00", is_extended_id=False),
    ]
    unexpected = [
        can.Message(arbitration_id=5 << 5 | 0x009, data=bytes(8), is_extended_id=False),
        can.Message(arbitration_id=0x01F, data=bytes(8), is_extended_id=False),
        can.Message(arbitration_id=0x009, data=bytes(8), is_extended_id=True),
        can.Message(arbitration_id=0x00D, data=bytes(8), is_extended_id=False),  # another master's setpoint
    ]
    with can.Bus(interface="virtual", channel=base.odrives.channel) as intruder:
        for msg in bad + unexpected:
            intruder.send(msg)
        wait_for(lambda: d.counters["malformed"] == len(bad) and d.counters["unexpected"] == len(unexpected),
                 5, f"frames counted ({dict(d.counters)})")
    time.sleep(0.2)
    after = d.odometry()
    assert d.state().mode is DriverMode.READY
    assert (after.x, after.y, after.yaw) == (before.x, before.y, before.yaw)  # the NaN was not used
    assert run(d, command(Action.MOVE_FORWARD)) == "done"
