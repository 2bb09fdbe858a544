"""The life cycle every service shares: configure, start, tick, stop on a signal.

A service subclass holds only its wiring (which keys feed which core methods);
the core it wraps knows nothing of Zenoh. :func:`run_service` is what
``ovamos run SERVICE`` calls, and what tests and the demo start in a spawned
process.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any, ClassVar

import zenoh
from shared.bus import Bus
from shared.config import ServiceConfig, ServiceConfigError, read_config

__all__ = ["Service", "ServiceConfig", "ServiceConfigError", "load_config", "run_service"]

log = logging.getLogger("ovamos.service")


class Service:
    """Base class: override :meth:`start`, and :meth:`tick` for periodic work."""

    name: ClassVar[str]
    Config: ClassVar[type[ServiceConfig]] = ServiceConfig
    #: how often :meth:`tick` runs; None = never (purely event-driven services)
    tick_hz: float | None = None

    def __init__(self, bus: Bus, config: ServiceConfig) -> None:
        self.bus = bus
        self.config = config
        self.log = bus.log

    def start(self) -> None:
        """Declare publishers and subscriptions."""

    def tick(self) -> None:
        """Periodic work, called ``tick_hz`` times a second from the main thread."""

    def info(self) -> dict[str, Any]:
        """Service-specific status shown by ``ovamos status``."""
        return {}

    def stop(self) -> None:
        """Release what :meth:`start` acquired beyond the bus (files, devices)."""


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
    bus = Bus.open(zenoh_config, robot_id, cls.name, instance, info=lambda: svc.info() if svc else {})
    install_signal_handlers(stop)
    try:
        svc = cls(bus, config)
        svc.start()
        log.info("%s/%s up on robot %s", cls.name, instance, robot_id)
        if svc.tick_hz is None:
            stop.wait()
        next_tick = time.monotonic()
        while not stop.is_set():
            _tick(svc)
            next_tick = max(next_tick + 1.0 / svc.tick_hz, time.monotonic())
            stop.wait(next_tick - time.monotonic())
    finally:
        if svc is not None:
            svc.stop()
        bus.close()
        log.info("%s/%s stopped", cls.name, instance)


def _tick(svc: Service) -> None:
    """One tick; a failing tick is logged and counted, the service keeps running."""
    try:
        svc.tick()
    except Exception:
        svc.bus.record_failure("tick")
