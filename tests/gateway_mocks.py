"""Test doubles for the gateway's tests: the gateway run for real, and mocks of its peers.

``RunningGateway`` is the real thing (``run_service(GatewayService)`` with
uvicorn on a free loopback port). ``MockPlanner`` and ``MockMapping`` stand in
for the planner and mapping services over real Zenoh: the planner mock
records the TaskSpecs it receives and publishes TaskEvents on demand; the
mapping mock answers ``map/snapshot`` queries with a small fixed map.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from ovamos.services.gateway.config import GatewayConfig
from ovamos.services.gateway.service import GatewayService
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import (
    DecisionTrace,
    DriverMode,
    DriverState,
    EStop,
    FoundObject,
    Goal,
    MapSnapshot,
    ObjectInstance,
    Odometry,
    TaskEvent,
    TaskSpec,
    TaskStatus,
    TraceOption,
)
from ovamos.shared.procs import free_port
from ovamos.shared.service import run_service
from tests.polling import port_open, wait_for

ROBOT = "sim"


def gateway_config(state_dir: Any, **overrides: Any) -> GatewayConfig:
    """A loopback config on a free port with fast re-publication (tests wait less)."""
    return GatewayConfig(**{"port": free_port(), "state_dir": state_dir, "republish_s": 0.2,
                            "cancel_linger_s": 1.0, "map_timeout_s": 1.0, "sse_heartbeat_s": 0.5,
                            **overrides})


class RunningGateway:
    """The gateway service on its own thread, as ``ovamos run gateway`` runs it."""

    def __init__(self, endpoint: str, config: GatewayConfig) -> None:
        self.config = config
        self.url = f"http://127.0.0.1:{config.port}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=run_service, args=(
            GatewayService, build_config(connect=[endpoint]), config),
            kwargs={"robot_id": ROBOT, "instance": "0", "stop": self._stop}, daemon=True)
        self._thread.start()
        wait_for(lambda: port_open(config.port) or not self._thread.is_alive(), what="the gateway")
        assert self._thread.is_alive(), "the gateway stopped during start-up"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(30)
        assert not self._thread.is_alive(), "the gateway did not stop"


ODOM_SESSION = "20261201T120000Z-0a1b2c"
"""The odometry session the mocks' maps and reports are in."""


class MockPlanner:
    """A fake planner (mock): records TaskSpecs from ``task/current``, sends TaskEvents."""

    def __init__(self, endpoint: str, robot_id: str = ROBOT) -> None:
        self.bus = Bus.open(build_config(connect=[endpoint]), robot_id, "mock-planner")
        self._lock = threading.Lock()
        self._specs: list[TaskSpec] = []
        self.bus.subscribe(keys.task_current(robot_id), TaskSpec, self._on_spec)
        self.events = self.bus.publisher(keys.task_events(robot_id), TaskEvent)
        self.traces = self.bus.publisher(keys.plan_trace(robot_id), DecisionTrace)

    def _on_spec(self, spec: TaskSpec) -> None:
        with self._lock:
            self._specs.append(spec)

    def specs(self, task_id: str | None = None) -> list[TaskSpec]:
        with self._lock:
            return [s for s in self._specs if task_id is None or s.task_id == task_id]

    def report(self, task_id: str, status: TaskStatus, targets: list[str], *, steps: int,
               found: tuple[FoundObject, ...] = (), x: float = 0.0, y: float = 0.0,
               goal: Goal | None = None, odom_session: str = ODOM_SESSION) -> None:
        self.events.put(TaskEvent(task_id=task_id, status=status, targets=tuple(targets), found=found,
                                  steps=steps, distance_m=0.25 * steps, stamp=time.time(), x=x, y=y,
                                  message=f"mock step {steps}", goal=goal, odom_session=odom_session))

    def decide(self, task_id: str, options: tuple[TraceOption, ...], step: int = 0) -> None:
        """A decision trace: what this planner weighed (the page draws its candidates)."""
        self.traces.put(DecisionTrace(task_id=task_id, step=step, stamp=time.time(), map_seq=0, robot_x=0.0,
                                      robot_y=0.0, remaining=(), options=options, reason="mock"))

    def close(self) -> None:
        self.bus.close()


def small_map() -> MapSnapshot:
    """A 40 x 40 map: explored square with a wall, one value layer, one confirmed chair."""
    explored = np.zeros((40, 40), bool)
    explored[5:35, 5:35] = True
    obstacle = np.zeros((40, 40), bool)
    obstacle[20, 5:30] = True
    values = np.zeros((1, 40, 40), np.float32)
    values[0, 25:30, 10:15] = 0.8
    return MapSnapshot(seq=3, odom_session=ODOM_SESSION, stamp=time.time(), resolution=0.05, origin=(0.0, 0.0),
                       layers=("chair",),
                       objects=(ObjectInstance(label="chair", x=0.6, y=1.4, score=0.9, hits=3,
                                               confirmed=True),),
                       obstacle=obstacle, explored=explored, counts=np.ones((1, 40, 40), np.uint16),
                       values=values, frontiers=np.array([[1.7, 1.0]]))


class MockMapping:
    """A fake mapping service (mock): answers ``map/snapshot`` queries with :func:`small_map`."""

    def __init__(self, endpoint: str, robot_id: str = ROBOT, service: str = "mock-mapping") -> None:
        self.bus = Bus.open(build_config(connect=[endpoint]), robot_id, service)
        self.bus.queryable(keys.map_snapshot(robot_id), small_map)

    def close(self) -> None:
        self.bus.close()


class MockDriver:
    """A fake base driver (mock) over real Zenoh: latches its e-stop on ``driver/estop`` and clears it
    on ``driver/estop/clear`` as the real one does, publishing its state on every change and a few times a second."""

    def __init__(self, endpoint: str, answer: bool = True) -> None:
        self.bus = Bus.open(build_config(connect=[endpoint]), ROBOT, "mock-driver")
        self.requests: list[EStop] = []
        self.latched = False
        self.answer = answer
        self._states = self.bus.publisher(keys.driver_state(ROBOT), DriverState)
        self._odom = self.bus.publisher(keys.odom(ROBOT), Odometry)
        self.bus.subscribe(keys.estop(ROBOT), EStop, self._on_estop)
        self.bus.subscribe(keys.estop_clear(ROBOT), EStop, self._on_estop)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _on_estop(self, request: EStop) -> None:
        self.requests.append(request)
        self.latched = request.engage
        self._publish()

    def _publish(self) -> None:
        if self.answer:
            self._states.put(DriverState(stamp=0.0, mode=DriverMode.ESTOP if self.latched else DriverMode.READY,
                                         estop_latched=self.latched))
            self._odom.put(Odometry(seq=0, stamp=0.0, x=0.5, y=0.5, yaw=1.0))

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            self._publish()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.bus.close()
