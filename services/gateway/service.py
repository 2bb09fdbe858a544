"""``ovamos run gateway``: the gateway's cores wired to the bus, and the HTTP API over them
served by uvicorn inside the common service life cycle.

The cores know nothing of Zenoh: :class:`~ovamos.services.gateway.tasks.TaskManager` (the task
life cycle) and :class:`~ovamos.services.gateway.robots.RobotMonitor` (each robot's driver
state, pose and e-stop). :func:`wire` subscribes them to the inputs the topology declares
(:data:`ovamos.shared.topology.TOPOLOGY`) for every robot the gateway serves, and hands them
that robot's declared outputs. :func:`create_app` builds the app around them: nothing touches
Zenoh at import, the bus is acquired in the app's lifespan (from ``bus_source``, in a worker
thread since opening may wait for a router), so the module can be imported by a process that
forks later, and one process can build several apps (tests restart the gateway on the same
state file). The bus given by ``bus_source`` must have its inbox taken (``ovamos run
gateway``'s main loop, or a bus opened with ``dispatch="thread"``).

Running as a :class:`~ovamos.shared.service.Service` gives the gateway what every
service has (a liveliness token, a stats queryable, SIGINT/SIGTERM handling,
``--connect`` / ``--zenoh`` options) with no special case in the CLI. The bus
that :func:`~ovamos.shared.service.run_service` opened is lent to the app; uvicorn
runs on its own thread (it installs no signal handlers off the main thread,
so shutdown stays with run_service) and the app is stopped before the bus
is closed.

Threads: the main thread, once :meth:`GatewayService.start` returned, takes the
bus's inbox (run_service's loop) and so owns the tasks (planner events,
submits, cancels, re-publish rounds: :mod:`ovamos.services.gateway.tasks`); the
``gateway-http`` thread runs uvicorn's event loop; FastAPI's worker threads
run the routes (:mod:`ovamos.services.gateway.routes`). No tick: the gateway is event
driven, and its re-publish timer lives on the event loop. In detail:

- the asyncio event loop (uvicorn's thread) runs the middleware, the error
  handlers, the event streams and the re-publish timer; it never touches the
  store or Zenoh and takes no lock that anything holds across I/O (the
  counters' lock only), so a slow commit cannot stall HTTP or the streams;
- FastAPI's worker threads run the routes that read the store or query Zenoh
  (plain ``def``), and wait there for the owner thread on submit / cancel;
- the bus's inbox taker owns the tasks: planner events, submits, cancels and
  re-publish rounds run there, and it notifies the streams through
  ``loop.call_soon_threadsafe``.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time
from collections import defaultdict
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractContextManager, ExitStack, asynccontextmanager, nullcontext
from typing import Any

import uvicorn
from fastapi import FastAPI

from ovamos.services.gateway.app import http_app
from ovamos.services.gateway.config import GatewayConfig
from ovamos.services.gateway.maps import NoMap
from ovamos.services.gateway.models import ServiceEntry
from ovamos.services.gateway.robots import RobotMonitor
from ovamos.services.gateway.routes import Gateway
from ovamos.services.gateway.sse import TaskWatchers
from ovamos.services.gateway.store import TaskRecord, TaskStore
from ovamos.services.gateway.tasks import Notify, TaskManager
from ovamos.shared import keys
from ovamos.shared.bus import Bus, BusCore, Publisher
from ovamos.shared.bus.status import live_services
from ovamos.shared.messages import MapSnapshot
from ovamos.shared.service import Service, ServiceConfigError, subscribe_robots
from ovamos.shared.topology import TOPOLOGY

__all__ = ["GatewayService", "create_app", "wire", "fetch_snapshot", "alive_services"]

log = logging.getLogger("ovamos.gateway")

BusSource = Callable[[], AbstractContextManager[Bus]]

STARTUP_TIMEOUT_S = 30.0
GRACEFUL_SHUTDOWN_S = 3  # open requests get this long; event streams are ended before it starts


def wire(bus: BusCore, config: GatewayConfig, store: TaskStore, notify: Notify
         ) -> tuple[TaskManager, RobotMonitor]:
    """The gateway's cores on ``bus``: each served robot's declared outputs published, the resume
    queued, then each robot's declared inputs subscribed (so the resume runs ahead of them)."""
    node = TOPOLOGY[GatewayService.name]
    out: dict[tuple[str, str], Publisher[Any]] = {
        (port.name, robot): bus.publisher(port.key(robot), port.message)
        for robot in config.robots for port in node.outputs}
    event_keys = {node.port("inputs", "task_events").key(robot) for robot in config.robots}

    def malformed_events() -> int:
        return sum(c.malformed for key, c in bus.counters.snapshot().items() if key in event_keys)

    manager = TaskManager(store, config, inbox=bus.inbox, notify=notify, log=bus.log,
                          publish=lambda robot, spec: out["task_current", robot].put(spec),
                          record_failure=bus.record_failure, malformed_events=malformed_events)
    monitor = RobotMonitor(config, estop=lambda robot, request: out["estop", robot].put(request),
                           estop_clear=lambda robot, request: out["estop_clear", robot].put(request))
    manager.start()
    subscribe_robots(bus, GatewayService.name, config.robots, {
        "task_events": manager.on_event, "driver_state": monitor.on_driver_state, "odom": monitor.on_odom,
        "plan_trace": monitor.on_plan_trace})
    return manager, monitor


def fetch_snapshot(bus: Bus, robot_id: str, timeout_s: float) -> MapSnapshot:
    """The first valid snapshot a mapping service answers; NoMap when none does (a malformed
    answer is counted by the bus and treated as none). Blocks: for HTTP worker threads."""
    key = TOPOLOGY[GatewayService.name].port("queries", "map_snapshot").key(robot_id)
    snapshot = bus.get(key, MapSnapshot, timeout_s)
    if snapshot is None:
        raise NoMap(f"no map for robot {robot_id!r}: no mapping service answered with a valid map "
                    f"within {timeout_s} s")
    return snapshot


def alive_services(bus: Bus, timeout_s: float) -> dict[str, list[ServiceEntry]]:
    """The service instances holding a liveliness token, by robot (any robot's). Blocks."""
    alive: dict[str, list[ServiceEntry]] = defaultdict(list)
    for s in live_services(bus.session, keys.ANY, timeout_s):
        alive[s.robot_id].append(ServiceEntry(service=s.service, instance=s.instance,
                                              pid=s.stats.pid if s.stats else None))
    return alive


def create_app(config: GatewayConfig, bus_source: BusSource) -> FastAPI:
    """An app serving ``config``; ``bus_source()`` gives the Zenoh bus as a context manager."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        loop = asyncio.get_running_loop()
        with ExitStack() as stack:
            store = TaskStore(config.db_path)
            stack.callback(store.close)
            bus = stack.enter_context(await asyncio.to_thread(bus_source))  # closed before the store
            watchers = TaskWatchers(loop)
            gateway: Gateway | None = None

            def notify(record: TaskRecord) -> None:
                if gateway is not None and watchers.watched(record.id):
                    watchers.publish(gateway.view(record))

            manager, monitor = await asyncio.to_thread(wire, bus, config, store, notify)
            stack.callback(manager.close)  # first: requests still waiting get a 503
            gateway = Gateway(config, store, manager, watchers, monitor,
                              fetch_map=lambda robot: fetch_snapshot(bus, robot, config.map_timeout_s),
                              alive=lambda: alive_services(bus, config.health_timeout_s))
            app.state.gateway = gateway
            republisher = asyncio.create_task(_republish(manager, config.republish_s))
            log.info("gateway serving robots %s, tasks in %s", ", ".join(config.robots), config.db_path)
            try:
                yield
            finally:
                republisher.cancel()
                watchers.close()

    return http_app(config, lifespan)


async def _republish(manager: TaskManager, period_s: float) -> None:
    """Every ``period_s`` (the loop's monotonic clock), queue a re-publish round for the owner
    thread; queueing never blocks, and a failed round is logged and counted there."""
    while True:
        await asyncio.sleep(period_s)
        manager.request_republish()


class GatewayService(Service):
    name = "gateway"
    Config = GatewayConfig
    config: GatewayConfig

    def __init__(self, bus: Bus, config: GatewayConfig) -> None:
        super().__init__(bus, config)
        self.app = create_app(config, lambda: nullcontext(bus))
        self.server = uvicorn.Server(uvicorn.Config(
            self.app, host=config.host, port=config.port, log_config=None, lifespan="on",
            timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S))
        self._socket: socket.socket | None = None
        self._thread = threading.Thread(target=self._serve, name="gateway-http", daemon=True)

    def start(self) -> None:
        """Bind, serve, and return once the app is up (raise when it cannot be).

        The socket is bound here, before uvicorn runs the app's lifespan, so a
        taken port fails at once with the OS's reason, before the gateway has
        touched its task store or published anything.
        """
        self._socket = _bind(self.config.host, self.config.port)
        self._thread.start()
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self.server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise ServiceConfigError(f"the gateway failed to start on {self.config.host}:"
                                         f"{self.config.port} (the log above says why)")
            time.sleep(0.05)
        self.log.info("gateway listening on %s", self.url)

    def _serve(self) -> None:
        assert self._socket is not None
        try:
            self.server.run(sockets=[self._socket])
        except SystemExit as exc:  # uvicorn's way of saying it failed; start() reports it
            self.log.error("the HTTP server exited (%s)", exc.code)

    @property
    def port(self) -> int:
        """The bound port (config port 0 means a free one was picked)."""
        assert self._socket is not None
        return self._socket.getsockname()[1]

    @property
    def url(self) -> str:
        return f"http://{self.config.host}:{self.port}"

    def info(self) -> dict[str, Any]:
        gateway = getattr(self.app.state, "gateway", None)
        return {"url": self.url if self.server.started else None,
                **(gateway.manager.counters() if gateway else {})}

    def stop(self) -> None:
        gateway = getattr(self.app.state, "gateway", None)
        if gateway is not None:
            gateway.manager.close()  # the main thread no longer takes requests: answer them 503
            gateway.watchers.close()
        self.server.should_exit = True
        if self._thread.is_alive():
            self._thread.join(GRACEFUL_SHUTDOWN_S + 10)
        if self._socket is not None:
            self._socket.close()


def _bind(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port``; ServiceConfigError (with the OS's reason) if it cannot be."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # restart while old sockets linger
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise ServiceConfigError(f"the gateway cannot serve on {host}:{port}: {exc.strerror or exc}"
                                 ) from None
    return sock
