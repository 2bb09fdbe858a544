"""Running a service in a thread over real Zenoh, and talking to it as the planner would."""

from __future__ import annotations

import threading
from typing import Any

from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.status import live_services
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import DriverState, Odometry, PlanCommand
from ovamos.shared.service import Service, ServiceConfig, run_service
from tests.polling import wait_for

ROBOT = "r1"


class Running:
    """``cls`` run by :func:`run_service` in a thread; :meth:`close` stops and joins it."""

    def __init__(self, cls: type[Service], endpoint: str, config: ServiceConfig, robot_id: str = ROBOT) -> None:
        self.stop = threading.Event()
        self.thread = threading.Thread(target=run_service, args=(cls, build_config(connect=[endpoint]), config),
                                       kwargs={"robot_id": robot_id, "instance": "0", "stop": self.stop})
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(30)
        assert not self.thread.is_alive()


class Planner:
    """Records what the driver publishes and re-sends a command until it shows up (as the planner)."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.states: list[DriverState] = []
        self.odoms: list[Odometry] = []
        self.commands = bus.publisher(keys.plan_command(ROBOT), PlanCommand)
        bus.subscribe(keys.driver_state(ROBOT), DriverState, self.states.append)
        bus.subscribe(keys.odom(ROBOT), Odometry, self.odoms.append)

    def state(self) -> DriverState | None:
        return self.states[-1] if self.states else None

    def execute(self, command: PlanCommand, timeout: float = 30.0) -> DriverState:
        """Send until the driver reports it active or completed, then wait for completion."""
        def sent() -> bool:
            s = self.state()
            if s is not None and (s.active_action == command.action_id or s.last_completed >= command.action_id):
                return True
            self.commands.put(command)
            return False
        wait_for(sent, timeout, f"command {command.action_id} taken")
        return wait_for(lambda: (s := self.state()) and s.last_completed >= command.action_id and s,
                        timeout, f"command {command.action_id} completed")


def service_stats(bus: Bus, service: str) -> Any:
    (svc,) = [s for s in live_services(bus.session, ROBOT) if s.service == service]
    return svc.stats
