"""A planner killed mid-task and started again goes on with the task's progress (issue 33, 9a).

The planner runs as its own process (``ovamos run planner``) and is SIGKILLed twice in the
middle of a search; the gateway is the real one (its task record is what a person reads), the
base and the map are mocks (named so) that count the commands the base received. Before the
fix the restarted planner began the task again at step 0 with its whole budget: the record's
steps fell back, and the base ran more commands than the step limit allows. A kill between a
command's completion and its report lost that step too (about one run in two here) until the
next planner booked it from the driver's count.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from ovamos.services.gateway.client import GatewayClient
from ovamos.services.planner.task import SearchTask
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import FoundObject, MapSnapshot, ObjectInstance, TaskSpec, TaskStatus
from ovamos.shared.procs import kill
from tests.conftest import StartCli
from tests.gateway_mocks import RunningGateway, gateway_config
from tests.polling import wait_for
from tests.test_planner_service import ROBOT, MockBaseAndMap

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

MAX_STEPS = 40
ROWS, COLS = 60, 600  # a corridor 3 m by 30 m: the cup at its far end takes more than MAX_STEPS


class MockCorridor(MockBaseAndMap):
    """The mock base of the planner's service tests in a long explored corridor with a confirmed
    cup out of reach of the step budget; it reports its state every 0.1 s, as a driver does (a
    restarted planner waits for one before it decides)."""

    def __init__(self, bus: Bus) -> None:
        super().__init__(bus)
        self.objects = (ObjectInstance(label="cup", x=28.0, y=1.0, score=0.9, hits=3, confirmed=True),)
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._heartbeat, daemon=True)
        self._beat.start()

    def _heartbeat(self) -> None:
        while not self._stop.wait(0.1):
            self.publish()

    def close(self) -> None:
        self._stop.set()
        self._beat.join(5)

    def snapshot(self) -> MapSnapshot:
        with self.lock:
            return MapSnapshot(seq=self.frame_seq, after_action=self.completed, stamp=time.time(),
                               resolution=0.05, origin=(0.0, 0.0), layers=("cup",), objects=self.objects,
                               obstacle=np.zeros((ROWS, COLS), bool), explored=np.ones((ROWS, COLS), bool),
                               counts=np.zeros((1, ROWS, COLS), np.uint16),
                               values=np.zeros((1, ROWS, COLS), np.float32), frontiers=np.zeros((0, 2)))

    def commands(self) -> int:
        """How many distinct commands the base received (a re-sent copy counts once)."""
        with self.lock:
            return len(self.executed)


@pytest.fixture
def base(inproc_router: str) -> Iterator[MockCorridor]:
    with Bus.open(build_config(connect=[inproc_router]), ROBOT, "test-mock") as bus:
        mock = MockCorridor(bus)
        yield mock
        mock.close()


@pytest.fixture
def api(inproc_router: str, tmp_path: Path) -> Iterator[GatewayClient]:
    gateway = RunningGateway(inproc_router, gateway_config(tmp_path / "state", robots=[ROBOT]))
    with GatewayClient(gateway.url) as client:
        yield client
    gateway.close()


def test_a_planner_killed_mid_task_keeps_the_tasks_steps_distance_and_budget(
        cli: StartCli, inproc_router: str, base: MockCorridor, api: GatewayClient) -> None:
    def planner() -> subprocess.Popen:
        return cli("run", "planner", "--connect", inproc_router, "--robot-id", ROBOT, "--log-level",
                   "WARNING", "--set", "tick_hz=50", "--set", 'agent={"initial_turns": 1}')

    proc = planner()
    task_id = api.submit(["cup"], robot_id=ROBOT, max_steps=MAX_STEPS).id
    seen: list[tuple[int, float]] = []  # the record's (steps, distance) as a person polling sees it

    def steps_reach(n: int) -> bool:
        view = api.get(task_id)
        seen.append((view.steps, view.distance_m))
        return view.steps >= n

    for at in (10, 22):
        wait_for(lambda at=at: steps_reach(at), timeout=60, what=f"the task at step {at}", interval=0.05)
        kill(proc)
        proc = planner()
    final = api.wait(task_id, timeout_s=120, poll_s=0.05, on_update=lambda v: seen.append(
        (v.steps, v.distance_m)))

    assert final.status is TaskStatus.FAILED and final.message.startswith(f"step limit {MAX_STEPS} reached")
    assert final.steps == MAX_STEPS
    steps, distances = [s for s, _ in seen], [d for _, d in seen]
    assert steps == sorted(steps) and distances == sorted(distances), "the record's progress went back"
    # the step budget is the task's, not each planner process's (before the fix the base ran 40
    # commands after the last restart alone), and a command the killed planner had not reported
    # yet is booked by the next one: the count is the commands the base ran, the distance its
    assert base.commands() == final.steps
    assert final.distance_m == pytest.approx(base.x - 1.0)


def test_a_resumed_task_with_nothing_left_to_do_ends_at_once() -> None:
    """The planner was killed after the last step but before reporting how the task ended."""
    spent = SearchTask.from_spec(TaskSpec(task_id="t", targets=("cup",), max_steps=5, steps=5, stamp=0.0))
    spent.start()
    assert spent.state is TaskStatus.FAILED and spent.reason == "step limit 5 reached"
    cup = FoundObject(label="cup", x=1.0, y=2.0, step=3)
    found = SearchTask.from_spec(TaskSpec(task_id="t", targets=("cup",), steps=3, found=(cup,), stamp=0.0))
    found.start()
    assert found.state is TaskStatus.DONE and found.found == {"cup": cup}
