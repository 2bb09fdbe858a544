"""``ovamos run gateway``: the HTTP API served by uvicorn inside the common service life cycle.

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
run the routes (:mod:`ovamos.services.gateway.app`). No tick: the gateway is event
driven, and its re-publish timer lives on the event loop.
"""

from __future__ import annotations

import socket
import threading
import time
from contextlib import nullcontext
from typing import Any

import uvicorn

from ovamos.services.gateway.app import create_app
from ovamos.services.gateway.config import GatewayConfig
from ovamos.shared.bus import Bus
from ovamos.shared.service import Service, ServiceConfigError

STARTUP_TIMEOUT_S = 30.0
GRACEFUL_SHUTDOWN_S = 3  # open requests get this long; event streams are ended before it starts


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
