"""The base driver service over real Zenoh (loopback), with simulated ODrives on its virtual bus."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import pytest

from ovamos.services.base_driver.config import BaseDriverServiceConfig, DriverConfig
from ovamos.services.base_driver.odrive.config import CanConfig, ODriveConfig
from ovamos.services.base_driver.service import BaseDriverService
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import DriverMode, EStop, PlanCommand
from ovamos.shared.motion import Action
from tests.polling import wait_for
from tests.service_helpers import ROBOT, Planner, Running, service_stats


@pytest.fixture
def planner(inproc_router: str) -> Iterator[Planner]:
    channel = f"test-{uuid.uuid4().hex[:8]}"
    config = BaseDriverServiceConfig(simulated_axes=True, state_hz=5,
                                     driver=DriverConfig(odrive=ODriveConfig(can=CanConfig(channel=channel))))
    running = Running(BaseDriverService, inproc_router, config)
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-planner") as bus:
        planner = Planner(bus)
        wait_for(lambda: (s := planner.state()) and s.mode is DriverMode.READY, 30, "driver ready")
        yield planner
    running.close()


def test_a_command_completes_and_odometry_follows(planner: Planner) -> None:
    state = planner.execute(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD))
    assert state.last_outcome == "done" and state.last_completed == 1
    wait_for(lambda: planner.odoms and planner.odoms[-1].x == pytest.approx(0.25, abs=0.01), 10,
             "odometry at 0.25 m")
    # re-sent copies of a completed command are not executed again
    for _ in range(5):
        planner.commands.put(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD))
    state = planner.execute(PlanCommand(action_id=2, stamp=0.0, action=Action.TURN_LEFT))
    assert state.last_outcome == "done"
    assert planner.odoms[-1].x == pytest.approx(0.25, abs=0.01)
    stats = service_stats(planner.bus, "base_driver")
    assert stats.info["counters"]["commands"] == 2


def test_malformed_commands_are_counted_and_the_service_keeps_running(planner: Planner) -> None:
    key = keys.plan_command(ROBOT)

    def counted() -> bool:  # repeated: a put before the route to the service is known is lost
        planner.bus.session.put(key, b"{not json")
        planner.bus.session.put(key, b'{"v": 1, "action_id": 0, "stamp": 0}')  # id must be >= 1
        entry = service_stats(planner.bus, "base_driver").counters.get(key)
        return entry is not None and entry.malformed >= 2 and entry.errors == 0
    wait_for(counted, 20, "malformed commands counted")
    state = planner.execute(PlanCommand(action_id=1, stamp=0.0, action=Action.TURN_RIGHT))
    assert state.last_outcome == "done"


def test_estop_over_zenoh_latches_until_cleared(planner: Planner) -> None:
    estop = planner.bus.publisher(keys.estop(ROBOT), EStop)
    wait_for(lambda: estop.put(EStop(engage=True, source="gateway", reason="test", stamp=0.0))
             or planner.state().mode is DriverMode.ESTOP, 10, "e-stop latched")
    state = planner.execute(PlanCommand(action_id=1, stamp=0.0, action=Action.MOVE_FORWARD))
    assert state.last_outcome == "rejected" and state.estop_latched
    # A clear on the engage key (what an e-stop-only credential can put) is refused and counted.
    estop.put(EStop(engage=False, source="operator", stamp=0.0))
    wait_for(lambda: (entry := service_stats(planner.bus, "base_driver").counters.get(keys.estop(ROBOT)))
             is not None and entry.malformed >= 1, 10, "the clear on driver/estop refused")
    assert planner.state().estop_latched
    clear = planner.bus.publisher(keys.estop_clear(ROBOT), EStop)
    wait_for(lambda: clear.put(EStop(engage=False, source="gateway", stamp=0.0))
             or planner.state().mode is DriverMode.READY, 10, "ready after the clear")
    assert planner.execute(PlanCommand(action_id=2, stamp=0.0, action=Action.STOP)).last_outcome == "done"


def test_the_planners_liveliness_gone_is_reported_in_driver_state(planner: Planner, inproc_router: str) -> None:
    """Nothing is said before a planner was seen; its token gone = "planner unreachable"; back = cleared."""
    assert planner.state().warnings == ()
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "planner"):
        wait_for(lambda: service_stats(planner.bus, "base_driver").info.get("planner_reachable") is True
                 and planner.state().warnings == (), 10, "the planner seen")
    wait_for(lambda: planner.state().warnings == ("planner unreachable",), 10, "planner unreachable")
    assert planner.state().mode is DriverMode.READY  # a warning: the base itself is fine
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "planner", "1"):
        wait_for(lambda: planner.state().warnings == (), 10, "the warning cleared")
