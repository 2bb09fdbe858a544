"""The planner service over real Zenoh: a task in, commands out in lock-step, progress reported.

The base and the mapping service are mocks (named so): the mock base executes a
command by bumping its frame seq and reporting completion; the mock map answers
snapshot queries with that seq, an empty explored room and a confirmed cup.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from ovamos.services.perception.config import PerceptionServiceConfig, SimBackendConfig
from ovamos.services.planner.config import PlannerServiceConfig
from ovamos.services.planner.service import PlannerService
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import (
    DriverMode,
    DriverState,
    MapSnapshot,
    ObjectInstance,
    Odometry,
    PlanCommand,
    ServiceStats,
    TaskEvent,
    TaskSpec,
    TaskStatus,
)
from tests.perception_helpers import RunningPerception
from tests.polling import wait_for
from tests.service_helpers import Running
from tests.sim_scenes import two_rooms

ROBOT = "r1"
N = 120


class MockBaseAndMap:
    """Executes primitives on a kinematic pose, answers map queries; counts executions per id."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.lock = threading.Lock()
        self.executed: dict[int, int] = {}
        self.frame_seq, self.completed, self.x = 0, 0, 1.0
        self.state_pub = bus.publisher(keys.driver_state(ROBOT), DriverState)
        self.odom_pub = bus.publisher(keys.odom(ROBOT), Odometry)
        cup = ObjectInstance(label="cup", x=2.5, y=1.0, score=0.9, hits=3, confirmed=True)
        self.objects = (cup,)
        bus.subscribe(keys.plan_command(ROBOT), PlanCommand, self.on_command)
        bus.queryable(keys.map_snapshot(ROBOT), self.snapshot)

    def snapshot(self) -> MapSnapshot:
        with self.lock:
            return MapSnapshot(seq=self.frame_seq, after_action=self.completed, stamp=time.time(), resolution=0.05, origin=(0.0, 0.0),
                               layers=("cup",), objects=self.objects, obstacle=np.zeros((N, N), bool),
                               explored=np.ones((N, N), bool), counts=np.zeros((1, N, N), np.uint16),
                               values=np.zeros((1, N, N), np.float32), frontiers=np.zeros((0, 2)))

    def on_command(self, cmd: PlanCommand) -> None:
        with self.lock:
            self.executed[cmd.action_id] = self.executed.get(cmd.action_id, 0) + 1
            if cmd.action_id <= self.completed:
                return  # a re-sent copy: executed once only
            if cmd.action is not None and cmd.action.value == "MOVE_FORWARD":
                self.x += 0.25
            self.completed, self.frame_seq = cmd.action_id, self.frame_seq + 1
        self.publish()

    def publish(self) -> None:
        with self.lock:
            state = DriverState(stamp=time.time(), mode=DriverMode.READY, last_completed=self.completed,
                                last_outcome="done" if self.completed else None)
            odom = Odometry(seq=self.completed, stamp=time.time(), x=self.x, y=1.0, yaw=0.0,
                            after_action=self.completed)
        self.odom_pub.put(odom)
        self.state_pub.put(state)


@pytest.fixture
def planner(inproc_router: str) -> Iterator[None]:
    config = PlannerServiceConfig(tick_hz=50)
    config.agent.initial_turns = 1
    running = Running(PlannerService, inproc_router, config)
    yield
    running.close()


def test_a_task_runs_in_lock_step_to_the_found_object(planner, inproc_router) -> None:
    events: list[TaskEvent] = []
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-mock") as bus:
        base = MockBaseAndMap(bus)
        bus.subscribe(keys.task_events(ROBOT), TaskEvent, events.append)
        task_pub = bus.publisher(keys.task_current(ROBOT), TaskSpec)
        spec = TaskSpec(task_id="t1", targets=("cup",), stamp=time.time())

        def progressed() -> bool:
            task_pub.put(spec)  # the gateway re-publishes its task too
            base.publish()
            return any(e.status is TaskStatus.DONE for e in events)

        wait_for(progressed, timeout=30, what="the task is done")
    done = next(e for e in events if e.status is TaskStatus.DONE)
    assert [f.label for f in done.found] == ["cup"]
    # one scan turn, then forward until within 0.9 m of the cup at x = 2.5, then STOP
    assert done.steps == base.completed and 3 <= done.steps <= 6
    assert base.x >= 2.5 - 0.9
    assert all(n >= 1 for n in base.executed.values()) and sorted(base.executed) == list(
        range(1, base.completed + 1))


def test_a_malformed_task_is_counted_and_the_service_keeps_running(planner, inproc_router) -> None:
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-mock") as bus:
        events: list[TaskEvent] = []
        bus.subscribe(keys.task_events(ROBOT), TaskEvent, events.append)
        session = bus.session
        spec = TaskSpec(task_id="t2", targets=("cup",), stamp=time.time())

        def planner_counted_it() -> bool:
            session.put(keys.task_current(ROBOT), b'{"v": 1, "task_id": 7}')
            stats = bus.get(keys.stats(ROBOT, "planner", "0"), ServiceStats)
            counters = stats.counters.get(keys.task_current(ROBOT)) if stats else None
            return counters is not None and counters.malformed >= 1

        wait_for(planner_counted_it, what="the malformed task is counted")
        wait_for(lambda: session.put(keys.task_current(ROBOT), spec.to_bytes())
                 or any(e.task_id == "t2" for e in events), what="a valid task is still accepted")


def test_a_target_the_simulated_house_cannot_hold_fails_the_task_naming_the_closest_class(
        planner, inproc_router, tmp_path) -> None:
    """``candel`` with the sim backend: perception never scores it, so the map never gets its
    values; the planner asks perception why and fails the task with its words (before, the task
    sat at step 0 for ever, waiting for perception)."""
    scene_file = tmp_path / "scene.json"
    two_rooms().save(scene_file)
    perception = RunningPerception(inproc_router, PerceptionServiceConfig(sim=SimBackendConfig(
        scene_file=scene_file)))
    events: list[TaskEvent] = []
    try:
        with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-mock") as bus:
            base = MockBaseAndMap(bus)  # its map has values of the cup only
            bus.subscribe(keys.task_events(ROBOT), TaskEvent, events.append)
            task_pub = bus.publisher(keys.task_current(ROBOT), TaskSpec)
            spec = TaskSpec(task_id="t3", targets=("cup", "candel"), stamp=time.time())

            def failed() -> TaskEvent | None:
                task_pub.put(spec)  # the gateway's re-publication, which perception reads too
                base.publish()
                return next((e for e in events if e.status is TaskStatus.FAILED), None)

            event = wait_for(failed, timeout=30, what="the task failed")
    finally:
        perception.close()
    assert event.message.startswith("unknown target 'candel' for the simulated house: did you mean "
                                    "'candle'? it can have: ")
    assert event.steps == 0 and base.completed == 0
