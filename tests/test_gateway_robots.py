"""The gateway's robot monitor without a bus: an e-stop is confirmed only by a driver state
received after it was first sent, and re-sent until then; a driver that never confirms is an
error that says what is known. (tests/test_gateway_hardening.py covers the same over Zenoh.)"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from ovamos.services.gateway.config import GatewayConfig
from ovamos.services.gateway.robots import EStopUnconfirmed, RobotMonitor
from ovamos.shared.messages import DriverMode, DriverState, EStop, Odometry

ROBOT = "r1"


def state(latched: bool) -> DriverState:
    return DriverState(stamp=time.time(), mode=DriverMode.ESTOP if latched else DriverMode.IDLE,
                       estop_latched=latched)


class Driver:
    """The robot's end of ``driver/estop``: records requests, and latches after ``confirm_after``."""

    def __init__(self, confirm_after: int | None) -> None:
        self.sent: list[tuple[str, EStop]] = []
        self.confirm_after = confirm_after
        self.monitor: RobotMonitor | None = None

    def receive(self, robot: str, request: EStop) -> None:
        self.sent.append((robot, request))
        if self.confirm_after is not None and len(self.sent) >= self.confirm_after:
            assert self.monitor is not None  # its state comes back on the owner thread, not this one
            threading.Thread(target=self.monitor.on_driver_state, args=(robot, state(request.engage))).start()


def monitor_for(driver: Driver, tmp_path: Path, **kw: float) -> RobotMonitor:
    config = GatewayConfig(state_dir=tmp_path, robots=[ROBOT], **kw)
    driver.monitor = RobotMonitor(config, estop=driver.receive, estop_clear=driver.receive)
    return driver.monitor


def test_an_estop_is_resent_until_a_later_driver_state_confirms_it(tmp_path: Path) -> None:
    driver = Driver(confirm_after=3)
    monitor = monitor_for(driver, tmp_path, estop_resend_s=0.05, estop_confirm_s=5.0)
    monitor.on_driver_state(ROBOT, state(latched=True))  # latched before the request: no confirmation
    confirmed = monitor.engage_estop(ROBOT, "test")
    assert confirmed.estop_latched and len(driver.sent) == 3
    assert all(robot == ROBOT and request.engage and request.reason == "test" for robot, request in driver.sent)
    assert monitor.driver(ROBOT).count == 2  # the state before the request, and the one confirming it


def test_an_estop_the_driver_never_confirms_is_an_error_that_says_what_is_known(tmp_path: Path) -> None:
    driver = Driver(confirm_after=None)
    monitor = monitor_for(driver, tmp_path, estop_resend_s=0.05, estop_confirm_s=0.2)
    with pytest.raises(EStopUnconfirmed, match="no driver state has ever been received") as raised:
        monitor.engage_estop(ROBOT, "test")
    assert "may still be moving" in str(raised.value) and len(driver.sent) >= 3
    monitor.on_driver_state(ROBOT, state(latched=True))
    with pytest.raises(EStopUnconfirmed, match="says mode estop, e-stop latched"):
        monitor.clear_estop(ROBOT)
    assert not driver.sent[-1][1].engage


def test_driver_states_and_odometry_of_another_session_are_never_kept_nor_confirm_an_estop(tmp_path: Path) -> None:
    """Issue 49: the page drew forged odometry. The monitor follows the robot's odometry session as
    every consumer does: a forged stream while the driver talks is counted, not kept, and a forged
    'latched' state does not confirm an e-stop the driver never latched."""
    driver = Driver(confirm_after=None)
    monitor = monitor_for(driver, tmp_path, estop_resend_s=0.05, estop_confirm_s=0.3)
    real = DriverState(stamp=time.time(), mode=DriverMode.READY, odom_session="A")
    monitor.on_driver_state(ROBOT, real)
    monitor.on_odom(ROBOT, Odometry(seq=1, stamp=0.0, x=2.0, y=3.0, yaw=0.0, odom_session="A"))
    for k in range(30):
        monitor.on_odom(ROBOT, Odometry(seq=k + 2, stamp=0.0, x=2.0, y=3.0, yaw=0.0, odom_session="A"))
        monitor.on_odom(ROBOT, Odometry(seq=k + 1, stamp=0.0, x=0.0, y=0.0, yaw=0.0, odom_session="forged"))
    kept = monitor.odometry(ROBOT)
    assert kept is not None and (kept.message.x, kept.message.odom_session) == (2.0, "A") and kept.count == 31
    assert monitor.sessions[ROBOT].stray["odom"] == 30

    def forge() -> None:  # a state of another session saying the latch is set
        monitor.on_driver_state(ROBOT, DriverState(stamp=time.time(), mode=DriverMode.ESTOP, estop_latched=True,
                                                   odom_session="forged"))
    driver.receive = lambda robot, request: (driver.sent.append((robot, request)), forge())  # type: ignore[method-assign]
    with pytest.raises(EStopUnconfirmed, match="not latched"):
        monitor.engage_estop(ROBOT, "test")
    assert monitor.driver(ROBOT).message == real
