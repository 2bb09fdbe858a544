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
from ovamos.shared.messages import DriverMode, DriverState, EStop

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
