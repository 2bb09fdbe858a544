"""The simulated robot, perception, mapping and planner services' adapters wired on the fake bus (no router).

The services are the real ones (their ``start``/``tick`` and handlers); only the
transport is :mod:`ovamos.shared.fake_bus`, and the test runs their one event loop by
hand, so the lock-step protocol can be checked decision by decision: with the
robot's clock 5 s ahead of or behind the laptop's, the planner must still run
the task to its end and never decide on a map that has not fused a frame taken
after its last command.
"""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import pytest

import ovamos.services.sim.kinematic
from ovamos.services.mapping.config import MappingServiceConfig
from ovamos.services.mapping.service import MappingService
from ovamos.services.perception.config import PerceptionServiceConfig
from ovamos.services.perception.service import PerceptionService
from ovamos.services.perception.sim_backend import SimBackend
from ovamos.services.planner.agent import AgentConfig
from ovamos.services.planner.config import PlannerServiceConfig
from ovamos.services.planner.service import PlannerService
from ovamos.services.sim.config import SimServiceConfig
from ovamos.services.sim.service import SimRobotService
from ovamos.shared import keys
from ovamos.shared.fake_bus import FakeNetwork, key_matches
from ovamos.shared.messages import PlanCommand, TaskEvent, TaskSpec, TaskStatus
from ovamos.shared.motion import Pose
from ovamos.shared.topology import TOPOLOGY
from tests.sim_scenes import two_rooms

ROBOT = "r1"


def test_key_matching_follows_zenoh_wildcards() -> None:
    assert key_matches("ovamos/*/odom", "ovamos/r1/odom")
    assert key_matches("ovamos/r1/**", "ovamos/r1/alive/planner/0")
    assert key_matches("ovamos/**", "ovamos")
    assert not key_matches("ovamos/*/odom", "ovamos/r1/sensors/odom")
    assert not key_matches("ovamos/r1/odom", "ovamos/r2/odom")


@pytest.mark.parametrize("robot_clock_offset_s", [5.0, -5.0])
def test_lock_step_over_the_fake_bus_with_a_skewed_robot_clock(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, robot_clock_offset_s: float) -> None:
    # the robot host's wall clock, off by the offset (monotonic time is per host anyway)
    robot_clock = SimpleNamespace(time=lambda: time.time() + robot_clock_offset_s,
                                  monotonic=time.monotonic, sleep=time.sleep)
    monkeypatch.setattr(ovamos.services.sim.kinematic, "time", robot_clock)
    scene = tmp_path / "scene.json"
    two_rooms().save(scene)
    net = FakeNetwork()
    sim = SimRobotService(net.bus(ROBOT, "sim"), SimServiceConfig(
        scene_file=scene, start=Pose(x=1.5, y=2.0, yaw=0.0), width=96, height=72))
    perception = PerceptionService(net.bus(ROBOT, "perception"), PerceptionServiceConfig(),
                                   SimBackend(two_rooms()))
    mapping = MappingService(net.bus(ROBOT, "mapping"), MappingServiceConfig(
        grid_cells=200, center=(3.0, 2.0)))
    planner_config = PlannerServiceConfig(agent=AgentConfig(initial_turns=1))
    planner = PlannerService(net.bus(ROBOT, "planner"), planner_config)
    running = (sim, perception, mapping, planner)
    tester = net.bus(ROBOT, "tester")
    stale: list[str] = []
    events: list[TaskEvent] = []

    def check_fresh(command: PlanCommand) -> None:
        ex = planner.executive
        if ex.snapshot is not None and ex.driver is not None \
                and ex.snapshot.after_action < ex.driver.last_completed:
            stale.append(f"command {command.action_id} decided on a map of after_action "
                         f"{ex.snapshot.after_action} < {ex.driver.last_completed}")

    tester.subscribe(keys.plan_command(ROBOT), PlanCommand, check_fresh)
    tester.subscribe(keys.task_events(ROBOT), TaskEvent, events.append)
    task = tester.publisher(keys.task_current(ROBOT), TaskSpec)
    try:
        for svc in running:
            svc.start()
        task.put(TaskSpec(task_id="t1", targets=("cup",), max_steps=10, stamp=time.time()))
        deadline = time.monotonic() + 120
        while not (events and events[-1].status in (TaskStatus.DONE, TaskStatus.FAILED)):
            assert time.monotonic() < deadline, f"stuck: {planner.executive.waiting}"
            for svc in running:
                svc.tick()
                net.pump()
            time.sleep(0.002)
    finally:
        for svc in running:
            svc.stop()
    assert stale == []
    assert undeclared(net, [svc.name for svc in running]) == []
    assert {s for s, _, _ in net.used} >= {svc.name for svc in running}  # (each one checked)
    last = events[-1]
    assert last.status is TaskStatus.DONE or last.steps == 10, last
    assert mapping.state.after_action >= 9  # every command's frame was fused, in order


def undeclared(net: FakeNetwork, services: list[str]) -> list[tuple[str, str, str]]:
    """What ``services`` published, subscribed, answered or queried on ``net`` outside their ports in
    the topology (issue 49: every message between services on a declared key with a typed message),
    besides every service's own stats answer."""
    out = []
    for service, kind, key in sorted(net.used):
        if service not in services or key == keys.stats(ROBOT, service, "0"):
            continue
        if key not in {port.key(ROBOT) for port in getattr(TOPOLOGY[service], kind)}:
            out.append((service, kind, key))
    return out


def test_a_key_outside_the_topology_is_found() -> None:
    """The check above can fail: a query the planner's ports do not declare (as its ask of
    perception's stats was) is reported."""
    net = FakeNetwork()
    bus = net.bus(ROBOT, "planner")
    bus.request(keys.stats(ROBOT, "perception"), PlanCommand, lambda _: None, 0.1)
    bus.subscribe(keys.plan_trace(ROBOT), PlanCommand, lambda _: None)
    assert undeclared(net, ["planner"]) == [("planner", "inputs", keys.plan_trace(ROBOT)),
                                            ("planner", "queries", keys.stats(ROBOT, "perception"))]
