"""The life cycle every service shares: configure, start, one event loop, stop on a signal.

A service subclass holds only its wiring (which of its declared inputs feed
which core methods, see :mod:`ovamos.shared.topology`); the core it wraps knows
nothing of Zenoh. :func:`run_service` is what ``ovamos run SERVICE`` calls,
and what tests and the demo start in a spawned process.

One thread per service (dora's node model): the main thread takes the bus's
events (messages, queries, replies) one at a time and runs the ticks between
them, so a service's state is touched by one thread only and needs no lock.
Zenoh's callbacks only enqueue (:mod:`ovamos.shared.inbox`).
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from ovamos.shared import keys
from ovamos.shared.bus import Bus, BusCore, Publisher
from ovamos.shared.config import ServiceConfig, ServiceConfigError, read_config
from ovamos.shared.topology import TOPOLOGY, Node

if TYPE_CHECKING:  # the bus is what imports zenoh (a contract)
    import zenoh

__all__ = ["Service", "ServiceConfig", "ServiceConfigError", "load_config", "run_loop", "run_service",
           "subscribe_robots"]

log = logging.getLogger("ovamos.service")


class Service:
    """Base class: override :meth:`start`, and :meth:`tick` for periodic work."""

    name: ClassVar[str]
    Config: ClassVar[type[ServiceConfig]] = ServiceConfig
    #: how often :meth:`tick` runs; None = never (purely event-driven services)
    tick_hz: float | None = None

    def __init__(self, bus: BusCore, config: ServiceConfig) -> None:
        self.bus = bus
        self.config = config
        self.log = bus.log
        self.out: dict[str, Publisher[Any]] = {}

    def start(self) -> None:
        """Declare publishers and subscriptions (usually one :meth:`wire` call)."""

    def wire(self, handlers: dict[str, Callable[[Any], None]], *, keep: dict[str, int] | None = None,
             answers: dict[str, Callable[[], Any]] | None = None) -> None:
        """Subscribe ``handlers`` to this service's declared inputs and publish its declared
        outputs as ``self.out[name]`` (:data:`ovamos.shared.topology.TOPOLOGY`).

        The handlers must cover the declared inputs exactly, so a service cannot
        listen to a key the graph does not show. ``keep`` overrides an input's
        declared keep-latest depth (a config setting); ``answers`` serves the
        declared queryables.
        """
        node = _declared_inputs(self.name, handlers)
        if set(answers or {}) != {p.name for p in node.answers}:
            raise ValueError(f"{self.name}: answers {sorted(answers or {})} but the topology declares "
                             f"{sorted(p.name for p in node.answers)}")
        robot = self.bus.robot_id
        for port in node.outputs:
            self.out[port.name] = self.bus.publisher(port.key(robot), port.message)
        for port in node.answers:
            self.bus.queryable(port.key(robot), (answers or {})[port.name])
        for port in node.inputs:
            depth = (keep or {}).get(port.name, port.keep)
            if port.message is None:
                self.bus.subscribe_raw(port.key(robot), handlers[port.name])
            else:
                self.bus.subscribe(port.key(robot), port.message, handlers[port.name], keep=depth)

    def wire_robots(self, robots: Sequence[str], handlers: dict[str, Callable[[str, Any], None]], *,
                    keep: dict[str, int] | None = None) -> None:
        """:meth:`wire` for a service that serves several robots (``robots``; ``["*"]``: every
        robot): ``handlers[name](robot_id, msg)`` gets each robot's inputs, and ``keep`` applies per
        robot. Outputs go to each robot's own key through :meth:`output`."""
        subscribe_robots(self.bus, self.name, robots, handlers, keep=keep)

    def output(self, name: str, robot_id: str) -> Publisher[Any]:
        """The publisher of declared output ``name`` on ``robot_id``'s key (declared on first use)."""
        entry = f"{name}@{robot_id}"
        if entry not in self.out:
            port = TOPOLOGY[self.name].port("outputs", name)
            self.out[entry] = self.bus.publisher(port.key(robot_id), port.message)
        return self.out[entry]

    def tick(self) -> None:
        """Periodic work, called ``tick_hz`` times a second on the service's thread."""

    def info(self) -> dict[str, Any]:
        """Service-specific status shown by ``ovamos status``."""
        return {}

    def stop(self) -> None:
        """Release what :meth:`start` acquired beyond the bus (files, devices)."""


def subscribe_robots(bus: BusCore, name: str, robots: Sequence[str],
                     handlers: dict[str, Callable[[str, Any], None]], *, keep: dict[str, int] | None = None
                     ) -> None:
    """:meth:`Service.wire_robots`'s subscriptions for service ``name`` on any bus, for a program
    that wires one without a :class:`Service` around it (the gateway's app, which may be given a
    bus of its own)."""
    node = _declared_inputs(name, handlers)
    for robot in robots:
        for port in node.inputs:
            handler = handlers[port.name]
            bus.subscribe_keyed(port.key(robot), port.message,
                                lambda key, msg, handler=handler: handler(keys.robot_of(key), msg),
                                keep=(keep or {}).get(port.name, port.keep))


def _declared_inputs(name: str, handlers: dict[str, Any]) -> Node:
    """Service ``name``'s node, once ``handlers`` cover its declared inputs exactly (a service cannot
    listen to a key the graph does not show)."""
    node = TOPOLOGY[name]
    declared = {p.name for p in node.inputs}
    if set(handlers) != declared:
        raise ValueError(f"{name}: handlers for {sorted(handlers)} but the topology declares "
                         f"inputs {sorted(declared)}")
    return node


def load_config(cls: type[Service], path: str | Path | None, overrides: dict[str, Any] | None = None
                ) -> ServiceConfig:
    """Read a service config (TOML or JSON) and validate it against the service's model."""
    return read_config(cls.Config, path, overrides, what=f"config for {cls.name}")


def install_signal_handlers(stop: threading.Event) -> None:
    """SIGINT / SIGTERM end the run gracefully. Python allows handlers only in the main
    thread; elsewhere (a service run in a thread by tests or an embedding program) the
    caller stops it through ``stop``."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())


def run_service(cls: type[Service], zenoh_config: zenoh.Config, config: ServiceConfig, *,
                robot_id: str, instance: str, stop: threading.Event) -> None:
    """Run one service instance until ``stop`` is set, then shut it down cleanly.

    SIGINT / SIGTERM set ``stop`` once the session is open; while it still
    waits for a router they end the process at once, as there is nothing to
    clean up yet (a Python handler would not run during Zenoh's blocking open).
    """
    svc: Service | None = None
    bus = Bus.open(zenoh_config, robot_id, cls.name, instance, dispatch="caller")
    install_signal_handlers(stop)
    try:
        svc = cls(bus, config)
        svc.start()
        log.info("%s/%s up on robot %s", cls.name, instance, robot_id)
        run_loop(svc, stop)
    finally:
        if svc is not None:
            svc.stop()
        bus.close()
        log.info("%s/%s stopped", cls.name, instance)


INFO_EVERY_S = 0.5


def run_loop(svc: Service, stop: threading.Event) -> None:
    """The service's event loop: its bus's events as they come, its tick every 1/tick_hz s, and
    its :meth:`Service.info` copied to the bus every ``INFO_EVERY_S`` (for stats queries)."""
    now = time.monotonic()
    next_tick, next_info = now, now
    while not stop.is_set():
        now = time.monotonic()
        if now >= next_info:
            _refresh_info(svc)
            next_info = now + INFO_EVERY_S
        due = next_info if svc.tick_hz is None else min(next_tick, next_info)
        svc.bus.inbox.run_until(due, stop)
        if stop.is_set() or svc.tick_hz is None or time.monotonic() < next_tick:
            continue
        _tick(svc)
        next_tick = max(next_tick + 1.0 / svc.tick_hz, time.monotonic())


def _refresh_info(svc: Service) -> None:
    try:
        svc.bus.info = svc.info()
    except Exception:
        svc.bus.record_failure("info")


def _tick(svc: Service) -> None:
    """One tick; a failing tick is logged and counted, the service keeps running."""
    try:
        svc.tick()
    except Exception:
        svc.bus.record_failure("tick")
