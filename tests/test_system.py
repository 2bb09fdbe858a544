"""The whole system under faults: every service a process, a task over HTTP, something killed mid-task.

Each test runs the demo's processes (router, mapping, perception, planner, simulated robot,
gateway) under the supervisor on free loopback ports, submits one of the demo episode's targets and
kills one process once the robot is moving. The task must still complete.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from ovamos.demo import DEMO_EPISODE, DEMO_SEED, demo_entries, write_configs
from ovamos.services.gateway.client import GatewayClient, GatewayError
from ovamos.services.gateway.models import TaskView
from ovamos.shared.messages import MapSnapshot
from ovamos.shared.procs import free_port, kill
from ovamos.supervisor import Backoff, Supervisor, port_open
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

ROBOT = "sim"
FAULT_STEP_BUDGET = 1500
TARGET = "floor_lamp"  # of the demo episode's targets


class System:
    def __init__(self, supervisor: Supervisor, client: GatewayClient, checkpoint: Path) -> None:
        self.supervisor, self.client, self.checkpoint = supervisor, client, checkpoint

    def ready(self) -> bool:
        try:
            services = {s["service"] for s in self.client.health()["robots"][ROBOT]["services"]}
        except (GatewayError, OSError):
            return False
        return services >= {"mapping", "perception", "planner", "sim", "gateway"}

    def task(self, task_id: str) -> TaskView:
        return self.client.get(task_id)


@pytest.fixture
def system(tmp_path: Path) -> Iterator[System]:
    http_port, zenoh_port = free_port(), free_port()
    configs = write_configs(tmp_path / "config", seed=DEMO_SEED, episode=DEMO_EPISODE, robot_id=ROBOT,
                            http_port=http_port)
    mapping = json.loads(configs["mapping"].read_text())
    configs["mapping"].write_text(json.dumps({**mapping, "checkpoint_every_s": 1.0}))
    entries = demo_entries(configs, robot_id=ROBOT, zenoh_port=zenoh_port)
    with Supervisor(entries, log_dir=tmp_path / "logs", backoff=Backoff(initial_s=0.2, max_s=1.0)) as sup, \
            GatewayClient(f"http://127.0.0.1:{http_port}") as client:
        wait_for(lambda: port_open("127.0.0.1", http_port), timeout=60, what="the gateway")
        running = System(sup, client, Path(mapping["checkpoint_path"]))
        wait_for(running.ready, timeout=90, what="every service alive")
        yield running


def _run_with_a_kill(system: System, victim: str, after_steps: int = 8,
                     before_kill: Callable[[str], object] = lambda task_id: None) -> TaskView:
    # The demo's floor lamp: found by step ~22 from the start, so a kill at step 8 lands mid-task
    # and the whole test takes seconds (the demo's three targets take ~200 steps).
    # A kill costs the robot part of its map (up to one checkpoint period) or some commands, and
    # the search then takes a different, possibly longer path: a generous step budget keeps this
    # test about recovery, not about how efficient the method is on a damaged map.
    task_id = system.client.submit([TARGET], robot_id=ROBOT, max_steps=FAULT_STEP_BUDGET).id
    wait_for(lambda: system.task(task_id).steps >= after_steps, timeout=120, what=f"{after_steps} steps")
    before_kill(task_id)
    proc = system.supervisor.process(victim)
    assert proc is not None
    assert not system.task(task_id).final, "the task ended before the kill: search a farther target"
    kill(proc)
    wait_for(lambda: system.task(task_id).final, timeout=300, what="the task ends")
    return system.task(task_id)


def _restarted(system: System, name: str) -> int:
    return next(s.restarts for s in system.supervisor.status() if s.name == name)


def test_a_killed_mapping_process_is_restarted_from_its_checkpoint_and_the_task_completes(system) -> None:
    final = _run_with_a_kill(system, "mapping", before_kill=lambda task_id: wait_for(
        lambda: system.checkpoint.exists(), timeout=10, what="a checkpoint (every 1 s here)"))
    assert final.status.value == "done", final.message
    assert sorted(f.label for f in final.found) == sorted(final.targets)
    assert _restarted(system, "mapping") >= 1
    log = (system.supervisor.status()[0].log_path.parent / "mapping.log").read_text()
    assert "resumed the map from" in log


def test_a_killed_robot_starts_a_new_odometry_session_the_map_starts_again_and_the_task_completes(
        system, tmp_path) -> None:
    """The simulated robot (camera and base driver) killed mid-task and restarted by the
    supervisor: its odometry starts again (a new session, the robot back at the start pose). The
    mapping service starts a fresh map and keeps the old one under its session id, the planner
    drops what it decided in the old frame and searches on the new map, and the task completes."""
    before: list[str | None] = []

    def session_known(task_id: str) -> bool:
        before[:] = [system.task(task_id).odom_session]
        return bool(before[0])
    final = _run_with_a_kill(system, "sim", before_kill=lambda task_id: wait_for(
        lambda: session_known(task_id), timeout=30, what="a task event's odometry session"))
    assert final.status.value == "done", final.message
    assert sorted(f.label for f in final.found) == sorted(final.targets)
    assert _restarted(system, "sim") >= 1
    assert final.odom_session and final.odom_session != before[0]
    logs = system.supervisor.status()[0].log_path.parent
    assert f"odometry session {final.odom_session!r}: a fresh map" in (logs / "mapping.log").read_text()
    assert f"odometry session is now {final.odom_session!r}" in (logs / "planner.log").read_text()
    kept = MapSnapshot.from_bytes((tmp_path / "config" / f"map.{before[0]}.ckpt").read_bytes())
    assert kept.odom_session == before[0] and kept.seq > 0 and kept.explored.any()


def test_a_killed_router_comes_back_and_the_services_reconnect_without_restarts(system) -> None:
    final = _run_with_a_kill(system, "router")
    assert final.status.value == "done", final.message
    assert _restarted(system, "router") >= 1
    assert all(s.restarts == 0 for s in system.supervisor.status() if s.name != "router")
